"""``--log-level``: the product's diagnostics at the chosen level; canopen's and python-can's only at debug."""

from __future__ import annotations

import logging
import subprocess
import sys

import pytest

from foilc_hil.cli import LogLevel, _configure_logging


@pytest.fixture(autouse=True)
def _restore_levels() -> object:
    names = ("foilc_hil", "drivers", "plant_emulator", "canopen", "can")
    before = {name: logging.getLogger(name).level for name in names}
    yield
    for name, level in before.items():
        logging.getLogger(name).setLevel(level)


@pytest.mark.parametrize("level", list(LogLevel))
def test_levels(level: LogLevel) -> None:
    _configure_logging(level)
    numeric = getattr(logging, level.name)
    assert logging.getLogger("drivers.cia402_master").getEffectiveLevel() == numeric
    library = logging.getLogger("canopen.sdo.client").getEffectiveLevel()
    assert library == (numeric if level is LogLevel.DEBUG else logging.CRITICAL)


@pytest.mark.slow
def test_a_bad_level_is_a_usage_error() -> None:
    done = subprocess.run([sys.executable, "-m", "foilc_hil.cli", "--log-level", "loud", "synthesize"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--log-level" in lines[0]
