"""Realtime 1 kHz across processes: the bench against canopen's and python-can's SYNC producers, quiet and loaded.

``python -m benchmarks.realtime [--quick] [--conditions quiet load] [--out benchmarks/realtime.json]`` (as root: it
needs ``unshare --net``)

Everything runs inside one private network namespace this module creates (``unshare --net``, multicast routed over
its own loopback), so no frame leaves it. In that namespace, for each condition (``quiet``; ``load``: busy-loop
processes started here, two per CPU, killed at the end), in the same run:

- **bench**: ``plant-emulator`` and ``foilc-hil run`` on ``configs/realtime_1khz.yaml`` as shipped (10 trials of
  6000 samples; ``--quick``: 2 trials of 1200), two processes over ``udp_multicast``;
- **canopen**: a process running ``canopen.Network.sync.start(0.001)``, python-can's periodic task underneath;
- **python-can**: a process running ``bus.send_periodic(SYNC, 0.001)``;

each peer once as a user would start it and once under ``chrt -f 50`` (the scheduling the bench gives its own
cyclic threads, so the comparison is of the sender, not of the privilege), that second run also holding the PM QoS
request of the CPUs' wake-up latency the shipped config asks for (``cpu_latency_us``,
:class:`drivers.realtime.CpuLatencyRequest`), as the host-floor probe does. One independent receiver process (itself
under ``chrt -f 60``: it is the instrument) records every frame with its kernel receive timestamp. From it:
SYNC interval deviation ``|dt - 1 ms|`` (p50/p99/max), SYNC lateness (the phase within the period against the
earliest of the surrounding SYNCs, :func:`_lateness`: immune to clock drift, to the phase jump between the bench's
start-up SYNCs and its loop, and to slots without a SYNC), slots without a SYNC, and for the bench the emulator's
answer time (TPDO1 after SYNC) and lost frames (SYNCs the bench logged as sent against SYNCs received; TPDO1
received by the receiver against TPDO1 logged by the bench). Then, alternated (:func:`_alternated`: 6 rounds, each
producer alone for 5 s, with the same privileges), the bench's own SYNC producer (``drivers.sync_process``, started
by ``ProcessSync`` as the bench starts it) and python-can's ``send_periodic``: the like-for-like comparison of the
two senders, judged by a test over the rounds (:func:`alternated_verdict`), not by one run's difference. The bench's
own counts (missed and skipped deadlines, lost feedback, its feedback latency from ``/timing``) come from its
``--json`` document and log.

:func:`collect` returns the whole document (the ``make bench`` generator calls it), :func:`markdown` renders it as
the "Realtime 1 kHz across processes" section of ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import functools
import json
import os
import platform
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

from benchmarks import frame_recorder, host_floor
from benchmarks.output import emit
from drivers.cia301 import SYNC_COB_ID, FunctionCode, cob_id
from drivers.realtime import CpuLatencyRequest

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "realtime_1khz.yaml"
GROUP = "239.74.163.7"
BUS = f"udp_multicast:{GROUP}"
PERIOD = 0.001
NODE = 1  # configs/realtime_1khz.yaml
SYNC_ID, TPDO1_ID = SYNC_COB_ID, cob_id(FunctionCode.TPDO1, NODE)
RPDO1_ID = cob_id(FunctionCode.RPDO1, NODE)  # controlword (16 bits), then the target (32 bits, signed)
NETNS_SETUP = ["ip link set lo up", "ip link set lo multicast on", "ip route add 224.0.0.0/4 dev lo"]
PEER_FIFO = 50
HOPS = 3  # process wake-ups in series in one bench cycle (see _floor_lines)
RECEIVER_FIFO = 49  # the instrument: above every normal process, below the cyclic threads it watches
# SYNCs each way that define the local grid: short enough that a phase jump of the producer (the bench's start-up
# SYNCs against its loop's) misjudges at most this many SYNCs, long enough to hold many on-time ones
LATENESS_WINDOW = 50
FULL = {"trials": 10, "time_scale": 1.0, "peer_seconds": 10.0, "alone_rounds": 6, "alone_seconds": 5.0}
QUICK = {"trials": 2, "time_scale": 0.2, "peer_seconds": 3.0, "alone_rounds": 2, "alone_seconds": 2.0}
#: one-sided significance of the alternated producers' comparison (:func:`alternated_verdict`)
SIGNIFICANCE = 0.05
CONDITIONS = ("quiet", "load")

# The instrument is benchmarks.frame_recorder (kernel timestamps, a 16 MiB receive buffer, its socket's drops).

_CANOPEN_PEER = """
import sys, time, canopen
network = canopen.Network()
network.connect(interface="udp_multicast", channel=sys.argv[1])
network.sync.start(float(sys.argv[2]))
time.sleep(float(sys.argv[3]))
network.sync.stop()
network.disconnect()
"""

_PYTHON_CAN_PEER = """
import sys, time, can
bus = can.Bus(interface="udp_multicast", channel=sys.argv[1])
task = bus.send_periodic(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False), float(sys.argv[2]))
time.sleep(float(sys.argv[3]))
task.stop()
bus.shutdown()
"""

# the bench's own SYNC producer (drivers.sync_process), started as the bench starts it: ProcessSync from a thread at
# SCHED_FIFO p - 1 runs the producer at p, with its memory locked, timer slack 1 ns and the channel's frame order
_BENCH_PRODUCER = """
import sys, time
from drivers.sync_process import ProcessSync
sync = ProcessSync("udp_multicast", sys.argv[1])
sync.start(float(sys.argv[2]))
time.sleep(float(sys.argv[3]))
sync.stop()
"""


# --- analysis of what the receiver saw ----------------------------------------------------------------------------


def _quantiles(values: np.ndarray) -> dict[str, float | None]:
    if values.size == 0:
        return {"p50": None, "p99": None, "max": None}
    p50, p99 = np.percentile(values, [50, 99])
    return {"p50": float(p50), "p99": float(p99), "max": float(values.max())}


def sync_statistics(times: np.ndarray, period: float = PERIOD) -> dict[str, Any]:
    """SYNC interval deviation, lateness and empty slots (microseconds) of SYNC receive times (seconds)."""
    if times.size < 3:
        return {"syncs": int(times.size)}
    intervals = np.diff(times)
    slots = np.maximum(1, np.rint(intervals / period)).astype(int)  # a SYNC more than half a period late is 1 slot
    lateness = _lateness(times, period)
    return {
        "syncs": int(times.size),
        "interval_deviation_us": _quantiles(np.abs(intervals - period) * 1e6),
        "lateness_us": _quantiles(lateness * 1e6),
        "empty_slots": int(np.sum(slots - 1)),
        "intervals_over_1_5_periods": int(np.sum(intervals > 1.5 * period)),
    }


def _lateness(times: np.ndarray, period: float) -> np.ndarray:
    """Each SYNC's lateness (seconds) against the slot grid of its neighbourhood, in [0, 0.75 period + early).

    No slot is counted (one miscounted slot would shift every later phase by a period): the phase of each SYNC
    within the period, ``u``, is compared with the local grid phase, the circular mean of ``u`` over the
    surrounding :data:`LATENESS_WINDOW` SYNCs each way (it follows the drift between the sender's and the receiver's
    clocks, which is then taken out); phases from a quarter period early to three quarters late are told apart; the
    earliest SYNC of the window defines lateness 0.
    """
    width = 2 * LATENESS_WINDOW + 1
    u = np.mod((times - times[0]) / period, 1.0)
    # the windows at either end hold fewer SYNCs, never copies: padding by the first SYNC's phase (np.pad's "edge")
    # gave a late first SYNC the weight of LATENESS_WINDOW + 1 in the grid of the SYNCs after it, and every one of
    # them read as late by as much (a producer whose first SYNC was 0.65 ms late measured a lateness p99 of 300 us
    # over 5 s)
    local = np.convolve(np.pad(np.exp(2j * np.pi * u), LATENESS_WINDOW), np.ones(width), mode="valid")
    centre = np.unwrap(np.angle(local)) / (2 * np.pi)  # continuous across the period boundary as the clocks drift
    phase = centre + np.mod(u - centre + 0.25, 1.0) - 0.25  # each SYNC's phase, on the same unwrapped scale
    # the clocks' steady drift (the median step of the local grid: a rare phase jump does not move it), so the
    # window's earliest SYNC is not earlier by the drift alone
    phase = phase - np.median(np.diff(centre)) * np.arange(times.size)
    earliest = np.lib.stride_tricks.sliding_window_view(np.pad(phase, LATENESS_WINDOW, constant_values=np.inf), width)
    return (phase - earliest.min(axis=1)) * period


def answer_times(frames: np.ndarray, node: int = NODE) -> np.ndarray:
    """Seconds from each SYNC to node ``node``'s TPDO1 answering it (the first one before the next SYNC)."""
    tpdo1 = cob_id(FunctionCode.TPDO1, node)
    answers: list[float] = []
    last_sync: float | None = None
    for can_id, stamp in frames[:, :2]:
        if can_id == SYNC_ID:
            last_sync = stamp
        elif can_id == tpdo1 and last_sync is not None:
            answers.append(stamp - last_sync)
            last_sync = None
    return np.array(answers)


