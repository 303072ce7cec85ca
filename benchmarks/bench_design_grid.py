"""Certified design at scale (issue 26): every law, every Q-filter, long trials, in process.

For each law (foilc, ioilc, p-type, noilc, gradient), each Q-filter (none; zero-phase and causal Butterworth of
orders 1, 2 and 4 at cutoffs from 2 % to 45 % of Nyquist) and each trial length (N = 2,000, 6,000, 20,000 samples of
the demo's PMSM axis at 1 ms, its eq. (52) profile stretched or cut to length), one in-process
``foilc_hil.design.pipeline.build_design`` with the CAN loop's one-cycle delay: its seconds, what its certificate
proves (the certified induced 2-norm of the trial-to-trial map at the worst plant, the spectral radius, monotone or
not, the method), or the refusal (exit 3) and its bound. The goals: 2 s at N = 6,000 and 8 s at N = 20,000.

Nothing here asserts a time. ``python -m benchmarks.bench_design_grid [--out F.json] [--quick] [--full]``.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from benchmarks.output import emit, json_parser

LAWS = ("foilc", "ioilc", "p-type", "noilc", "gradient")
LENGTHS = (2000, 6000, 20000)
#: (order, fraction of Nyquist, phase); None: no Q-filter. ``make bench`` runs :data:`BENCH_FILTERS`, ``--full``
#: every one (a design at N = 20,000 takes seconds: the whole grid is tens of minutes on 2 cores)
FILTERS: tuple[tuple[int, float, str] | None, ...] = (
    None,
    (1, 0.45, "zero"),
    (2, 0.20, "zero"),
    (4, 0.05, "zero"),
    (2, 0.02, "causal"),
    (4, 0.20, "causal"),
)
BENCH_FILTERS = (None, (2, 0.20, "zero"), (2, 0.02, "causal"))
#: seconds the issue allows a design at this N
GOALS = {6000: 2.0, 20000: 8.0}


@dataclass(frozen=True)
class Cell:
    """One design of the grid."""

    law: str
    filter: str
    n_samples: int
    seconds: float
    outcome: str  # "monotone", "asymptotic", "refused", "failed"
    norm_2: float | None
    spectral_radius: float | None
    method: str

    def to_json(self) -> dict[str, Any]:
        return {"law": self.law, "filter": self.filter, "n_samples": self.n_samples, "seconds": self.seconds,
                "outcome": self.outcome, "norm_2": self.norm_2, "spectral_radius": self.spectral_radius,
                "method": self.method, "goal_s": GOALS.get(self.n_samples)}


def _filter_name(spec: tuple[int, float, str] | None) -> str:
    return "none" if spec is None else f"order {spec[0]}, {spec[1]:.0%} Nyquist, {spec[2]}"


def _config(spec: tuple[int, float, str] | None, n_samples: int) -> Any:
    from foilc_hil.config import load_config

    base = load_config("configs/demo.yaml")
    nyquist = math.pi / base.sample_time
    # the demo's eq. (52) profile is 6 s at 1 ms: stretched in time to the grid's length
    overrides: dict[str, Any] = {"reference.time_scale": n_samples * base.sample_time / 6.0}
    if spec is not None:
        overrides["law.q_filter"] = {"order": spec[0], "cutoff": spec[1] * nyquist, "phase": spec[2]}
    return load_config("configs/demo.yaml", overrides)


def _cell(law: str, spec: tuple[int, float, str] | None, n_samples: int) -> Cell:
    from foilc_hil.design.pipeline import build_design
    from foilc_hil.errors import FoilcHilError, InfeasibleDesignError

    config = _config(spec, n_samples)
    started = time.perf_counter()
    try:
        design = build_design(config, law, n_samples, input_delay=1)
    except InfeasibleDesignError as exc:
        return Cell(law, _filter_name(spec), n_samples, time.perf_counter() - started, "refused", None, None,
                    str(exc).splitlines()[0][:160])
    except FoilcHilError as exc:
        return Cell(law, _filter_name(spec), n_samples, time.perf_counter() - started, "failed", None, None,
                    str(exc).splitlines()[0][:160])
    seconds = time.perf_counter() - started
    certificates = design.certificates
    if certificates is None:
        return Cell(law, _filter_name(spec), n_samples, seconds, "uncertified", None, None, "")
    # the method's name, without each plant's figures (those are the certificate's, in the design record)
    methods = sorted({re.sub(r"\s*\(([^:;()]*)[:;].*", r" (\1)", plant.norm_2_method) for plant in certificates.plants})
    outcome = "monotone" if certificates.monotonic else "asymptotic" if certificates.asymptotic else "refused"
    return Cell(law, _filter_name(spec), n_samples, seconds, outcome, certificates.norm_2,
                certificates.spectral_radius, "; ".join(methods))


def cells(laws: Sequence[str] = LAWS, lengths: Sequence[int] = LENGTHS,
          filters: Sequence[tuple[int, float, str] | None] = FILTERS) -> Iterator[Cell]:
    """Every cell of the grid, one design each, in law, filter, length order."""
    for law in laws:
        for spec in filters:
            for n_samples in lengths:
                yield _cell(law, spec, n_samples)


def collect(quick: bool = False, full: bool = False) -> dict[str, Any]:
    """The grid as a JSON document (``quick``: N = 2,000 only; ``full``: every filter of :data:`FILTERS`)."""
    for law in LAWS:  # warm-up: imports, compiled kernels and the solvers' first calls, not timed in the table
        _cell(law, None, 2000)
    lengths = (2000,) if quick else LENGTHS
    grid = [cell.to_json() for cell in cells(LAWS, lengths, FILTERS if full else BENCH_FILTERS)]
    within = [cell for cell in grid if cell["goal_s"] is not None]
    met = sum(1 for cell in within if cell["seconds"] <= cell["goal_s"])
    return {"plant": "configs/demo.yaml (PMSM axis at 1 ms)", "cells": grid,
            "goal_cells": len(within), "goal_met": met}


def table(document: dict[str, Any]) -> list[str]:
    """The grid as Markdown rows (docs/benchmarks.md)."""
    lines = ["| law | Q-filter | N | seconds | goal | outcome | certified 2-norm | spectral radius | method |",
             "|---|---|---|---|---|---|---|---|---|"]
    for cell in document["cells"]:
        goal = cell["goal_s"]
        met = "" if goal is None else (f"{goal:g} s: met" if cell["seconds"] <= goal else f"{goal:g} s: MISSED")
        norm = "" if cell["norm_2"] is None else f"{cell['norm_2']:.4g}"
        radius = "" if cell["spectral_radius"] is None else f"{cell['spectral_radius']:.4g}"
        lines.append(f"| {cell['law']} | {cell['filter']} | {cell['n_samples']} | {cell['seconds']:.2f} | {met} | "
                     f"{cell['outcome']} | {norm} | {radius} | {cell['method']} |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = json_parser("python -m benchmarks.bench_design_grid", __doc__)
    parser.add_argument("--quick", action="store_true", help="N = 2,000 only")
    parser.add_argument("--full", action="store_true", help="every filter (orders 1, 2, 4; both phases)")
    args = parser.parse_args(argv)
    emit(collect(args.quick, args.full), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
