"""Reproducible benchmarks; JSON out, peers side by side (see benchmarks/run.py)."""