# --- the scenarios --------------------------------------------------------------------------------------------------


def _python() -> str:
    return sys.executable


def _start_receiver(out: Path) -> subprocess.Popen[str]:
    return frame_recorder.start(GROUP, out, fifo=RECEIVER_FIFO)


def _stop_receiver(receiver: subprocess.Popen[str], out: Path) -> tuple[np.ndarray, int | None]:
    """The frames the receiver saw as ``(id, timestamp, target)`` rows (``target``: node 1's RPDO1 target, what the
    drive latches at the next SYNC; 0 for other frames), and the datagrams its socket dropped (None: not said)."""
    recording = frame_recorder.stop(receiver, out)
    targets = [int.from_bytes(data[2:6], "little", signed=True) if can_id == RPDO1_ID else 0
               for can_id, data in zip(recording.frames[:, 0], recording.data, strict=True)]
    return np.column_stack([recording.frames, np.array(targets, dtype=float)]), recording.dropped


@functools.cache  # read once: every privileged peer and each condition's floor probe ask
def _shipped_cpu_latency() -> int | None:
    """``bench.realtime.cpu_latency_us`` of the shipped config (None: it asks for none)."""
    import yaml

    value = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))["bench"]["realtime"].get("cpu_latency_us")
    return None if value is None else int(value)


