"""Gymnasium environments over the simulated lab."""
