"""Tiles and windows: halo geometry, tiling-invariant window sums, what a detector reads per tile,
and the absent (no-data) pixels of a block."""