def _privileged(fifo: bool) -> contextlib.AbstractContextManager[CpuLatencyRequest | None]:
    """The host privileges of the bench's own setup beyond SCHED_FIFO, for a privileged peer or the floor probe:
    the shipped config's PM QoS request, held meanwhile (nothing when it asks for none, for an unprivileged run, or
    when the host refuses it: the rows then say no request was held, as the bench's report does)."""
    microseconds = _shipped_cpu_latency()
    if not fifo or microseconds is None:
        return contextlib.nullcontext()
    request = CpuLatencyRequest(microseconds)
    if request.open() is not None:
        return contextlib.nullcontext()
    return contextlib.closing(request)


def _peer(name: str, script: str, seconds: float, fifo: bool, work: Path, *,
          priority: int = PEER_FIFO) -> dict[str, Any]:
    """One SYNC producer alone on the bus for ``seconds``, as the receiver saw it; ``fifo``: under ``chrt -f
    priority`` with the shipped PM QoS request held."""
    out = work / f"peer-{name}-{fifo}.json"
    receiver = _start_receiver(out)
    prefix = ["chrt", "-f", str(priority)] if fifo else []
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with _privileged(fifo) as held:
        subprocess.run([*prefix, _python(), "-c", script, GROUP, str(PERIOD), str(seconds)], check=True, cwd=ROOT,
                       env=env)
    frames, dropped = _stop_receiver(receiver, out)
    syncs = frames[frames[:, 0] == SYNC_ID, 1]
    return {"peer": name, "sched_fifo": fifo, "cpu_latency_us": _held_latency(held), "receiver_dropped": dropped,
            **sync_statistics(syncs)}


def _alternated(rounds: int, seconds: float, work: Path) -> dict[str, Any]:
    """The bench's SYNC producer and python-can's ``send_periodic``, each alone and with the same privileges
    (SCHED_FIFO :data:`PEER_FIFO`, the PM QoS request), alternated ``rounds`` times (the first of each pair
    alternates too): the like-for-like comparison of the two senders under the same host, round by round."""
    pairs = []
    for k in range(rounds):
        order = [("bench", _BENCH_PRODUCER, PEER_FIFO - 1), ("python-can", _PYTHON_CAN_PEER, PEER_FIFO)]
        measured = {name: _peer(name, script, seconds, True, work, priority=priority)
                    for name, script, priority in (order if k % 2 == 0 else order[::-1])}
        pairs.append({name: measured[name].get("lateness_us", {}).get("p99") for name in ("bench", "python-can")})
    return {"seconds": seconds, "rounds": pairs, **alternated_verdict(pairs)}


