"""Where each microsecond of a lockstep cycle goes, before and after the lean cyclic path (issue 9, target 2).

One lockstep ``run_rig`` on the embedded emulator -- the PMSM axis at 1 ms (``configs/realtime_1khz.yaml`` in
lockstep, 1 s trials), the row judged against the goal in :mod:`benchmarks.bench_lockstep` -- is timed stage by stage:
every function of :data:`STAGES` is wrapped with a timer that books its *exclusive* time (its own, minus that of the
wrapped functions it calls) to its stage, on the control thread; ``TrialLoop.run`` is the root, so what no other
stage claims (the trial loop, its timing records, progress, the hand-off to the between-trial update) is the bench's
bookkeeping. The same run without the timers gives the cycle time they distort (each timer costs a fraction of a
microsecond, booked to the stage that calls it).

*Before* is the same measurement on the code of :data:`BASELINE_COMMIT` (main before this work, unpacked with
``git archive``); *after* is this tree. Each runs in its own process (``python benchmarks/bench_profile.py --tree
DIR``, the tree first on ``PYTHONPATH``), so both import their own ``drivers``, ``plant_emulator`` and ``foilc_hil``;
a stage whose functions a tree lacks is booked nothing there. Nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

BASELINE_COMMIT = "03b1f938e7ab579ea74f1e03f68bbc69988a5c45"
"""main before the lean cyclic path: the *before* column."""

ROOT_STAGE = "bench bookkeeping (trial loop, timing records, progress)"
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    # the master's cyclic path is drivers.master.cyclic.CyclicPath since issue 27 (Cia402Drive delegates to it); the
    # Cia402Drive names are what the baseline tree has
    ("master: RPDO and SYNC out (Cia402Drive, DriveNetwork)", (
        "drivers.cia402_master:Cia402Drive.set_target", "drivers.cia402_master:Cia402Drive.sync",
        "drivers.master.cyclic:CyclicPath.set_target", "drivers.master.cyclic:CyclicPath.sync",
        "drivers.network:DriveNetwork.sync",
    )),
    ("transport: in-process delivery (copy, filters, pump)", (
        "drivers.inprocess:InProcessBus.send", "drivers.inprocess:_Channel.transmit",
        "drivers.inprocess:InProcessBus._deliver", "drivers.inprocess:InProcessNotifier.deliver",
        "drivers.inprocess:InProcessNotifier.deliver_to",
    )),
    ("receive dispatch (python-can Notifier, canopen notify, routes, frame tap)", (
        "can.notifier:Notifier._on_message_received", "canopen.network:MessageListener.on_message_received",
        "canopen.network:Network.notify", "canopen.network:Network.send_message",
        "drivers.inprocess:CanopenRoute.__call__", "drivers.network:UnknownFrameCounter.on_message_received",
        "drivers.bus:FrameTap.on_message_received",
    )),
    ("lockstep clock: time and timers (heartbeats, supervision poll)", (
        "drivers.inprocess:LockstepClock.advance_to", "drivers.inprocess:LockstepClock.sleep",
        "plant_emulator.supervision:Supervisor.poll", "drivers.inprocess:LockstepCyclicTask._fire",
    )),
    ("emulator: SYNC consumer and PDO engine (RPDO latch, TPDO out)", (
        "plant_emulator.device:VirtualDrive._on_sync", "plant_emulator.pdo_engine:PdoEngine.on_rpdo",
        "plant_emulator.pdo_engine:PdoEngine.latch", "plant_emulator.pdo_engine:PdoEngine.send_synchronous",
        "plant_emulator.pdo_engine:PdoEngine.send_event_driven", "plant_emulator.node:EmulatedNode.transmit",
    )),
    ("emulator: 402 application (controlword, statusword)", (
        "plant_emulator.application:Cia402Application.react",
        "plant_emulator.application:Cia402Application.publish_status",
    )),
    ("emulator: physics tick (power stage, object store)", ("plant_emulator.motion:AxisPhysics.tick",)),
    ("plant step (compiled PMSM physics)", ("plant_emulator.physics.pmsm:PmsmPlant.step",)),
    ("master: feedback (TPDO decode, wait)", (
        "drivers.cia402_master:Cia402Drive._on_tpdo", "drivers.cia402_master:Cia402Drive.wait_feedback",
        "drivers.master.cyclic:CyclicPath.on_tpdo", "drivers.master.cyclic:CyclicPath.wait_feedback",
    )),
    ("learning law (command)", ("foilc_hil.laws.learning:LearningLaw.command",)),
    (ROOT_STAGE, ("foilc_hil.loop.bench:TrialLoop.run",)),
)


# --- the child: one tree, one run -------------------------------------------------------------------------------


class StageTimer:
    """Exclusive time per stage on one thread: a wrapped call books its time minus its wrapped callees'."""

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self.seconds: dict[str, float] = {}
        self._stack: list[float] = []
        self._thread = threading.get_ident()
        self._clock = clock

    def wrap(self, stage: str, function: Callable[..., Any]) -> Callable[..., Any]:
        """``function`` with its exclusive time booked to ``stage`` (other threads run it untimed)."""
        stack, seconds, clock, thread = self._stack, self.seconds, self._clock, self._thread
        seconds.setdefault(stage, 0.0)

        @functools.wraps(function)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if threading.get_ident() != thread:
                return function(*args, **kwargs)
            stack.append(0.0)
            started = clock()
            try:
                return function(*args, **kwargs)
            finally:
                elapsed = clock() - started
                seconds[stage] += elapsed - stack.pop()
                if stack:
                    stack[-1] += elapsed

        return timed


