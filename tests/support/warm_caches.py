"""Fills the caches a test run shares, once, before `make pytest` starts its workers (`python -m
tests.support.warm_caches`).

On a fresh clone every cache is cold, and each pytest-xdist worker (and each process a test starts) would fill it
again, at the same moment as the others:

- numba's compiled kernels (``cache=True``, on disk beside their modules): importing a module compiles the kernels it
  warms at import; the MCAP frame kernel is compiled at its first batch, so one batch is written here;
- the byte code of the installed packages (``make``'s ``uv`` bootstrap does not byte-compile them: a module is
  compiled when it is first imported, and most never are) and pytest's rewritten test modules: one collection
  imports every test module and what it imports, and writes both.

Nothing here is a test: a collection error fails this step as it would fail the run.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import sys

import pytest

#: the modules whose kernels are compiled (or loaded from numba's cache) when they are imported (the design's own
#: kernels too: lifted_kernel alone is about 10 CPU-s to compile, which each worker otherwise spent at once, in
#: whichever test first reached a NOILC or gradient design)
KERNEL_MODULES = ("foilc_hil.design.fractional", "foilc_hil.design.gl_kernel", "foilc_hil.design.lifted_kernel",
                  "foilc_hil.design.rational_map", "foilc_hil.laws.kernels", "foilc_hil.loop.trial_kernel",
                  "plant_emulator.physics.kernels", "plant_emulator.physics.trial")


def _first_calls() -> None:
    """The kernels that compile at their first call, not at import (the design's lifted, rational-map and
    Grunwald-Letnikov kernels): one short offline run of each law on the paper's plant calls them with the types
    the tests use (numba specialises on types, not sizes). Cold, each worker compiled them at once, inside a test
    (a NOILC certificate test took 22 s on a fresh clone, 0.15 s warm)."""
    from foilc_hil.config import load_config
    from foilc_hil.loop.simulation import simulate

    config = load_config("configs/paper_sim.yaml")
    for law in ("foilc", "ioilc", "p-type", "noilc", "gradient"):
        simulate(config, law=law, trials=1)


def main() -> int:
    """Compile the kernels and collect the tests; pytest's exit code of the collection."""
    for name in KERNEL_MODULES:
        importlib.import_module(name)
    _first_calls()
    listing = io.StringIO()  # the 1,500 test ids: not wanted on make's output
    with contextlib.redirect_stdout(listing):
        code = pytest.main(["--collect-only", "-q", "-p", "no:cacheprovider"])
    if code != pytest.ExitCode.OK:
        sys.stdout.write(listing.getvalue())
    return int(code)


if __name__ == "__main__":
    sys.exit(main())
