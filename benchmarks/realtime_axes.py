"""Realtime jitter of four axes across processes: ``foilc-hil run --mode realtime`` on configs/scara_4axis.yaml.

``python -m benchmarks.realtime_axes [--trials N] [--emulators one four] [--period S] [--out FILE]`` (as root: it
needs ``unshare --net``). Its own module, so the lead can run it alone (it imports :mod:`benchmarks.realtime`'s
receiver and SYNC statistics; that module does not import this one).

Everything runs inside one private network namespace this module creates (``unshare --net``, multicast routed over
its own loopback), so no frame leaves it. The bench runs the shipped four-axis config (one SYNC for four CSV drives
at its 2.5 ms period: 57.7 % of 1 Mbit/s; ``--period`` runs it at another, e.g. :data:`SHORTEST_PERIOD`, the
shortest the bus-load limit of 70 % and the config's 0.5 s trial allow, see the config's header) in realtime mode,
with the realtime sections of configs/realtime_1khz.yaml (:func:`realtime_config`), against, in turn:

- ``one``: ONE ``plant-emulator --mode realtime --node-id 1,2,3,4`` process answering each SYNC for all four nodes
  (each node with its axis's plant from the config's ``axes:``, as in a process of its own);
- ``four``: four ``plant-emulator --mode realtime`` processes, each with its axis's own config
  (:func:`foilc_hil.config.axis_configs`).

The instrument is the independent receiver process of :mod:`benchmarks.realtime` (kernel receive timestamps). From
it: SYNC interval deviation ``|dt - period|`` (p50/p99/max), lateness, empty slots, and per axis: the emulator's
answer time (its TPDO1 after the SYNC), TPDO1 lost on the way to the bench (received by the receiver, not logged
by the bench) and RPDO1 lost on the way out (logged as sent by the bench, not received). The bench's own counts
(missed and skipped deadlines, lost feedback) come from its ``--json`` document; lost feedback per axis from its
log (SYNC periods in which the bench logged no TPDO1 of that node).

The emulators' CPU per cycle: the user and system time of every emulator process (``/proc/PID/stat``) over the
bench's run, divided by the SYNCs the receiver saw meanwhile. ``--receive-filter off`` starts the emulators with
:func:`drivers.receive_filter.install_id_filter` replaced by one that installs nothing (an A/B measurement of the
kernel-side filter; the product has no such switch: it filters wherever the bus can).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.output import emit
from benchmarks.realtime import (
    BUS,
    NETNS_SETUP,
    ROOT,
    _quantiles,
    _start_receiver,
    _stop_receiver,
    answer_times,
    sync_statistics,
)
from drivers.cia301 import SYNC_COB_ID, FunctionCode, cob_id

SCARA = ROOT / "configs" / "scara_4axis.yaml"
REALTIME = ROOT / "configs" / "realtime_1khz.yaml"  # the shipped realtime settings, taken over as a user would
TOPOLOGIES = ("one", "four")
TRIALS = 10  # issue 28's target: 10 trials (of 200 cycles at 2.5 ms) complete, in every run
RUNS = 5  # ... in 5 of 5 runs per topology
SHORTEST_PERIOD = 0.5 / 242  # s: 69.8 % of 1 Mbit/s; 2.06 ms would fit the bus but not 0.5 s in whole samples


def _unanswered_periods(frames: list[dict[str, Any]], node: int) -> int:
    """SYNC periods of the bench's log (from a sent SYNC to the next) in which it logged no TPDO1 of ``node``."""
    tpdo1 = cob_id(FunctionCode.TPDO1, node)
    periods: list[bool] = []
    for frame in frames:
        if frame["id"] == SYNC_COB_ID and frame["dir"] == "tx":
            periods.append(False)
        elif periods and frame["id"] == tpdo1 and frame["dir"] == "rx":
            periods[-1] = True
    return periods[:-1].count(False)  # the last period is cut by the end of the run


def _axis_figures(frames: np.ndarray, logged: list[dict[str, Any]], node: int) -> dict[str, Any]:
    """One axis: emulator answer time, frames lost each way, periods without its feedback in the bench's log."""
    tpdo1, rpdo1 = cob_id(FunctionCode.TPDO1, node), cob_id(FunctionCode.RPDO1, node)
    received_tpdo = int(np.sum(frames[:, 0] == tpdo1))
    logged_tpdo = sum(1 for f in logged if f["id"] == tpdo1 and f["dir"] == "rx")
    sent_rpdo = sum(1 for f in logged if f["id"] == rpdo1 and f["dir"] == "tx")
    return {
        "node_id": node,
        "emulator_answer_us": _quantiles(answer_times(frames, node) * 1e6),
        "tpdo1_received": received_tpdo,
        "tpdo1_lost_to_bench": received_tpdo - logged_tpdo,
        "rpdo1_sent_by_bench": sent_rpdo,
        "rpdo1_lost": sent_rpdo - int(np.sum(frames[:, 0] == rpdo1)),
        "periods_without_feedback_in_log": _unanswered_periods(logged, node),
    }


