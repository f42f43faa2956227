"""Clutter statistics: distributions, their fits and tail quantiles (log-cumulants, mixtures, CGGD,
circular statistics, the equivalent number of looks, the measured fit of a detector's model)."""
