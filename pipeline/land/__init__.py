"""Land masks: amplitude texture, the GSHHG coastline, and masks a user supplies as files."""