def _instrument(timer: StageTimer) -> list[tuple[object, str, Any]]:
    """Wrap every function of :data:`STAGES` the tree has (and its overrides in the same module); the undo list."""
    undo: list[tuple[object, str, Any]] = []
    for stage, targets in STAGES:
        for target in targets:
            module_name, qualname = target.split(":")
            class_name, method = qualname.split(".")
            try:
                module = importlib.import_module(module_name)
            except ImportError:
                continue
            base = getattr(module, class_name, None)
            if base is None:
                continue
            # type(c): a module may hold proxies whose attribute access raises (canopen's unassigned network)
            owners = [base, *(c for c in vars(module).values()
                              if issubclass(type(c), type) and c is not base and issubclass(c, base))]
            for owner in owners:
                if method in vars(owner):
                    original = vars(owner)[method]
                    undo.append((owner, method, original))
                    setattr(owner, method, timer.wrap(stage, original))
    return undo


def _runner() -> tuple[Any, Any]:
    """``run`` and its request type in the tree being profiled: the one rig, or the baseline's ``run_bench``."""
    try:
        from foilc_hil.loop import rig
    except ImportError:  # the baseline commit, before the one rig
        from foilc_hil.loop import bench

        return bench.run_bench, bench.RunRequest  # type: ignore[attr-defined]
    return rig.run_rig, rig.RunRequest


def _build_design() -> Any:
    """``build_design`` in the tree being profiled: ``loop.settings``'s, or the baseline's in ``loop.bench``."""
    try:
        from foilc_hil.loop import settings
    except ImportError:  # the baseline commit, before loop/settings.py
        from foilc_hil.loop import bench

        return bench.build_design  # type: ignore[attr-defined]
    return settings.build_design


def _run(trials: int = 3) -> tuple[int, float, float]:
    """One lockstep run of the PMSM axis at 1 ms: cycles, then seconds in ``TrialLoop.run`` (wall clock, and CPU
    time of the control thread: what a loaded machine leaves least distorted)."""
    from drivers.config import BusConfig
    from foilc_hil.config import load_config
    from foilc_hil.loop import bench
    from foilc_hil.references import trial_samples
    from plant_emulator.device import TimingMode

    config = load_config("configs/realtime_1khz.yaml", {
        "reference.profile": "piecewise",
        "reference.segments": [{"duration": 1.0, "start": 0.0, "end": 300.0}],
        "bench.mode": "lockstep",
        "emulator.timing": "lockstep",
        "bench.settle_time": 0.005,
        "drive.heartbeat_timeout_factor": 10.0,
        "drive.heartbeat_consumer_ms": 2000,
    })
    if not _DESIGN:  # made once per process, not timed: every run has the same config
        _DESIGN.append(_build_design()(config, "foilc", trial_samples(config.reference, config.sample_time)))
    design = _DESIGN[0]
    spent: list[tuple[float, float]] = []
    original = bench.TrialLoop.run

    def timed_run(loop: Any, count: int) -> Any:
        started, cpu = time.perf_counter(), time.thread_time()
        try:
            return original(loop, count)
        finally:
            spent.append((time.perf_counter() - started, time.thread_time() - cpu))

    run, request = _runner()
    bench.TrialLoop.run = timed_run  # type: ignore[method-assign,assignment]
    try:
        report = run(request(
            config=config, out=None, law="foilc", trials=trials, mode=TimingMode.LOCKSTEP, design=design, quiet=True,
            bus=BusConfig(interface="embedded", channel="profile")))
    finally:
        bench.TrialLoop.run = original  # type: ignore[method-assign]
    timing = report.outcome.timing
    if timing is None:
        raise RuntimeError("run_rig returned no timing summary")
    wall, cpu = spent[0]
    return timing.cycles, wall, cpu


