"""Calibration solving: models, robust solve, projection uncertainty, model choice and verdict."""
