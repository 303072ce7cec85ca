"""The cyclic frames received on the thread that waits for them: :class:`CyclicReceiver` (realtime bench).

A bus's Notifier thread receives every frame and hands a TPDO to the loop thread through a condition variable: two
wake-ups in series (the Notifier woken by the kernel, then the loop woken by the Notifier), each late by the host's
wake-up latency and by the wait for the GIL. In a realtime run the bench instead receives the cyclic TPDOs on its
loop thread itself: a second python-can bus object on the same interface and channel (python-can gives every bus
object its own copy of each frame on ``socketcan``, ``udp_multicast`` and ``virtual``) keeping the drives' TPDO
COB-IDs, polled with ``recv`` between SYNC and the feedback deadline. The Notifier keeps receiving every frame on
the first bus object (the frame tap, so the log is unchanged; EMCY, heartbeat, SDO), but no longer dispatches the
TPDOs: :class:`~drivers.network.DriveNetwork` routes them here instead. The COB-IDs are picked here, not by the
bus's ``can_filters``: on interfaces that filter in software (``udp_multicast``, ``virtual``) a non-blocking
``recv`` returns nothing when the first queued frame is filtered out, so a drain would stop at it.

Polling: ``recv`` is called non-blocking for the first ``spin`` seconds of a wait (the thread stays on the CPU and
keeps the GIL, so a frame arriving then costs no wake-up), then blocking for the rest (the kernel wakes the thread,
and it may then wait for the GIL the Notifier took to show the same frame to the tap: no faster than the
Notifier's hand-off, so a realtime bench spins). Frames still queued when the next SYNC is sent (they arrived after

their wait gave up) are dispatched first by :meth:`CyclicReceiver.drain`, so they answer the cycle they belong to,
never the next one.

Thread safety: :meth:`route`, :meth:`poll`, :meth:`drain` and :meth:`close` run on the one control thread; the
callbacks run there too, and take their drive's lock as they do on the Notifier thread.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import can

from drivers.bus import open_bus
from drivers.config import BusConfig
from drivers.inprocess import INTERFACE as INPROCESS_INTERFACE
from drivers.realtime import CyclicReceive

__all__ = ["CyclicReceive", "CyclicReceiver", "open_cyclic_receiver"]

Callback = Callable[[int, bytearray, float], None]


class CyclicReceiver:
    """Receives the routed COB-IDs on a bus object of their own, on the calling thread.

    Parameters
    ----------
    bus
        A second bus object on the network's interface and channel; owned: :meth:`close` shuts it down.
    spin
        Seconds from the start of each wait for feedback spent in non-blocking ``recv`` calls before blocking ones.
    """

    def __init__(self, bus: can.BusABC, spin: float = 0.0) -> None:
        if not spin >= 0:
            raise ValueError(f"spin must be >= 0 s, got {spin!r}")
        self.bus = bus
        self.spin = float(spin)
        self._routes: dict[int, Callback] = {}
        self.frames = 0  # routed frames dispatched
        self._held: can.Message | None = None  # received, not dispatched yet (dispatch_until stopped before it)

    def route(self, can_id: int, callback: Callback) -> None:
        """Dispatch frames with ``can_id`` to ``callback`` from now on (other frames are dropped)."""
        self._routes[can_id] = callback

    def unroute(self, can_id: int) -> None:
        """Stop dispatching ``can_id`` (idempotent)."""
        self._routes.pop(can_id, None)

    @property
    def routes(self) -> frozenset[int]:
        """The COB-IDs received here."""
        return frozenset(self._routes)

    def poll(self, timeout: float, spin_until: float = 0.0) -> bool:
        """Receive one frame within ``timeout`` seconds and dispatch it; False when none came or it is not routed.

        Until ``spin_until`` (``time.monotonic()``; a wait sets it to its start plus :attr:`spin`) ``recv`` does not
        block.
        """
        if self._held is not None:
            held, self._held = self._held, None
            return self._dispatch(held)
        recv = self.bus.recv
        now = time.monotonic()
        if now < spin_until:
            end = now + timeout
            while now < spin_until:
                msg = recv(0.0)
                if msg is not None:
                    return self._dispatch(msg)
                now = time.monotonic()
            timeout = end - now
            if timeout <= 0.0:
                return False
        msg = recv(timeout)
        return msg is not None and self._dispatch(msg)

    def drain(self) -> bool:
        """Dispatch every frame already received (before a new cycle begins they answer the old one; at the end of
        a wait, e.g. one given no time at all, they may complete it); True when any was routed."""
        routed = False
        if self._held is not None:
            held, self._held = self._held, None
            routed = self._dispatch(held)
        recv = self.bus.recv
        while (msg := recv(0.0)) is not None:
            routed = self._dispatch(msg) or routed
        return routed

    def dispatch_until(self, done: Callable[[], bool], stop_id: int) -> bool | None:
        """Dispatch the frames already received, in order, until ``done()`` holds (True) or the next frame has
        ``stop_id`` (kept, undispatched, for the next :meth:`poll` or :meth:`drain`: False); None when the queue ran
        dry first. Which came first on the bus, an echo ``done`` waits for or a frame ``stop_id``, read no further."""
        recv = self.bus.recv
        while not done():
            msg = self._held if self._held is not None else recv(0.0)
            self._held = None
            if msg is None:
                return None
            if msg.arbitration_id == stop_id and not msg.is_error_frame:
                self._held = msg
                return False
            self._dispatch(msg)
        return True

    def _dispatch(self, msg: can.Message) -> bool:
        callback = self._routes.get(msg.arbitration_id)
        if callback is None or msg.is_error_frame or msg.is_remote_frame:
            return False  # the bench's own SYNC and RPDO, heartbeats, other nodes' frames: the Notifier has them
        self.frames += 1
        callback(msg.arbitration_id, msg.data, msg.timestamp)
        return True

    def close(self) -> None:
        """Shut the receiving bus object down (idempotent)."""
        self._routes.clear()
        self.bus.shutdown()


def open_cyclic_receiver(bus_cfg: BusConfig, spin: float) -> CyclicReceiver | None:
    """A :class:`CyclicReceiver` on a second bus object of ``bus_cfg``, or None where there cannot be one.

    The in-process transport has none: its frames are delivered to its one receive path inside ``send``.
    """
    if bus_cfg.interface in (INPROCESS_INTERFACE, "embedded"):
        return None
    return CyclicReceiver(open_bus(bus_cfg), spin)