def alternated_verdict(pairs: Sequence[dict[str, float | None]]) -> dict[str, Any]:
    """The verdict of the alternated rounds' SYNC lateness p99 (``bench`` and ``python-can`` per round): the median
    of python-can's over the bench's (> 1: the bench earlier), and Wilcoxon's signed-rank test on the rounds' log
    ratios, one-sided each way. ``better`` or ``worse`` only at :data:`SIGNIFICANCE`; otherwise the difference is
    inside the rounds' noise, and with fewer than 5 rounds no verdict can be significant at all."""
    from scipy.stats import wilcoxon

    logs = np.array([np.log(p["python-can"] / p["bench"]) for p in pairs if p["bench"] and p["python-can"]])
    if logs.size == 0:
        return {"median_ratio": None, "p_better": None, "p_worse": None, "verdict": "not measured"}
    p_better = float(wilcoxon(logs, alternative="greater").pvalue) if np.any(logs) else 1.0
    p_worse = float(wilcoxon(logs, alternative="less").pvalue) if np.any(logs) else 1.0
    verdict = ("better" if p_better < SIGNIFICANCE else "worse" if p_worse < SIGNIFICANCE
               else "inside the noise")
    return {"median_ratio": float(np.exp(np.median(logs))), "p_better": p_better, "p_worse": p_worse,
            "verdict": verdict}


def _held_latency(held: CpuLatencyRequest | None) -> int | None:
    return None if held is None else held.microseconds


def _bench_config(work: Path, trials: int, time_scale: float) -> Path:
    import yaml

    document = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    document["trials"] = trials
    document["reference"]["time_scale"] = time_scale
    path = work / "realtime.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def _bench(config: Path, work: Path, tag: str) -> dict[str, Any]:
    out, log = work / f"bench-{tag}.json", work / f"bench-{tag}.mcap"
    emulator_log = work / f"emulator-{tag}.stderr"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with emulator_log.open("w") as stderr:
        emulator = subprocess.Popen(
            [_python(), "-m", "plant_emulator", "--config", str(config), "--bus", BUS, "--mode", "realtime"],
            stderr=stderr, cwd=ROOT, env=env,
        )
    try:
        for _ in range(600):  # its ready line, at most 60 s
            if "ready" in emulator_log.read_text():
                break
            time.sleep(0.1)
        receiver = _start_receiver(out)
        run = subprocess.run(
            [_python(), "-m", "foilc_hil.cli", "run", "--config", str(config), "--bus", BUS, "--mode", "realtime",
             "--out", str(log), "--json", "--quiet"],
            capture_output=True, text=True, cwd=ROOT, env=env,
        )
        frames, dropped = _stop_receiver(receiver, out)
    finally:
        emulator.send_signal(signal.SIGINT)
        emulator.wait(timeout=30)
    document = json.loads(run.stdout) if run.stdout.strip() else {"error": run.stderr.strip()}
    figures = _bench_figures(document, frames, log)
    figures["receiver"]["receiver_dropped"] = dropped
    return {"exit_code": run.returncode, **figures}


def _bench_figures(document: dict[str, Any], frames: np.ndarray, log: Path) -> dict[str, Any]:
    """The bench's own report, and the receiver's view of the same run (lost frames included)."""
    from foilc_hil.io.mcap_log import read_log

    contents = read_log(log)
    import yaml

    scale = float(yaml.safe_load(CONFIG.read_text(encoding="utf-8"))["drive"]["velocity_scale"])
    # every SYNC on the bus comes back to the bench's receive socket (the multicast loop), whoever sent it: the loop, a
    # thread or a process; so the log holds each as received, and only the loop's also as sent
    sent_syncs = sum(1 for f in contents.frames if f["id"] == SYNC_ID and f["dir"] == "rx")
    logged_tpdo = sum(1 for f in contents.frames if f["id"] == TPDO1_ID and f["dir"] == "rx")
    latency = np.array([r["feedback_latency_us"] for r in contents.timing if r["feedback_latency_us"] is not None])
    syncs = frames[frames[:, 0] == SYNC_ID, 1]
    timing = document.get("timing", {})
    cycles = timing.get("cycles") or 0
    return {
        "trials_completed": len(document.get("trials", [])),
        "error": document.get("error"),
        "timing": timing,
        "missed_deadline_fraction": timing.get("missed_deadlines", 0) / cycles if cycles else None,
        "faults": document.get("faults"),
        "latched_truth": latched_truth(frames, contents, scale),
        "feedback_latency_us": _quantiles(latency),
        "receiver": {
            **sync_statistics(syncs),
            "emulator_answer_us": _quantiles(answer_times(frames) * 1e6),
            "syncs_on_bench_log": sent_syncs,
            "syncs_lost": sent_syncs - int(syncs.size),
            "tpdo1_received": int(np.sum(frames[:, 0] == TPDO1_ID)),
            "tpdo1_lost_to_bench": int(np.sum(frames[:, 0] == TPDO1_ID)) - logged_tpdo,
        },
    }


