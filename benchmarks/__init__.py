"""Benchmarks, run from the repository root: `python -m benchmarks.bench --help`. Not part of the installed package."""
