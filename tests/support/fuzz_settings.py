"""Bounds shared by the fuzz tests (``tests/test_fuzz_*.py``, ``docs/fuzzing.md``).

``make test`` runs each fuzz test with a small number of examples so all of them together stay well under 25 s
on a loaded two-core machine. ``FOILC_FUZZ_EXAMPLES=N`` multiplies nothing and guesses nothing: it sets every fuzz
test's example count to ``N`` for a longer run by hand (the numbers of one such run are in ``docs/fuzzing.md``).
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings


def fuzz_settings(examples: int) -> settings:
    """Settings for one fuzz test: ``examples`` in ``make test``, ``FOILC_FUZZ_EXAMPLES`` when set."""
    override = os.environ.get("FOILC_FUZZ_EXAMPLES")
    return settings(
        max_examples=int(override) if override else examples,
        # each example writes a file into tmp_path or reuses one emulator: that sharing is the point, not a bug
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                               HealthCheck.data_too_large],
    )