def realtime_config(work: Path, period: float | None = None) -> Path:
    """configs/scara_4axis.yaml as shipped (axes, period, laws) with the realtime sections of
    configs/realtime_1khz.yaml: ``bench.mode``, ``bench.faults``, ``bench.realtime`` and ``emulator`` (the host setup
    of both processes, the fault tolerances and the emulator's SYNC supervision for a busy 2-core host); ``period``
    replaces ``sample_time`` (the SYNC period; every axis is designed for it)."""
    import yaml

    document = yaml.safe_load(SCARA.read_text(encoding="utf-8"))
    realtime = yaml.safe_load(REALTIME.read_text(encoding="utf-8"))
    document["bench"] = {**document.get("bench", {}), "mode": "realtime", "faults": realtime["bench"]["faults"],
                         "realtime": realtime["bench"]["realtime"]}
    document["emulator"] = realtime["emulator"]
    if period is not None:
        document["sample_time"] = period
    path = work / "scara_realtime.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


#: the emulator's entry point with the receive filter left out (``--receive-filter off``, A/B only)
_UNFILTERED = ("import sys, drivers.receive_filter as f; f.install_id_filter = lambda bus, ids: f.FilterKind.NONE; "
               "from plant_emulator.cli import main; sys.exit(main())")


def _emulator_commands(topology: str, config: Path, work: Path, filtered: bool = True) -> list[list[str]]:
    from foilc_hil.config import axis_configs, dump_config, load_config

    entry = ["-m", "plant_emulator"] if filtered else ["-c", _UNFILTERED]
    base = [sys.executable, *entry, "--bus", BUS, "--mode", "realtime"]
    if topology == "one":
        return [[*base, "--config", str(config), "--node-id", "1,2,3,4"]]
    commands = []
    for axis in axis_configs(load_config(config)):
        path = work / f"axis{axis.drive.node_id}.yaml"
        path.write_text(dump_config(axis), encoding="utf-8")
        commands.append([*base, "--config", str(path)])
    return commands


def _cpu_seconds(pid: int) -> float:
    """User plus system CPU time of process ``pid`` so far (``/proc/PID/stat`` fields 14 and 15)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _run(topology: str, trials: int, work: Path, law: str | None, period: float | None,
         filtered: bool = True) -> dict[str, Any]:
    """One bench run against ``topology``'s emulators, seen by the receiver."""
    from foilc_hil.config import axis_configs, load_config
    from foilc_hil.io.mcap_log import read_log

    out, log = work / f"axes-{topology}.json", work / f"axes-{topology}.mcap"
    config = realtime_config(work, period)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    emulators, logs = [], []
    try:
        for k, command in enumerate(_emulator_commands(topology, config, work, filtered)):
            logs.append(work / f"emulator-{topology}-{k}.stderr")
            with logs[-1].open("w") as stderr:
                emulators.append(subprocess.Popen(command, stderr=stderr, cwd=ROOT, env=env))
        for _ in range(600):  # every ready line, at most 60 s
            if all("ready" in path.read_text() for path in logs):
                break
            time.sleep(0.1)
        load_before = os.getloadavg()[0]
        receiver = _start_receiver(out)
        cpu_before = [_cpu_seconds(emulator.pid) for emulator in emulators]
        run = subprocess.run(
            [sys.executable, "-m", "foilc_hil.cli", "run", "--config", str(config), "--bus", BUS, "--mode",
             "realtime", "--trials", str(trials), "--out", str(log), "--json", "--quiet",
             *(["--law", law] if law else [])],
            capture_output=True, text=True, cwd=ROOT, env=env,
        )
        cpu = sum(_cpu_seconds(e.pid) for e in emulators) - sum(cpu_before)
        frames, dropped = _stop_receiver(receiver, out)
    finally:
        for emulator in emulators:  # only the emulators started above, by their own handles
            emulator.send_signal(signal.SIGINT)
            emulator.wait(timeout=30)
    document: dict[str, Any] = json.loads(run.stdout) if run.stdout.strip() else {"error": run.stderr.strip()}
    logged = read_log(log).frames if log.exists() else []
    period = load_config(config).sample_time
    sent_syncs = sum(1 for f in logged if f["id"] == SYNC_COB_ID and f["dir"] == "rx")
    syncs = frames[frames[:, 0] == SYNC_COB_ID, 1]
    timing = document.get("timing", {})
    cycles = timing.get("cycles") or 0
    return {
        "topology": topology,
        "law": law or "as configured",
        "emulator_processes": len(logs),
        "period_s": period,
        "exit_code": run.returncode,
        "error": document.get("error"),
        "load_average_1min_before": load_before,
        "load_average_1min_after": os.getloadavg()[0],
        "trials_completed": len(document.get("trials", [])),
        "receive_filter": "on" if filtered else "off",
        "emulator_filters": sorted({_filter_of(path) for path in logs}),
        "emulator_cpu_us_per_sync": 1e6 * cpu / syncs.size if syncs.size else None,
        "timing": timing,
        "missed_deadline_fraction": timing.get("missed_deadlines", 0) / cycles if cycles else None,
        "receiver": {**sync_statistics(syncs, period), "syncs_on_bench_log": sent_syncs,
                     "syncs_lost": sent_syncs - int(syncs.size), "receiver_dropped": dropped},
        "axes": [_axis_figures(frames, logged, axis.drive.node_id) for axis in axis_configs(load_config(config))],
        "emulator_stderr_tail": [path.read_text().splitlines()[-3:] for path in logs],
        "sse": {str(axis["node_id"]): [trial["sse"] for trial in axis["trials"]] for axis in document.get("axes", [])},
    }