def latched_truth(frames: np.ndarray, contents: Any, scale: float) -> dict[str, Any]:
    """The log's ``/ilc/sample.latched`` against what the receiver saw: at each SYNC the drive latched the last RPDO
    before it (its target over ``scale``); row ``i`` of a trial is the SYNC ``first_sync + i + 1`` (counted from the
    bench's first, which the receiver, started before the bench, saw too). Counts, and the first disagreement."""
    latched: list[float | None] = []  # [k - 1]: latched at SYNC k
    last: float | None = None
    for can_id, _, target in frames:
        if can_id == SYNC_ID:
            latched.append(last)
        elif can_id == RPDO1_ID:
            last = target / scale
    checked = agree = 0
    first_disagreement = None
    for record in contents.trials:
        if "first_sync" not in record:
            continue
        first = int(record["first_sync"])
        for row in (s for s in contents.samples if s["trial"] == record["trial"] and "latched" in s):
            index = first + int(row["sample"])
            on_wire = latched[index] if index < len(latched) else None
            checked += 1
            if on_wire is not None and row["latched"] == on_wire:
                agree += 1
            elif first_disagreement is None:
                first_disagreement = {"trial": record["trial"], "sample": row["sample"], "logged": row["latched"],
                                      "on_wire": on_wire}
    differing = sum(1 for s in contents.samples if "latched" in s and s["latched"] != round(s["control"] * scale)
                    / scale)
    return {"samples": checked, "agree": agree, "first_disagreement": first_disagreement,
            "latched_not_command": differing}


def _condition(name: str, settings: dict[str, Any], work: Path) -> dict[str, Any]:
    load: list[subprocess.Popen[bytes]] = []
    if name == "load":
        load = [subprocess.Popen(["sh", "-c", "while :; do :; done"]) for _ in range(2 * (os.cpu_count() or 1))]
        time.sleep(1.0)
    try:
        config = _bench_config(work, settings["trials"], settings["time_scale"])
        result: dict[str, Any] = {"load_average_1min_before": os.getloadavg()[0]}
        steal = host_floor.StealMeter.now()
        result["bench"] = _bench(config, work, name)
        result["peers"] = [
            _peer(peer, script, settings["peer_seconds"], fifo, work)
            for peer, script in (("canopen", _CANOPEN_PEER), ("python-can", _PYTHON_CAN_PEER))
            for fifo in (False, True)
        ]
        result["alone"] = _alternated(settings["alone_rounds"], settings["alone_seconds"], work)
        with _privileged(True) as held:  # the probe runs as the bench's cyclic threads do
            result["host_floor"] = host_floor.wakeups(settings["peer_seconds"], PERIOD, work)
        result["host_floor"]["cpu_latency_us"] = _held_latency(held)
        result["steal_percent"] = host_floor.StealMeter.now().percent_since(steal)
        result["load_average_1min_after"] = os.getloadavg()[0]
        return result
    finally:
        for process in load:  # only the busy loops started above, by their own handles
            process.kill()
            process.wait()


def _inside(quick: bool, conditions_wanted: Sequence[str] = CONDITIONS) -> dict[str, Any]:
    """The whole measurement (run inside the private namespace)."""
    for step in NETNS_SETUP:
        subprocess.run(shlex.split(step), check=True)
    settings = QUICK if quick else FULL
    with tempfile.TemporaryDirectory(prefix="foilc-realtime-") as directory:
        conditions = {name: _condition(name, settings, Path(directory)) for name in conditions_wanted}
    return {
        "settings": settings,
        "config": str(CONFIG.relative_to(ROOT)),
        "conditions": conditions,
        "ratios": ratios(conditions),
    }


def ratios(conditions: dict[str, Any]) -> dict[str, Any]:
    """Peer SYNC p99 (interval deviation, lateness) over the bench's, per condition and peer (> 1: bench better)."""
    table: dict[str, Any] = {}
    for name, condition in conditions.items():
        bench = condition["bench"]["receiver"]
        for peer in condition["peers"]:
            key = f"{name}/{peer['peer']}{'/fifo' if peer['sched_fifo'] else ''}"
            table[key] = {
                metric: _ratio(peer.get(metric, {}).get("p99"), bench.get(metric, {}).get("p99"))
                for metric in ("interval_deviation_us", "lateness_us")
            }
    return table


def _ratio(peer: float | None, bench: float | None) -> float | None:
    return peer / bench if peer is not None and bench else None


