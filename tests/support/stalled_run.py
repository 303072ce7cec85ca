"""A realtime run with SYNC from a clock and a stalled loop, in this process (python-can ``virtual``): the set-up of
the latched-truth and demand-echo tests.

Two trials of a P-type law on a first-order plant at 5 ms, the bench's loop thread stalled for four periods at sample
:data:`STALLED` of trial 2 (``stall@2+10``) while its SYNC clock goes on, so the stalled command and the ones sent
catching up miss their SYNC. The bench's bus object gets its own frames back, as ``udp_multicast`` gives them: the
log then holds one stream in the bus's order (``logtools.wire.sync_windows``), which python-can's ``virtual``
otherwise lacks.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import can

from drivers.config import BusConfig
from foilc_hil.config import load_config
from foilc_hil.loop.rig import RunReport, RunRequest, run_rig
from plant_emulator.device import TimingMode
from plant_emulator.embedded import EmbeddedEmulator

TS = 0.005
SCALE = 1000.0  # drive.velocity_scale
STALLED = 10  # the sample of trial 2 whose cycle stalls


def stalled_config(**overrides: Any) -> Any:
    """The run's config, with dotted-key ``overrides`` (e.g. ``{"drive.demand_echo": True}``)."""
    return load_config(None, {
        "sample_time": TS, "trials": 2,
        "reference.profile": "piecewise", "reference.segments": [{"duration": 0.2, "start": 0.0, "end": 30.0}],
        "bench.settle_time": 5 * TS, "bench.mode": "realtime", "bench.settle_tolerance": 0.5,
        # the test's own process: no frozen collector, Python's switch interval (the clock is under test, not them)
        "bench.realtime.gc": "on", "bench.realtime.switch_interval": None,
        "bench.faults.lost_feedback": 1000, "emulator.sync_loss_cycles": 1000.0,
        "emulator.timing": "realtime",
        "drive.velocity_scale": SCALE, "drive.heartbeat_timeout_factor": 10.0, "drive.heartbeat_consumer_ms": 2000,
        "plant.model": "first_order", "plant.a": -1.23, "plant.b": 1.68, "drive.velocity_limit": 1.0e4,
        "law.kind": "p-type",
        "inject": [{"kind": "stall", "trial": 2, "cycle": STALLED, "duration": 4 * TS}],
        **overrides,
    })


def stalled_run(config: Any, out: Path) -> RunReport:
    """Run ``config`` against a realtime embedded emulator on its own ``virtual`` channel, logging to ``out``."""
    emulator = EmbeddedEmulator.from_config(config)
    with contextlib.ExitStack() as stack:
        emulator.drive.start(can.Bus(interface="virtual", channel=emulator.channel))
        stack.callback(emulator.drive.stop)
        bus = BusConfig(interface="virtual", channel=emulator.channel, receive_own_messages=True)
        return run_rig(RunRequest(config=config, out=out, mode=TimingMode.REALTIME, bus=bus))
