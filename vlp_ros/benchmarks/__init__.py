"""Measurement scripts that print tables: accuracy against ground truth and speed against a reference."""
