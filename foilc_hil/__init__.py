"""foilc-hil: two-dimensional fractional-order iterative learning control on a CAN hardware-in-the-loop bench.

The public Python API (``docs/api.md``; the reference is built by ``make docs``) is the names of :data:`__all__`,
imported on first use (PEP 562): ``import foilc_hil`` itself imports nothing else, so it stays cheap.

>>> import foilc_hil as fh
>>> cfg = fh.load_config("configs/demo.yaml", overrides={"trials": 3})       # doctest: +SKIP
>>> with fh.Bench(cfg, design=fh.design(cfg), out="run.mcap") as bench:     # doctest: +SKIP
...     for trial in bench.trials(3):
...         print(trial.index, trial.sse)
>>> log = fh.open_log("run.mcap")                                          # doctest: +SKIP

Every other module and name is internal. Layering (imports point downwards only; ``tests/project/test_layering.py``
enforces it):

0. ``drivers`` -- the CAN side of a drive: CiA 301/402 protocol, object dictionary, PDO codecs, the master; the
   root of the error tree (``drivers.errors``) and the config sections' base (``drivers.schema``).
1. ``plant_emulator`` -- plant physics (the one physics code path) and the virtual CiA 402 drive.
2. ``foilc_hil.errors``, ``foilc_hil.schema`` -- the error hierarchy and config toolkit under one name (re-exported
   from layers 0 and 1, plus the control stack's errors).
3. the rest of ``foilc_hil`` -- control science, bench loop, logging, CLI; this package's top (the API) above it.

Layers 0 and 1 import nothing of ``foilc_hil``: a script uses the master or the emulator without the control stack.
"""

from __future__ import annotations

import importlib
import sys
import types

# typing.TYPE_CHECKING without importing typing (a fifth of this module's cold import): mypy reads any constant of
# that name as true
TYPE_CHECKING = False
if TYPE_CHECKING:
    from typing import Any

    from foilc_hil import errors
    from foilc_hil.api.bench import Bench, design, load_config, simulate
    from foilc_hil.api.log import Log, open_log
    from foilc_hil.api.results import TrialResult
    from foilc_hil.config import Config
    from foilc_hil.design.record import Design

__version__ = "0.1.0"

__all__ = [
    "Bench",
    "Config",
    "Design",
    "Log",
    "TrialResult",
    "__version__",
    "design",
    "errors",
    "load_config",
    "open_log",
    "simulate",
]

#: where each public name is defined
_SOURCES = {
    "Bench": "foilc_hil.api.bench",
    "design": "foilc_hil.api.bench",
    "simulate": "foilc_hil.api.bench",
    "Log": "foilc_hil.api.log",
    "open_log": "foilc_hil.api.log",
    "TrialResult": "foilc_hil.api.results",
    "Config": "foilc_hil.config",
    "load_config": "foilc_hil.api.bench",
    "Design": "foilc_hil.design.record",
}


def __getattr__(name: str) -> Any:
    """A public name, imported from its module on first use and kept (PEP 562)."""
    if name == "errors":
        return importlib.import_module("foilc_hil.errors")
    source = _SOURCES.get(name)
    if source is None:
        raise AttributeError(f"module 'foilc_hil' has no attribute {name!r}")
    value = getattr(importlib.import_module(source), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


class _Package(types.ModuleType):
    """This package's module type: the function :func:`design` keeps its name against the subpackage of the same
    name. Why: importing ``foilc_hil.design.*`` makes the import system set the subpackage as this package's
    attribute ``design``, which would replace ``fh.design`` by a module; imports of the subpackage are unaffected
    (they go through ``sys.modules``)."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "design" and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
