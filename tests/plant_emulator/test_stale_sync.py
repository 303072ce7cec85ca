"""A realtime drive that handles a SYNC a period or more after it arrived leaves it unanswered (``device._stale``).

The answer would reach the master after the next SYNC, which would take it for that SYNC's: a velocity measured a
period earlier and a demand echo of an older command. The drive's lock is held across a whole period while a SYNC
waits (the emulator's process stalled); the SYNC is handled then, later than a period by construction (the wait can
only be longer on a loaded machine, never shorter), and must not be answered. A SYNC handled at once is.
"""

from __future__ import annotations

import time

import pytest

from plant_emulator.config import PlantConfig
from plant_emulator.settings import EmulatorConfig
from tests.support.emulator_harness import Harness

pytestmark = pytest.mark.timeout(120)

PERIOD = 0.5  # s: a fresh SYNC is handled well within it even on a loaded machine


def test_a_sync_handled_a_period_late_is_not_answered_and_a_fresh_one_is() -> None:
    settings = EmulatorConfig(timing="realtime", sync_loss_cycles=1000.0)
    with Harness(PlantConfig(model="first_order", a=-2.0, b=3.0, c=1.0), settings=settings,
                 cycle_period=PERIOD) as h:
        h.start()
        h.sync(wait_for=h.tpdo1)  # answered: handled at once
        answered = h.recorder.count(h.tpdo1)
        assert h.drive.stale_syncs == 0
        with h.drive._lock:  # the emulator's process stalls with a SYNC in its queue
            h.network.send_message(0x80, b"")
            time.sleep(2 * PERIOD)
        h._settle()  # everything sent so far is handled
        assert h.drive.stale_syncs == 1
        assert h.recorder.count(h.tpdo1) == answered  # no answer to the stale SYNC
        h.sync(wait_for=h.tpdo1)  # the next one, fresh, is answered
        assert h.drive.stale_syncs == 1
