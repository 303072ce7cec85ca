"""``drivers`` and ``plant_emulator`` stand alone at run time too: importing them loads nothing of ``foilc_hil``
(``tests/project/test_layering.py`` checks the source; this checks what a fresh interpreter actually loads), and the
names ``foilc_hil`` re-exports from them are the same objects."""

from __future__ import annotations

import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import drivers
import drivers.schema
import drivers.timing
import drivers.yaml_document
import foilc_hil.schema
import plant_emulator.device
import plant_emulator.matrix

ROOT = Path(__file__).resolve().parents[2]


def loaded_by(modules: list[str]) -> list[str]:
    """The ``foilc_hil`` modules a fresh interpreter has loaded after importing ``modules``."""
    probe = ("import importlib, json, sys\n"
             f"for name in {modules!r}: importlib.import_module(name)\n"
             "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] == 'foilc_hil')))")
    child = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, timeout=120,
                           check=False)
    assert child.returncode == 0, child.stderr
    return list(json.loads(child.stdout.splitlines()[-1]))


@pytest.mark.slow
def test_every_drivers_module_imports_without_foilc_hil() -> None:
    modules = [info.name for info in pkgutil.iter_modules(drivers.__path__, "drivers.")]
    assert "drivers.cia402_master" in modules and "drivers.errors" in modules
    assert loaded_by(modules) == []


def test_the_probe_sees_foilc_hil() -> None:
    """Not blind: importing a foilc_hil module is reported."""
    assert "foilc_hil.errors" in loaded_by(["foilc_hil.errors"])


@pytest.mark.slow
def test_the_emulator_imports_without_foilc_hil() -> None:
    assert loaded_by(["plant_emulator.embedded", "plant_emulator.cli"]) == []


def test_re_exports_are_the_same_objects() -> None:
    assert plant_emulator.device.TimingMode is drivers.timing.TimingMode
    assert foilc_hil.schema.Section is drivers.schema.Section
    assert foilc_hil.schema.validate is drivers.schema.validate
    assert foilc_hil.schema.load_document is drivers.yaml_document.load_document
    assert foilc_hil.schema.Matrix is plant_emulator.matrix.Matrix
    assert foilc_hil.schema.as_array is plant_emulator.matrix.as_array