def _filter_of(emulator_log: Path) -> str:
    """The receive filter an emulator's ready line names (``-``: it names none)."""
    for line in emulator_log.read_text().splitlines():
        if "receive filter " in line:
            return line.rsplit("receive filter ", 1)[1].rstrip(")")
    return "-"


def _inside(trials: int, topologies: Sequence[str], law: str | None = None, period: float | None = None,
            filtered: bool = True, runs: int = 1) -> dict[str, Any]:
    """The whole measurement (run inside the private namespace): ``runs`` rounds, each topology once a round (so a
    change of the host's load falls on both alike)."""
    for step in NETNS_SETUP:
        subprocess.run(shlex.split(step), check=True)
    with tempfile.TemporaryDirectory(prefix="foilc-realtime-axes-") as directory:
        done = [_run(topology, trials, Path(directory), law, period, filtered)
                for _ in range(runs) for topology in topologies]
    return {"config": str(SCARA.relative_to(ROOT)), "trials": trials, "cpus": os.cpu_count(), "runs": done}


def collect(trials: int = TRIALS, topologies: Sequence[str] = TOPOLOGIES, law: str | None = None,
            period: float | None = None, filtered: bool = True, runs: int = 1) -> dict[str, Any]:
    """Run the measurement in a private network namespace (``unshare --net``); the results document."""
    started = time.time()
    command = [sys.executable, "-m", "benchmarks.realtime_axes", "--inside", "--trials", str(trials),
               "--runs", str(runs), "--emulators", *topologies, *(["--law", law] if law else []),
               *(["--period", repr(period)] if period is not None else []),
               "--receive-filter", "on" if filtered else "off"]
    result = subprocess.run(["unshare", "--net", "--", *command], capture_output=True, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True)
    document: dict[str, Any] = json.loads(result.stdout)
    document["date"] = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    document["seconds"] = round(time.time() - started, 1)
    document["command"] = shlex.join(["python", "-m", "benchmarks.realtime_axes", *command[4:]])
    return document


