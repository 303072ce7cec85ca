"""Several axes on one bus (``axes:``, configs/scara_4axis.yaml) in lockstep, and the bus load its log shows.

``axis_cycles``
    Lockstep ``foilc-hil run`` of the first 1, 2 and 4 axes of configs/scara_4axis.yaml on the embedded emulator
    (one trial loop, one SYNC per cycle for all axes, :mod:`foilc_hil.loop.axes`): cycles/s (the bench's own count
    over its loop, ``TimingSummary``) times the number of axes, against the peer: the first axis alone (its config
    without ``axes:``; the same rig, :func:`foilc_hil.loop.rig.run_rig`, with one member), interleaved in the same
    run. Above 1: one loop over several axes moves more axis-cycles per second than one single-axis loop.
``bus_load``
    The load a 4-axis run's log shows -- the exact wire bits (:func:`benchmarks.can_wire.wire_bits`: stuff bits,
    interframe space) of every frame between two consecutive SYNCs of the loop, averaged over its periods, at
    1 Mbit/s and ``sample_time`` -- against the worst-case figure ``run`` computes before it starts
    (:func:`foilc_hil.commands.run.check_bus_load`). Above 1: the computed bound holds (it counts a heartbeat of
    every producer at its worst phase; the measured periods carry them only where they fall).

Nothing here asserts a time. ``python -m benchmarks.bench_axes [--repeats N] [--out F.json]``.
"""

from __future__ import annotations

import statistics
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks.comparison import Comparison, Figure
from benchmarks.output import emit, json_parser

SCARA = Path(__file__).resolve().parents[1] / "configs" / "scara_4axis.yaml"
AXES = (1, 2, 4)
TRIALS = 2


def _config(n_axes: int) -> Any:
    from foilc_hil.config import load_config

    config = load_config(SCARA)
    return config.model_copy(update={"axes": config.axes[:n_axes]})


def axes_run(n_axes: int, out: Path | None = None) -> float:
    """Cycles/s of one lockstep run of the first ``n_axes`` axes (``run_rig``); ``out``: also write its log."""
    from foilc_hil.loop.rig import RunRequest, run_rig

    report = run_rig(RunRequest(config=_config(n_axes), out=out, trials=TRIALS, quiet=True))
    return _rate(report.outcome.timing)


def single_axis_run() -> float:
    """Cycles/s of the first axis alone (its single-axis config, no ``axes:``)."""
    from foilc_hil.config import axis_configs
    from foilc_hil.loop.rig import RunRequest, run_rig

    first = axis_configs(_config(1))[0]
    return _rate(run_rig(RunRequest(config=first, out=None, trials=TRIALS, quiet=True)).outcome.timing)


def _rate(timing: Any) -> float:
    if timing is None or timing.cycles_per_second is None:
        raise RuntimeError("the run returned no timing summary")
    return float(timing.cycles_per_second)


def measured_load(log: Path, bitrate: int, period: float) -> float:
    """Wire bits per SYNC period of the log's loop (periods carrying every axis's RPDO1), over ``bitrate x period``."""
    from benchmarks.can_wire import wire_bits
    from drivers.cia301 import SYNC_COB_ID, FunctionCode, cob_id
    from foilc_hil.io.mcap_log import frame_to_message, read_log

    periods: list[list[Any]] = []
    for frame in read_log(log).frames:
        if frame["id"] == SYNC_COB_ID and frame["dir"] == "tx":
            periods.append([])
        if periods:
            periods[-1].append(frame_to_message(frame))
    rpdos = {cob_id(FunctionCode.RPDO1, node) for node in range(1, 5)}
    loop = [period for period in periods if rpdos <= {msg.arbitration_id for msg in period}]
    if not loop:
        raise RuntimeError(f"{log}: no SYNC period carries every axis's RPDO1")
    return statistics.fmean(sum(wire_bits(msg) for msg in period) for period in loop) / (bitrate * period)


def collect(repeats: int = 3) -> tuple[dict[str, Any], list[Comparison]]:
    """Every figure ``repeats`` times, the runs interleaved; returns the JSON summary and the comparison rows."""
    from drivers.busload import DEFAULT_BITRATE
    from foilc_hil.commands.run import check_bus_load

    axes_run(1)  # warm-up: imports, numba, EDS parsing
    runs: dict[str, list[float]] = {"single": [], **{f"axes{n}": [] for n in AXES}}
    for _ in range(repeats):
        runs["single"].append(single_axis_run())
        for n in AXES:
            runs[f"axes{n}"].append(n * axes_run(n))
    config = _config(4)
    computed = check_bus_load(config, config.bus)
    measured: list[float] = []
    with tempfile.TemporaryDirectory() as directory:
        log = Path(directory) / "axes.mcap"
        axes_run(4, out=log)
        measured.append(measured_load(log, DEFAULT_BITRATE, config.sample_time))
    peer = Figure(tuple(runs["single"]))
    rows = [Comparison(target=f"lockstep run of {n} axes on one bus (one loop, one SYNC), axis-cycles/s",
                       unit="axis-cycles/s", higher_is_better=True, project=Figure(tuple(runs[f"axes{n}"])),
                       peer=peer, peer_name="single-axis run of the first axis")
            for n in AXES]
    rows.append(Comparison(
        target="bus load of 4 axes at 2.5 ms: measured from the log (wire bits per SYNC period) vs computed",
        unit="% of 1 Mbit/s", higher_is_better=False, project=Figure(tuple(100 * m for m in measured)),
        peer=Figure((100 * computed.load,)), peer_name="worst case computed before the run (drivers.busload)",
        min_ratio=1.0, note="ratio >= 1: the computed worst case bounds what the bus carried"))
    summary = {"axis_cycles_per_second": runs, "bus_load": {"measured": measured, "computed": computed.load}}
    return summary, rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = json_parser("python -m benchmarks.bench_axes", __doc__)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    summary, rows = collect(args.repeats)
    emit({**summary, "comparisons": [row.to_json() for row in rows]}, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
