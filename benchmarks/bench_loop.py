"""Bench-loop benchmarks: lockstep cycles per second over the virtual bus, and the per-cycle hot-path cost with
and without logging.

Three measurements, each a short run of the real code:

``loop_only``
    :class:`foilc_hil.loop.bench.TrialLoop` against an in-memory drive (a first-order plant answering each SYNC at
    once, no CAN): the loop's own cost per cycle (law, clamp, safety, timing record).
``can_lockstep_no_log`` / ``can_lockstep_logged``
    :func:`foilc_hil.loop.rig.run_rig` over the embedded emulator (the in-process transport of
    :mod:`drivers.inprocess`, the CiA 402 master and the virtual drive in one thread), without a log and with the
    queued MCAP log. ``cycles_per_second`` is
    what the demo's sample-time choice rests on; ``compute_p50_us`` is the hot-path cost (feedback in -> command
    sent, including the frame tap's enqueue when logging).

Timings depend on the machine and its load; nothing here asserts them.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivers.cia402 import State402
from drivers.drive import Feedback


class InMemoryDrive:
    """A drive with no bus: a ZOH first-order plant that answers each SYNC at once, with the CAN loop's
    one-cycle delay (a target set now is applied at the next SYNC)."""

    bad_frames = 0  # no bus: nothing to decode

    def __init__(self, a: float, b: float, sample_time: float) -> None:
        self._ad = math.exp(a * sample_time)
        self._bd = (self._ad - 1.0) / a * b
        self._y = 0.0
        self._active = 0.0
        self._pending = 0.0
        self._count = 0
        self._feedback = Feedback(0, 0x27, State402.OPERATION_ENABLED, 0.0, 0.0, 0, 0.0)

    def sync(self) -> int:
        self._count += 1
        self._y = self._ad * self._y + self._bd * self._active
        self._active = self._pending
        self._feedback = Feedback(self._count, 0x27, State402.OPERATION_ENABLED, self._y, 0.0, 0, 0.0)
        return self._count

    def wait_feedback(self, timeout: float) -> Feedback:
        return self._feedback

    def set_target(self, value: float) -> float:
        self._pending = value
        return value

    def quick_stop(self) -> None:
        return None


def _first_order_config(sample_time: float, duration: float) -> Any:
    from foilc_hil.config import load_config

    return load_config(
        None,
        {
            "plant.model": "first_order",
            "plant.a": -1.23,
            "plant.b": 1.68,
            "sample_time": sample_time,
            "reference.profile": "piecewise",
            "reference.segments": [{"duration": duration, "start": 0.0, "end": 30.0}],
            "tuning.kp": 0.05,
            "tuning.r": 0.5,
            "bench.settle_time": 5 * sample_time,
            "bench.settle_tolerance": 0.05,
            "drive.velocity_scale": 1000.0,
            "drive.velocity_limit": 1.0e4,
            "drive.heartbeat_timeout_factor": 10.0,
            "drive.heartbeat_consumer_ms": 2000,
        },
    )


def loop_only(samples: int = 2000, trials: int = 5) -> dict[str, Any]:
    """The trial loop's own per-cycle cost (no CAN)."""
    from foilc_hil.config import LawKind
    from foilc_hil.design.models import DiscreteModel, Uncertainty
    from foilc_hil.design.ptype import p_type_default_gain
    from foilc_hil.design.record import Design
    from foilc_hil.laws.learning import PType
    from foilc_hil.loop.bench import TrialLoop
    from foilc_hil.loop.safety import CommandLimiter
    from foilc_hil.loop.settings import LoopSettings

    sample_time = 0.001
    a, b = -1.23, 1.68
    ad = math.exp(a * sample_time)
    bd = (ad - 1.0) / a * b
    A = np.array([[ad, bd], [0.0, 0.0]])
    B = np.array([[0.0], [1.0]])
    C = np.array([[1.0, 0.0]])
    reference = np.ones(samples)
    gamma = p_type_default_gain(A, B, C, 1)
    model = DiscreteModel(A, B, C, sample_time, input_delay=1, C_measured=C)
    design = Design(LawKind.P_TYPE, model, Uncertainty.none(2, 1), np.hstack([np.zeros((1, 2)), gamma]), 0.0, 1.0)
    law = PType(design, samples)
    loop = TrialLoop(
        InMemoryDrive(a, b, sample_time),
        law,
        reference,
        CommandLimiter(-1e6, 1e6),
        LoopSettings(sample_time=sample_time, settle_time=sample_time, settle_tolerance=1e9),
    )
    started = time.perf_counter()
    outcome = loop.run(trials)
    elapsed = time.perf_counter() - started
    assert outcome.timing is not None
    return {
        "cycles": loop.cycles,
        "cycles_per_second": loop.cycles / elapsed,
        "per_cycle_us": elapsed / loop.cycles * 1e6,
        "compute_p50_us": outcome.timing.compute_p50_us,
        "compute_p99_us": outcome.timing.compute_p99_us,
    }


def can_lockstep(logged: bool, *, sample_time: float = 0.005, duration: float = 2.0, trials: int = 5) -> dict[str, Any]:
    """Lockstep run over the embedded emulator (in-process transport), with or without the MCAP log."""
    from drivers.config import BusConfig
    from foilc_hil.loop.rig import RunRequest, run_rig
    from plant_emulator.device import TimingMode

    config = _first_order_config(sample_time, duration)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.mcap" if logged else None
        started = time.perf_counter()
        report = run_rig(
            RunRequest(
                config=config,
                out=out,
                law="foilc",
                trials=trials,
                mode=TimingMode.LOCKSTEP,
                bus=BusConfig(interface="embedded", channel="foilc-hil-bench"),
            )
        )
        elapsed = time.perf_counter() - started
        log_bytes = out.stat().st_size if out is not None else 0
    timing = report.outcome.timing
    assert timing is not None
    return {
        "cycles": timing.cycles,
        "cycles_per_second": timing.cycles_per_second,
        "wall_s_including_startup": elapsed,
        "cycle_time_p50_us": timing.cycle_time_p50_us,
        "cycle_time_p99_us": timing.cycle_time_p99_us,
        "compute_p50_us": timing.compute_p50_us,
        "compute_p99_us": timing.compute_p99_us,
        "log_bytes": log_bytes,
    }
