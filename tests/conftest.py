"""Shared test settings.

Hypothesis runs without per-example deadlines: these machines are shared and noisy, and a deadline is a timing
assertion in disguise. Under CI (``CI`` set) examples are derandomised so a run is reproducible.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("default", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")
