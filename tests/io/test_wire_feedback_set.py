"""A cycle's feedback on the wire is the node's complete TPDO set in its SYNC window, as the master assembles it.

The drive answers each SYNC with two TPDOs (statusword + velocity, then torque + position: the default mapping).
Under load the emulator's thread can be preempted between them while the clock thread sends the next SYNC: the
velocity TPDO lands in the cycle's window, the other in the next one. The master's feedback is the whole set
(:meth:`drivers.master.cyclic.CyclicPath.on_tpdo`), so the loop, which waits until that next SYNC, held the last
good value and counted a lost feedback. ``replay --verify`` looked at the velocity TPDO alone, and where its value
happened to equal the held one (trial 1 of a run from rest is all zeros) counted the cycle answered:
``/ilc/trial lost_feedback is 11, the wire shows 8`` in ``tests/loop/test_latched_truth.py`` under load.
"""

from __future__ import annotations

import base64
from typing import Any

from drivers.cia301 import SYNC_COB_ID
from foilc_hil.logtools.wire import PdoField, WireMap, check_trial_wire, sync_windows

SCALE = 1000.0
TPDO1, TPDO2, RPDO1 = 0x181, 0x281, 0x201
WIRE = WireMap(
    target=PdoField(RPDO1, 16, 32, True, 6),
    velocity=PdoField(TPDO1, 16, 32, True, 6),
    tpdo_sizes={TPDO1: 6, TPDO2: 6},
    target_scale=SCALE,
    target_limit=1.0e4,
    velocity_scale=SCALE,
)


def _frame(cob: int, data: bytes = b"", direction: str = "rx") -> dict[str, Any]:
    return {"id": cob, "dir": direction, "data": base64.b64encode(data).decode()}


def _sync() -> dict[str, Any]:
    return _frame(SYNC_COB_ID, direction="tx")


def _tpdo1(velocity_raw: int) -> dict[str, Any]:
    return _frame(TPDO1, (0x1237).to_bytes(2, "little") + velocity_raw.to_bytes(4, "little", signed=True))


def _tpdo2() -> dict[str, Any]:
    return _frame(TPDO2, bytes(6))


def _rpdo() -> dict[str, Any]:
    return _frame(RPDO1, (0x000F).to_bytes(2, "little") + bytes(4), "tx")


def _check(frames: list[dict[str, Any]], inputs: list[float], lost: int) -> Any:
    """One trial of two samples (three cycles) from the first SYNC, zero commands, ``lost`` in its record."""
    record = {"trial": 1, "first_sync": 1, "lost_feedback": lost, "bad_frames": 0}
    return check_trial_wire(sync_windows(frames), record, inputs, [0.0, 0.0], WIRE)


# cycle 1's velocity TPDO before SYNC 2, its second TPDO after it (ahead of cycle 2's own set)
STRADDLING = [
    _sync(), _tpdo1(0), _tpdo2(), _rpdo(),
    _sync(), _tpdo1(0), _rpdo(),
    _sync(), _tpdo2(), _tpdo1(0), _tpdo2(), _rpdo(),
]


def test_a_set_straddling_the_next_sync_is_a_lost_feedback_even_where_its_velocity_is_the_held_one() -> None:
    # the loop held 0.0 for cycle 1 and counted it lost; the TPDO in the window says 0.0 too
    assert _check(STRADDLING, [0.0, 0.0, 0.0], lost=1) is None


def test_a_record_that_counts_the_straddling_set_answered_is_found() -> None:
    mismatch = _check(STRADDLING, [0.0, 0.0, 0.0], lost=0)
    assert mismatch is not None and mismatch.reason == "/ilc/trial lost_feedback is 0, the wire shows 1"


def test_the_feedback_is_the_first_complete_set_with_the_velocity_it_completed_with() -> None:
    # cycle 0: a velocity TPDO replaced before the set completes (7 -> 8), another after it (9): the master's
    # feedback is 0.008; cycle 1's second TPDO comes first, then its velocity completes the set
    frames = [
        _sync(), _tpdo1(7), _tpdo1(8), _tpdo2(), _tpdo1(9), _rpdo(),
        _sync(), _tpdo2(), _tpdo1(5), _rpdo(),
        _sync(), _tpdo1(5), _tpdo2(), _rpdo(),
    ]
    assert _check(frames, [0.008, 0.005, 0.005], lost=0) is None
    mismatch = _check(frames, [0.007, 0.005, 0.005], lost=0)
    assert mismatch is not None and (mismatch.sample, mismatch.on_wire) == (0, 0.008)
