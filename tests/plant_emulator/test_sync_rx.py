"""The realtime drive's SYNC timing: the receive thread's window around the next SYNC (:mod:`plant_emulator.sync_rx`)
and the physics ticks kept mid-cycle (:func:`plant_emulator.motion.phased_tick`). Functional: no time is asserted."""

from __future__ import annotations

import itertools
import threading
import time

import can
import pytest

from drivers.cia301 import SYNC_COB_ID
from drivers.realtime import NOTIFIER_THREAD_PREFIX
from plant_emulator.config import PlantConfig
from plant_emulator.embedded import EmbeddedEmulator
from plant_emulator.motion import PHASE_MEMORY, phased_tick
from plant_emulator.settings import EmulatorConfig, EmulatorRealtimeConfig
from plant_emulator.sync_rx import LOST_PERIODS, SyncAnticipatingNotifier, sync_wait

P, M = 1.0, 0.2  # period and margin, in periods
_channels = itertools.count()


@pytest.mark.parametrize(("now", "wait"), [
    (0.3, 0.5),  # before the window of SYNC 1: block until it opens
    (0.8, 0.0), (1.0, 0.0), (1.15, 0.0),  # inside it: poll
    (1.5, 0.3),  # SYNC 1 did not come: block until the window of SYNC 2 opens
    (LOST_PERIODS - 0.1, 0.0),  # still expecting one
])
def test_the_window_around_the_next_sync(now: float, wait: float) -> None:
    assert sync_wait(now, 0.0, P, M) == pytest.approx(wait)


def test_no_window_once_syncs_stopped() -> None:
    assert sync_wait(LOST_PERIODS + 0.5, 0.0, P, M) is None


@pytest.mark.parametrize(("tick", "expected"), [(10.0, 10.5), (10.9, 10.5), (11.2, 11.5), (12.7, 12.5)])
def test_physics_ticks_move_to_mid_cycle(tick: float, expected: float) -> None:
    assert phased_tick(tick, 10.0, P, 0.5) == pytest.approx(expected)


def test_physics_keeps_its_own_grid_without_recent_syncs() -> None:
    assert phased_tick(3.3, None, P, 0.5) == 3.3
    assert phased_tick(10.0 + PHASE_MEMORY + 0.3, 10.0, P, 0.5) == 10.0 + PHASE_MEMORY + 0.3


def test_the_anticipating_thread_delivers_every_frame_and_catches_syncs_awake() -> None:
    """A window as wide as the period: every SYNC after the first finds the thread polling."""
    channel = f"sync-rx-test-{next(_channels)}"
    master = can.Bus(interface="virtual", channel=channel)
    drive_end = can.Bus(interface="virtual", channel=channel)
    received: list[int] = []
    done = threading.Event()

    class Listener(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            received.append(msg.arbitration_id)
            if len(received) == 10:
                done.set()

    notifier = SyncAnticipatingNotifier(drive_end, [Listener()], 0.1, margin=0.005, period=lambda: 0.01,
                                        sync_id=lambda: SYNC_COB_ID)
    try:
        assert any(t.name.startswith(NOTIFIER_THREAD_PREFIX) for t in notifier._readers  # the realtime setup's name
                   if isinstance(t, threading.Thread))
        for _ in range(5):
            master.send(can.Message(arbitration_id=0x205, data=b"\x0f\x00", is_extended_id=False))
            master.send(can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False))
            time.sleep(0.01)
        assert done.wait(5.0)
        assert received == [0x205, SYNC_COB_ID] * 5
        assert notifier.anticipated >= 1
    finally:
        notifier.stop()
        for end in (master, drive_end):
            end.shutdown()


@pytest.mark.slow
@pytest.mark.parametrize("margin", [0.0, 0.0002])
def test_a_realtime_drive_anticipates_sync_only_when_asked(margin: float) -> None:
    settings = EmulatorConfig(timing="realtime", realtime=EmulatorRealtimeConfig(sync_anticipation=margin))
    plant = PlantConfig(model="first_order", a=-1.23, b=1.68)
    with EmbeddedEmulator(plant, settings, node_id=(3, 4), sample_time=0.01) as emulator:
        notifiers = [drive.node.link.notifier for drive in emulator.drives if drive.node.link is not None]
        anticipating = [isinstance(notifier, SyncAnticipatingNotifier) for notifier in notifiers]
        assert anticipating == ([True, False] if margin else [False, False])  # one per process
    assert SyncAnticipatingNotifier.running() == 0