_DESIGN: list[Any] = []


def child(repeats: int) -> dict[str, Any]:
    """This process's tree: the plain cycle time (median of ``repeats``) and the stage times of one timed run."""
    _run(trials=1)  # warm-up: imports, EDS, the design, numba's cache
    runs = [_run() for _ in range(repeats)]
    wall = sorted(seconds / cycles * 1e6 for cycles, seconds, _ in runs)
    cpu = sorted(seconds / cycles * 1e6 for cycles, _, seconds in runs)
    timer = StageTimer()
    undo = _instrument(timer)
    try:
        cycles, seconds, _ = _run()
    finally:
        for owner, method, original in reversed(undo):
            setattr(owner, method, original)
    return {
        "cycles": cycles,
        "cycle_us": wall[len(wall) // 2],
        "cycle_us_all": wall,
        "cycle_cpu_us": cpu[len(cpu) // 2],
        "cycle_cpu_us_all": cpu,
        "timed_cycle_us": seconds / cycles * 1e6,
        "stage_us": {stage: timer.seconds.get(stage, 0.0) / cycles * 1e6 for stage, _ in STAGES},
    }


# --- the parent: both trees, same run ---------------------------------------------------------------------------


def _profile_tree(tree: Path, repeats: int) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    result = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--tree", str(tree), "--repeats", str(repeats)],
        cwd=tree, env=env, capture_output=True, text=True, timeout=1200, check=False)
    if result.returncode != 0:
        raise RuntimeError(f"profile of {tree} failed: {result.stderr.strip().splitlines()[-1:]}")
    document: dict[str, Any] = json.loads(result.stdout)
    return document


def _baseline(directory: Path) -> Path | None:
    """:data:`BASELINE_COMMIT` unpacked into ``directory`` (None when git or the commit is not there)."""
    repo = Path(__file__).resolve().parents[1]
    archive = subprocess.run(["git", "-C", str(repo), "archive", "--format=tar", BASELINE_COMMIT],
                             capture_output=True, timeout=120, check=False)
    if archive.returncode != 0:
        return None
    tar_path = directory / "baseline.tar"
    tar_path.write_bytes(archive.stdout)
    with tarfile.open(tar_path) as tar:
        tar.extractall(directory / "tree", filter="data")
    return directory / "tree"


def collect(repeats: int = 3) -> dict[str, Any]:
    """The profile of the baseline (*before*) and of this tree (*after*), one after the other, with the load."""
    load_start = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="foilc-profile-") as directory:
        baseline = _baseline(Path(directory))
        before = _profile_tree(baseline, repeats) if baseline is not None else None
        after = _profile_tree(Path(__file__).resolve().parents[1], repeats)
    return {"baseline_commit": BASELINE_COMMIT, "before": before, "after": after,
            "stages": [stage for stage, _ in STAGES], "load_average": [load_start, os.getloadavg()[0]]}


def markdown(profile: dict[str, Any]) -> list[str]:
    """The "where each microsecond goes" table of :func:`collect`'s document."""
    before, after = profile["before"], profile["after"]

    def cell(side: dict[str, Any] | None, stage: str) -> str:
        return "-" if side is None else f"{side['stage_us'][stage]:.1f}"

    def total(side: dict[str, Any] | None, key: str) -> str:
        return "-" if side is None else f"{side[key]:.1f}"

    lines = [
        "| stage of one cycle | before (us/cycle) | after (us/cycle) |",
        "|---|---|---|",
        *(f"| {stage} | {cell(before, stage)} | {cell(after, stage)} |" for stage in profile["stages"]),
        f"| **sum, timed run** | {total(before, 'timed_cycle_us')} | {total(after, 'timed_cycle_us')} |",
        f"| **cycle without the timers (median, wall clock)** | {total(before, 'cycle_us')} | "
        f"{total(after, 'cycle_us')} |",
        f"| **cycle without the timers (median, CPU time of the control thread)** | "
        f"{total(before, 'cycle_cpu_us')} | {total(after, 'cycle_cpu_us')} |",
    ]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python benchmarks/bench_profile.py", description=__doc__)
    parser.add_argument("--tree", help="(internal) profile this tree in this process and print its JSON")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    if args.tree:
        print(json.dumps(child(args.repeats)))
        return 0
    profile = collect(args.repeats)
    print(json.dumps(profile, indent=2))
    print("\n".join(markdown(profile)), file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
