"""python-can's ``virtual`` interface, as the bench uses it, delivers frames in one order to every bus object.

A CAN bus has one frame order. The bench reads it twice in one process: its cyclic receiver (the loop's view:
was this SYNC answered before the next one?) and the frame tap (the log, which ``replay --verify`` reads). When the
SYNC clock's thread and the emulator's thread sent at once, python-can's ``virtual`` could queue their frames in
opposite orders on the two bus objects, and the record disagreed with the log's wire
(``/ilc/trial lost_feedback is 11, the wire shows 8``). :mod:`drivers.bus` makes each send reach every queue before
another send begins.
"""

from __future__ import annotations

import itertools
import threading
from typing import Any

import can
from can.interfaces.virtual import VirtualBus

import drivers.bus  # noqa: F401  (importing it orders virtual sends: the bench always does)

_CHANNELS = itertools.count()
SYNC, TPDO = 0x080, 0x181


def _held_put(queue: Any, frame_id: int, arrived: threading.Event, release: threading.Event) -> None:
    """``queue``'s ``put`` of ``frame_id`` signals ``arrived`` and waits for ``release`` before it enqueues."""
    put = queue.put

    def held(item: can.Message, *args: Any, **kwargs: Any) -> None:
        if item.arbitration_id == frame_id:
            arrived.set()
            release.wait()
        put(item, *args, **kwargs)

    queue.put = held


def _signalled_put(queue: Any, frame_id: int, done: threading.Event) -> None:
    """``queue``'s ``put`` of ``frame_id`` signals ``done`` once it is enqueued."""
    put = queue.put

    def signalled(item: can.Message, *args: Any, **kwargs: Any) -> None:
        put(item, *args, **kwargs)
        if item.arbitration_id == frame_id:
            done.set()

    queue.put = signalled


def _ids(bus: can.BusABC) -> list[int]:
    ids = []
    while (msg := bus.recv(0.0)) is not None:
        ids.append(msg.arbitration_id)
    return ids


def test_two_threads_sending_at_once_reach_every_bus_object_in_one_order() -> None:
    channel = f"order-{next(_CHANNELS)}"
    clock, drive, loop, tap = (VirtualBus(channel=channel) for _ in range(4))
    try:
        # the clock's SYNC is queued on the loop's bus object, then held on its way to the tap's
        at_tap, release, tpdo_queued = threading.Event(), threading.Event(), threading.Event()
        _held_put(tap.queue, SYNC, at_tap, release)
        _signalled_put(loop.queue, TPDO, tpdo_queued)
        sync = threading.Thread(target=clock.send, args=(can.Message(arbitration_id=SYNC, data=b""),))
        sync.start()
        at_tap.wait()
        answer = threading.Thread(target=drive.send, args=(can.Message(arbitration_id=TPDO, data=b"\x01"),))
        answer.start()
        # unordered, the drive's TPDO overtakes the SYNC on the tap's queue now; ordered, it waits for the SYNC's
        # send to finish (the wait then runs out: the outcome is the same however long it is)
        tpdo_queued.wait(0.5)
        release.set()
        sync.join()
        answer.join()
        assert _ids(loop) == _ids(tap) == [SYNC, TPDO]
    finally:
        for bus in (clock, drive, loop, tap):
            bus.shutdown()