def collect(quick: bool = False, conditions: Sequence[str] = CONDITIONS) -> dict[str, Any]:
    """Run the benchmark in a private network namespace (``unshare --net``); the results document."""
    options = [*(["--quick"] if quick else []), "--conditions", *conditions]
    command = [_python(), "-m", "benchmarks.realtime", "--inside", *options]
    started = time.time()
    result = subprocess.run(["unshare", "--net", "--", *command], capture_output=True, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True)
    document = json.loads(result.stdout)
    document["targets"] = targets(document)
    document["machine"] = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
    }
    document["date"] = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    document["seconds"] = round(time.time() - started, 1)
    document["command"] = shlex.join(["python", "-m", "benchmarks.realtime", *options])
    return document


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.realtime", description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="JSON file to write (default: stdout)")
    parser.add_argument("--quick", action="store_true", help="2 short trials and 3 s peers instead of 10 x 6000")
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS),
                        help="which conditions to run (default both; 'quiet' alone starts no busy loops)")
    parser.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)  # already in the namespace
    parser.add_argument("--markdown", metavar="JSON", help="print the docs section of a results file and exit")
    args = parser.parse_args(argv)
    if args.markdown:
        sys.stdout.write(markdown(json.loads(Path(args.markdown).read_text(encoding="utf-8"))))
        return 0
    if args.inside:
        sys.stdout.write(json.dumps(_inside(args.quick, args.conditions)))
        return 0
    emit(collect(args.quick, args.conditions), args.out)
    return 0


# --- the docs section -------------------------------------------------------------------------------------------


