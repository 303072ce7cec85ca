"""``make bench``: science (fractional derivative, LMI solvers), logging and bench-loop benchmarks in one JSON document
(``--out``, default stdout); peers run side by side in the same process.

``python -m benchmarks.run --out benchmarks/results.json``
"""

from __future__ import annotations

import os
import platform
from collections.abc import Sequence
from typing import Any

from benchmarks.output import emit, json_parser


def _median_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The run with the median cycles/s, plus every run's cycles/s (the machine is shared: spread matters)."""
    ordered = sorted(runs, key=lambda run: run["cycles_per_second"] or 0.0)
    median = dict(ordered[len(ordered) // 2])
    median["cycles_per_second_all_runs"] = [run["cycles_per_second"] for run in runs]
    return median


def collect(repeats: int = 3) -> dict[str, Any]:
    import tempfile
    from pathlib import Path

    from benchmarks import bench_lockstep, bench_logging, bench_loop, bench_science

    bench_loop.can_lockstep(logged=False, trials=1)  # warm-up: imports, EDS parsing, first design
    no_log: list[dict[str, Any]] = []
    logged: list[dict[str, Any]] = []
    for _ in range(repeats):  # alternate, so a load spike on the shared machine hits both alike
        no_log.append(bench_loop.can_lockstep(logged=False))
        logged.append(bench_loop.can_lockstep(logged=True))
    without, with_log = _median_run(no_log), _median_run(logged)
    with tempfile.TemporaryDirectory() as directory:
        logging_costs = bench_logging.per_call_costs(Path(directory))
    return {
        "logging_per_call": logging_costs,
        "machine": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "load_average_1min": os.getloadavg()[0],
        },
        "science": bench_science.collect(),
        "loop_only": bench_loop.loop_only(),
        # foilc-hil run on the embedded emulator (in-process transport and, for contrast, python-can virtual
        # buses), first-order and PMSM plant, against a hand-written python-can lockstep loop, interleaved
        "lockstep_vs_handwritten": bench_lockstep.collect(repeats),
        "can_lockstep_virtual": {
            "without_logging": without,
            "with_logging": with_log,
            "logging_overhead_compute_p50_us": (
                with_log["compute_p50_us"] - without["compute_p50_us"]
                if with_log["compute_p50_us"] is not None and without["compute_p50_us"] is not None
                else None
            ),
        },
    }


def main(argv: Sequence[str] | None = None) -> int:
    args = json_parser("python -m benchmarks.run", __doc__).parse_args(argv)
    emit(collect(), args.out)
    return 0

if __name__ == "__main__":
    raise SystemExit(main())
