"""Tests of ``benchmarks/``: the figures, reports and verdicts of ``make bench`` and ``make bench-realtime``."""
