"""Metrics and evaluation protocols (the only place scores are computed)."""