def targets(document: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 28's target 4, per topology and period: every run completes its trials (exit 0, all of them)."""
    rows = []
    for (topology, period), runs in _by_topology(document).items():
        complete = sum(1 for run in runs if run["exit_code"] == 0 and run["trials_completed"] == document["trials"])
        rows.append({"condition": f"{period * 1e3:g} ms", "peer": None, "ratio": None,
                     "target": f"four axes, {_TOPOLOGY[topology]}: {document['trials']} trials complete in every run",
                     "bench": f"{complete} of {len(runs)}", "met": complete == len(runs)})
    return rows


_TOPOLOGY = {"one": "one emulator process", "four": "four emulator processes"}


def _by_topology(document: dict[str, Any]) -> dict[tuple[str, float], list[dict[str, Any]]]:
    grouped: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for run in document["runs"]:
        grouped.setdefault((run["topology"], run["period_s"]), []).append(run)
    return grouped


def markdown(document: dict[str, Any]) -> str:
    """The "Four axes across processes" section of ``docs/benchmarks.md`` from a results document."""
    lines = [
        "## Four axes across processes",
        "",
        f"`{document.get('command', 'python -m benchmarks.realtime_axes')}` ({document.get('date', '-')}, "
        f"{document['cpus']} CPUs, {document.get('seconds', 0):.0f} s): `{document['config']}` in realtime with "
        f"configs/realtime_1khz.yaml's host settings, {document['trials']} trials a run; one private network "
        "namespace; frames seen by the independent receiver (`benchmarks.frame_recorder`). Emulator CPU: the user "
        "and system time of every emulator process over the bench's run, per SYNC.",
        "",
        "| emulators | period (ms) | exit | trials | missed deadlines | SYNC interval dev p99 (us) | empty slots | "
        "emulator CPU per SYNC (us) | receive filter | load before -> after |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in document["runs"]:
        fraction, receiver = run["missed_deadline_fraction"], run["receiver"]
        lines.append(
            f"| {_TOPOLOGY[run['topology']]} | {run['period_s'] * 1e3:.3f} | {run['exit_code']} | "
            f"{run['trials_completed']} | {'-' if fraction is None else f'{100 * fraction:.2f} %'} | "
            f"{_us(receiver.get('interval_deviation_us', {}).get('p99'))} | {receiver.get('empty_slots', '-')} | "
            f"{_us(run.get('emulator_cpu_us_per_sync'))} | {', '.join(run.get('emulator_filters', ['-']))} | "
            f"{run['load_average_1min_before']:.1f} -> {run['load_average_1min_after']:.1f} |")
    lines += ["", "| period | target | runs | |", "|---|---|---|---|"]
    lines += [f"| {row['condition']} | {row['target']} | {row['bench']} | {'met' if row['met'] else 'missed'} |"
              for row in targets(document)]
    return "\n".join(lines) + "\n"


def summary(document: dict[str, Any]) -> str:
    """One paragraph per run: the SYNC's jitter, the bench's counts, and one line per axis."""
    lines = []
    for run in document["runs"]:
        receiver, timing = run["receiver"], run["timing"]
        deviation = receiver.get("interval_deviation_us", {})
        lines.append(
            f"{run['topology']} ({run['emulator_processes']} emulator process(es)), {run['law']}, "
            f"{run['period_s'] * 1e3:g} ms, "
            f"exit {run['exit_code']}, load {run['load_average_1min_before']:.1f}->{run['load_average_1min_after']:.1f}"
            f": {receiver.get('syncs', 0)} SYNCs, interval deviation p50/p99/max "
            f"{_us(deviation.get('p50'))}/{_us(deviation.get('p99'))}/{_us(deviation.get('max'))} us, empty slots "
            f"{receiver.get('empty_slots', '-')}, SYNCs lost {receiver['syncs_lost']}; bench: cycles "
            f"{timing.get('cycles', '-')}, missed deadlines {timing.get('missed_deadlines', '-')}, skipped "
            f"{timing.get('skipped_deadlines', '-')}, lost feedback {timing.get('missing_feedback', '-')}; "
            f"trials {run['trials_completed']}; emulator CPU {_us(run.get('emulator_cpu_us_per_sync'))} us per SYNC "
            f"(receive filter {', '.join(run.get('emulator_filters', ['-']))})")
        for axis in run["axes"]:
            answer = axis["emulator_answer_us"]
            lines.append(
                f"  node {axis['node_id']}: answer p50/p99/max {_us(answer['p50'])}/{_us(answer['p99'])}/"
                f"{_us(answer['max'])} us, TPDO1 lost to bench {axis['tpdo1_lost_to_bench']}, RPDO1 lost "
                f"{axis['rpdo1_lost']}, periods without feedback in log {axis['periods_without_feedback_in_log']}")
    return "\n".join(lines) + "\n"


def _us(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.realtime_axes", description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="JSON file to write (default: stdout)")
    parser.add_argument("--trials", type=int, default=TRIALS, help=f"trials per run (default {TRIALS})")
    parser.add_argument("--emulators", nargs="+", choices=TOPOLOGIES, default=list(TOPOLOGIES),
                        help="one process for the four nodes, four processes, or both (default)")
    parser.add_argument("--law", help="the run's --law (default: the config's, IOILC)")
    parser.add_argument("--period", type=float,
                        help=f"SYNC period in s (default: the config's 2.5 ms; shortest allowed {SHORTEST_PERIOD!r})")
    parser.add_argument("--runs", type=int, default=1, help=f"rounds of every topology (make bench-realtime: {RUNS})")
    parser.add_argument("--markdown", metavar="JSON", help="print the docs section of a results file and exit")
    parser.add_argument("--receive-filter", choices=("on", "off"), default="on",
                        help="off: the emulators install no receive filter (an A/B measurement)")
    parser.add_argument("--summary", metavar="JSON", help="print the text summary of a results file and exit")
    parser.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)  # already in the namespace
    args = parser.parse_args(argv)
    if args.summary:
        sys.stdout.write(summary(json.loads(Path(args.summary).read_text(encoding="utf-8"))))
        return 0
    if args.markdown:
        sys.stdout.write(markdown(json.loads(Path(args.markdown).read_text(encoding="utf-8"))))
        return 0
    if args.inside:
        filtered = args.receive_filter == "on"
        sys.stdout.write(json.dumps(_inside(args.trials, args.emulators, args.law, args.period, filtered, args.runs)))
        return 0
    emit(collect(args.trials, args.emulators, args.law, args.period, args.receive_filter == "on", args.runs), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
