"""``make bench``: physics, simulate, logging, science and bench-loop benchmarks in one run, peers side by side;
writes one JSON document (``--out``, default stdout) and, with ``--doc``, renders it into ``docs/benchmarks.md``
(:mod:`benchmarks.report`).

``python -m benchmarks.run --out benchmarks/results.json --doc docs/benchmarks.md``
"""

from __future__ import annotations

import datetime
import os
import platform
from collections.abc import Sequence
from typing import Any

from benchmarks.comparison import Comparison, Figure, comparisons_json
from benchmarks.output import emit, json_parser


def _median_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The run with the median cycles/s, plus every run's cycles/s (the machine is shared: spread matters)."""
    ordered = sorted(runs, key=lambda run: run["cycles_per_second"] or 0.0)
    median = dict(ordered[len(ordered) // 2])
    median["cycles_per_second_all_runs"] = [run["cycles_per_second"] for run in runs]
    return median


def _lockstep(repeats: int) -> tuple[dict[str, Any], Comparison]:
    """Lockstep over the embedded emulator without and with the MCAP log, alternated; the logging-loss row."""
    from benchmarks import bench_loop

    bench_loop.can_lockstep(logged=False, trials=1)  # warm-up: imports, EDS parsing, first design
    no_log: list[dict[str, Any]] = []
    logged: list[dict[str, Any]] = []
    # at least 7 pairs: the goal is a 10 % difference, and a run's rate moves by 10 to 20 % from one run to the next
    # on this shared machine (runs of 0.3 s each; interleaved, logged ones were faster than unlogged ones as often)
    for _ in range(max(repeats, 7)):  # alternate, so a load spike on the shared machine hits both alike
        no_log.append(bench_loop.can_lockstep(logged=False))
        logged.append(bench_loop.can_lockstep(logged=True))
    row = Comparison(
        target="CAN lockstep throughput with every frame and sample logged",
        unit="cycles/s",
        higher_is_better=True,
        project=Figure(tuple(run["cycles_per_second"] for run in logged)),
        peer=Figure(tuple(run["cycles_per_second"] for run in no_log)),
        peer_name="the same loop without logging",
        min_ratio=0.9,
        note="goal: under 10 % lost to logging (ratio >= 0.9). The log is written by a child process "
        "(foilc_hil.io.log_process): the loop's process packs one tuple per frame, one item of float64 columns per "
        "trial for the samples, and one marshal batch per 128 items; the JSON and the file are the child's "
        "(SCHED_BATCH, reading the pipe on its own clock: the loop's writes never wake it), on the other core. On a "
        "loaded 2-core machine there is no idle core for the child, and the spread is wide",
    )
    return {"without_logging": _median_run(no_log), "with_logging": _median_run(logged)}, row


def collect(repeats: int = 3) -> dict[str, Any]:
    import tempfile
    from pathlib import Path

    from benchmarks import (
        bench_axes,
        bench_design_grid,
        bench_foxglove_writer,
        bench_live,
        bench_lockstep,
        bench_logging,
        bench_loop,
        bench_physics,
        bench_profile,
        bench_science,
        bench_simulate,
    )
    from benchmarks.bench_robustness import robustness_comparisons

    started_load = os.getloadavg()[0]
    date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M")
    physics = bench_physics.physics_comparisons(repeats=max(repeats, 5))
    simulated = bench_simulate.simulate_comparisons(repeats)
    lockstep, lockstep_row = _lockstep(repeats)
    # at least 5: the judged row's rate moved 8,500..12,800 cycles/s within one run of 3 (a 10,000 goal)
    lockstep_peer, lockstep_rows = bench_lockstep.collect(max(repeats, 5))
    lockstep_profile = bench_profile.collect(repeats)
    science_rows = bench_science.science_comparisons(repeats)
    design_grid = bench_design_grid.collect()  # issue 26: every law x Q-filter x N, in process
    robustness = robustness_comparisons()  # root: Dask's loopback TCP inside `unshare --net`
    axes, axes_rows = bench_axes.collect(repeats)
    # at least 11 pairs: the ratio's pairs spread 0.4x..1.7x at a load of 8-9 on 2 cores (a goal of 0.9x)
    live, live_row = bench_live.live_comparison(max(repeats, 11))  # root: a private network namespace
    with tempfile.TemporaryDirectory() as directory:
        logging_costs = bench_logging.per_call_costs(Path(directory))
        # at least 5: this row's ratio was 1.20x, 1.33x and 0.95x in three runs of 3 (a goal of 1x)
        writers = bench_logging.writer_comparisons(Path(directory), repeats=max(repeats, 5))
        # issue 29 target 5: ours against foxglove-sdk's MCAPWriter on the same documents (the faster one stays)
        foxglove_writer, foxglove_rows = bench_foxglove_writer.writer_comparisons(Path(directory), max(repeats, 5))
    return {
        "date": date,
        "repeats": repeats,
        "machine": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "load_average_1min": started_load,
        },
        "comparisons": comparisons_json(
            [*physics, *simulated, lockstep_row, live_row, *lockstep_rows, *axes_rows, *writers, *foxglove_rows,
             *science_rows, *robustness]
        ),
        "physics": {"jit": bench_physics.jit_cost()},
        "logging_per_call": logging_costs,
        "science": bench_science.collect(),
        "loop_only": bench_loop.loop_only(),
        "can_lockstep_virtual": lockstep,
        # the same logged lockstep run with and without --live (a viewer process subscribed to every channel)
        "live_view": live,
        "foxglove_writer": foxglove_writer,
        # foilc-hil run on the embedded emulator (in-process transport and, for contrast, python-can virtual
        # buses), first-order and PMSM plant, against a hand-written python-can lockstep loop, interleaved
        "lockstep_vs_handwritten": lockstep_peer,
        # where each microsecond of a lockstep cycle goes, on main before the lean cyclic path and now
        "lockstep_profile": lockstep_profile,
        # axes: runs of 1, 2 and 4 axes against the single-axis run, and the bus load of a 4-axis log
        "axes": axes,
        "design_grid": design_grid,
        "load_average_end": os.getloadavg()[0],
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = json_parser("python -m benchmarks.run", __doc__)
    parser.add_argument("--doc", help="also render the results into this Markdown file (docs/benchmarks.md)")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions of each figure (default 3)")
    args = parser.parse_args(argv)
    results = collect(args.repeats)
    emit(results, args.out)
    if args.doc:
        from pathlib import Path

        from benchmarks.report import render

        Path(args.doc).write_text(render(results), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
