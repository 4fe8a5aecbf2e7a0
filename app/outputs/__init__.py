"""Everything written to disk: calibration files other tools read, and pictures a person reads."""
