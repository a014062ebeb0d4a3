"""Evaluation: metrics (pure NumPy), reports and plots."""