def _us(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def _sync_row(label: str, stats: dict[str, Any], bench: dict[str, Any]) -> str:
    deviation, lateness = stats.get("interval_deviation_us", {}), stats.get("lateness_us", {})
    ratio = _ratio(lateness.get("p99"), bench.get("lateness_us", {}).get("p99"))
    return (
        f"| {label} | {stats.get('syncs', 0)} | {_us(deviation.get('p50'))} | {_us(deviation.get('p99'))} | "
        f"{_us(deviation.get('max'))} | {_us(lateness.get('p99'))} | {stats.get('empty_slots', '-')} | "
        f"{'-' if ratio is None else f'{ratio:.2f}'} |"
    )


def targets(document: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 9's realtime targets, per condition: the bench's figure, the peer's, their ratio, met or missed.

    Targets: at most 0.1 % missed deadlines (stated for a quiet machine); SYNC lateness p99 at least 5x lower than
    canopen's producer and no worse than python-can's ``send_periodic`` (both as a user starts them), shown for the
    interval deviation too (lateness is judged within a period: a SYNC several periods late counts as empty slots,
    which the interval deviation sees); no frame lost. Issue 28 adds: missed deadlines at most twice the same run's
    host-floor estimate, with the estimate beside it (in the peer column), and the latched-truth check.
    """
    rows: list[dict[str, Any]] = []
    for name, condition in document["conditions"].items():
        bench = condition["bench"]
        receiver = bench["receiver"]
        fraction = bench["missed_deadline_fraction"]
        completed = bench["exit_code"] == 0
        rows.append({"condition": name, "target": "the run completes", "bench": bench["exit_code"], "peer": None,
                     "ratio": None, "met": completed})
        rows.append({"condition": name, "target": "missed deadlines <= 0.1 %", "bench": fraction, "peer": None,
                     "ratio": None, "met": completed and fraction is not None and fraction <= 0.001})
        peers = {(p["peer"], p["sched_fifo"]): p for p in condition["peers"]}
        for metric, label in (("lateness_us", "SYNC lateness p99"), ("interval_deviation_us", "SYNC interval dev p99")):
            for peer, needed in (("canopen", 5.0), ("python-can", 1.0)):
                figure = peers[(peer, False)].get(metric, {}).get("p99")
                own = receiver.get(metric, {}).get("p99")
                ratio = _ratio(figure, own)
                rows.append({"condition": name, "target": f"{label}: {peer} / bench >= {needed:g}", "bench": own,
                             "peer": figure, "ratio": ratio, "met": ratio is not None and ratio >= needed})
        # per kind, never summed: 20 SYNCs the receiver missed and 20 TPDO1 it missed (-20 "lost to the bench") once
        # added up to 0 and read as met
        lost = (receiver["syncs_lost"], receiver["tpdo1_lost_to_bench"])
        rows.append({"condition": name, "target": "no frame lost (SYNC, TPDO1)", "bench": f"{lost[0]}, {lost[1]}",
                     "peer": None, "ratio": None, "met": lost == (0, 0)})
        rows += _issue28_rows(name, condition)
    return rows


def floor_estimate(condition: dict[str, Any]) -> float | None:
    """The fraction of cycles the host alone would make miss (:func:`_floor_lines`): each of :data:`HOPS` wake-ups
    in series later than half a period, independently; None without a host-floor probe."""
    floor = condition.get("host_floor")
    if floor is None:
        return None
    return float(1 - (1 - floor["over_500us_fraction"]) ** HOPS)


def _issue28_rows(name: str, condition: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 28's rows: missed deadlines against the same run's host floor (at most 2x under load), and the
    latched-truth check (the log's ``latched`` against the receiver's frames, every sample)."""
    bench = condition["bench"]
    fraction, estimate = bench["missed_deadline_fraction"], floor_estimate(condition)
    ratio = fraction / estimate if fraction is not None and estimate else None
    rows = [{"condition": name, "target": "missed deadlines / host-floor estimate <= 2", "bench": fraction,
             "peer": estimate, "ratio": ratio, "met": ratio is not None and ratio <= 2.0}]
    alone = condition.get("alone")
    if alone is not None:
        rounds = alone["rounds"]
        rows.append({"condition": name,
                     "target": f"SYNC lateness p99, producers alone, {len(rounds)} alternated rounds: python-can "
                     f"(chrt) / bench, not worse at {SIGNIFICANCE:g} (Wilcoxon: {alone['verdict']})",
                     "bench": _median_of(rounds, "bench"), "peer": _median_of(rounds, "python-can"),
                     "ratio": alone["median_ratio"], "met": alone["verdict"] in ("better", "inside the noise")})
    truth = bench.get("latched_truth")
    if truth is not None:
        rows.append({"condition": name, "target": "latched agrees with the wire on every sample",
                     "bench": f"{truth['agree']} of {truth['samples']}", "peer": None, "ratio": None,
                     "met": truth["samples"] > 0 and truth["agree"] == truth["samples"]})
    return rows


def _median_of(rounds: Sequence[dict[str, float | None]], name: str) -> float | None:
    values = [float(value) for r in rounds if (value := r[name]) is not None]
    return float(np.median(values)) if values else None


def _alone_lines(condition: dict[str, Any]) -> list[str]:
    """The alternated producers of a condition (:func:`_alternated`), if the run measured them."""
    alone = condition.get("alone")
    if alone is None:
        return []
    pairs = ", ".join(f"{_us(r['bench'])}/{_us(r['python-can'])}" for r in alone["rounds"])
    p_better, p_worse, ratio = alone["p_better"], alone["p_worse"], alone["median_ratio"]
    tests = "" if p_better is None else f"; Wilcoxon one-sided p: better {p_better:.3f}, worse {p_worse:.3f}"
    return [
        f"Producers alone, alternated ({len(alone['rounds'])} rounds of {alone['seconds']:g} s each, both "
        f"`chrt -f {PEER_FIFO}` with the PM QoS request: the bench's `drivers.sync_process` started by `ProcessSync` "
        f"as the bench starts it, and python-can's `send_periodic`): SYNC lateness p99 bench/python-can per round "
        f"{pairs} us; median ratio python-can/bench "
        f"{'-' if ratio is None else f'{ratio:.2f}'}{tests}: "
        f"**{alone['verdict']}**.",
        "",
    ]


def _dropped(count: int | None) -> str:
    return "an unknown number of datagrams (not recorded)" if count is None else f"{count} datagrams"


def _floor_latency(floor: dict[str, Any]) -> str:
    latency = floor.get("cpu_latency_us")
    return "" if latency is None else f", PM QoS {latency} us held"


def _privileges(peer: dict[str, Any]) -> str:
    """A peer row's label suffix: the privileges it ran with (none: a user's plain start)."""
    if not peer["sched_fifo"]:
        return ""
    latency = peer.get("cpu_latency_us")  # not recorded before session 11: none was held
    return f" (chrt -f {PEER_FIFO})" if latency is None else f" (chrt -f {PEER_FIFO}, PM QoS {latency} us)"


def _floor_lines(condition: dict[str, Any]) -> list[str]:
    """The host floor of a condition (:mod:`benchmarks.host_floor`), if the run measured it."""
    floor = condition.get("host_floor")
    if floor is None:
        return []
    steal = condition.get("steal_percent")
    return [
        f"Host floor (`benchmarks.host_floor`: a `chrt -f {host_floor.PROBE_FIFO}` process only waking on 1 ms "
        f"deadlines{_floor_latency(floor)}, {floor['wakeups']} wake-ups): lateness p50/p99/p99.9/max "
        f"{_us(floor['p50_us'])}/"
        f"{_us(floor['p99_us'])}/{_us(floor['p99_9_us'])}/{_us(floor['max_us'])} us; later than 0.5 ms "
        f"{100 * floor['over_500us_fraction']:.2f} %, later than 1 ms {100 * floor['over_1000us_fraction']:.2f} %. "
        f"CPU steal over the condition: {'-' if steal is None else f'{steal:.2f} %'} of the guest's CPU time. "
        # why 3: a cycle's command waits on three wake-ups in series (the emulator's receive of SYNC, the bench's
        # receive of the TPDO, the bench's loop), each of which may take half the period before anything runs
        f"A cycle waits on at least {HOPS} wake-ups in series (the emulator's receive, the bench's receive and "
        f"loop), so about {100 * (1 - (1 - floor['over_500us_fraction']) ** HOPS):.1f} % of cycles would miss "
        "their deadline from the host alone (an estimate: each hop later than half a period, independently).",
    ]


def cell(value: Any) -> str:
    """A target row's figure as the tables print it (``-`` for none)."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4f}" if value < 1 else f"{value:.1f}"
    return str(value)


def markdown(document: dict[str, Any]) -> str:
    """The "Realtime 1 kHz across processes" section of ``docs/benchmarks.md`` from a results document."""
    settings = document["settings"]
    lines = [
        "## Realtime 1 kHz across processes",
        "",
        f"`{document['command']}` ({document['date']}, {document['machine']['cpus']} CPUs, Python "
        f"{document['machine']['python']}, {document['seconds']:.0f} s): `{document['config']}` as shipped, "
        f"{settings['trials']} trials at time scale {settings['time_scale']}, peers {settings['peer_seconds']:g} s "
        "each; one private network namespace; SYNC seen by an independent receiver process (kernel timestamps).",
        "",
    ]
    for name, condition in document["conditions"].items():
        bench = condition["bench"]
        receiver, timing = bench["receiver"], bench["timing"]
        fraction = bench["missed_deadline_fraction"]
        lines += [
            f"### {name} (load average {condition['load_average_1min_before']:.1f} -> "
            f"{condition['load_average_1min_after']:.1f})",
            "",
            f"Bench: exit {bench['exit_code']}, {bench['trials_completed']} trials, {timing.get('cycles', 0)} cycles, "
            f"missed deadlines {timing.get('missed_deadlines', '-')} "
            f"({'-' if fraction is None else f'{100 * fraction:.2f} %'}), skipped slots "
            f"{timing.get('skipped_deadlines', '-')}, lost feedback {timing.get('missing_feedback', '-')}; feedback "
            f"latency p50/p99/max {_us(bench['feedback_latency_us']['p50'])}/{_us(bench['feedback_latency_us']['p99'])}"
            f"/{_us(bench['feedback_latency_us']['max'])} us; emulator answer p99 "
            f"{_us(receiver.get('emulator_answer_us', {}).get('p99'))} us; frames lost: SYNC "
            f"{receiver['syncs_lost']} (on the bench's log, received from the bus whoever sent it, not seen by the "
            "receiver), TPDO1 "
            f"{receiver['tpdo1_lost_to_bench']} (seen by the receiver, not logged by the bench; negative: the bench "
            f"logged more than the receiver saw); the receiver's socket dropped "
            f"{_dropped(receiver.get('receiver_dropped'))}.",
            "",
            "| SYNC producer | SYNCs | interval dev p50 (us) | p99 | max | lateness p99 (us) | empty slots | "
            "lateness p99 / bench's |",
            "|---|---|---|---|---|---|---|---|",
            _sync_row("bench (`foilc-hil run`)", receiver, receiver),
        ]
        lines += [
            _sync_row(f"{peer['peer']}{_privileges(peer)}", peer, receiver)
            for peer in condition["peers"]
        ]
        lines += ["", *_alone_lines(condition), *_floor_lines(condition), ""]
    lines += [
        "### Targets (issue 9)",
        "",
        "| condition | target | bench | peer | ratio | |",
        "|---|---|---|---|---|---|",
        *[
            f"| {row['condition']} | {row['target']} | {cell(row['bench'])} | {cell(row['peer'])} | "
            f"{cell(row['ratio'])} | {'met' if row['met'] else 'missed'} |"
            for row in targets(document)
        ],
        "",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
