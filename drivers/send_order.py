"""One frame order for the simulated buses, as a CAN wire has: every receiver sees the frames in the same order.

A CAN bus serialises frames by arbitration, so every node sees one order, and "the RPDO came before the SYNC" is a
fact of the wire. The simulated buses have no wire:

- python-can's ``virtual`` copies a frame into each bus object's queue one after the other under no lock, so two
  threads sending at once reached two bus objects of one process in opposite orders (:func:`order_virtual_sends`);
- on ``udp_multicast``'s loopback, a datagram is delivered to every member socket by the sending CPU, inside its
  ``sendto``. Two processes sending on two CPUs within microseconds of each other -- the bench's RPDO and its SYNC
  producer's SYNC -- interleave those deliveries, so the bench read its RPDO's echo after the SYNC (the drive
  latched the old command) while an independent receiver read the RPDO first (the new one): the log and the
  receiver disagreed on one sample in two of five runs of the cross-process latched-truth test.

:class:`ChannelOrder` gives ``udp_multicast`` the wire's order: every bus object :func:`drivers.bus.open_bus` opens
on the channel takes one lock, shared across processes, around each ``sendto`` (an ``flock`` on a file named after
the group and port; the kernel releases it when its holder dies). A send then reaches every socket before the next
one starts. Waiting is bounded (:data:`WAIT_BOUND`): a holder stopped with the lock held (SIGSTOP between its
``sendto`` and its unlock: its frame is out already) must not stop SYNC, so past the bound the frame goes out
unordered and is counted (:attr:`ChannelOrder.unordered`); the wait spins, and after one that ran out the next
sends do not wait until the lock is seen free again. The one case it cannot cover: a loaded kernel that
defers the loopback's delivery to ``ksoftirqd``, after ``sendto`` returned.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
import threading
import time
import weakref
from typing import Any

import can

__all__ = ["WAIT_BOUND", "ChannelOrder", "multicast_channel", "order_multicast_sends", "order_virtual_sends"]

WAIT_BOUND = 50e-6
"""Seconds a send waits for the channel's lock before it goes out unordered. The order is at stake only while two
deliveries run at once on two CPUs, and a delivery runs in the kernel with bottom halves off (never preempted on a
kernel without PREEMPT_RT, where softirqs are threads): it lasts microseconds. A holder that keeps the lock longer
was preempted before its ``sendto`` (its frame will come after this one for every receiver) or after it (its frame
is everywhere already): either way one order. 250 us at first, a wait only the SYNC could pay for when a holder was
preempted with the lock; not seen to cost anything measurable (3 alternated full runs, SYNC lateness p99 73 / 102 /
43 us with the lock against 223 / 109 / 187 us without it)."""


def order_virtual_sends() -> None:
    """Give python-can's ``virtual`` interface the one frame order of a CAN bus (idempotent).

    Each send delivers to every queue under python-can's own lock of the channels (the one its open and shutdown
    hold while they change a channel's list of queues, which the send walks), so every bus object sees one order.
    Before, the loop's cyclic receiver (one bus object) saw SYNC ``n + 1`` before a TPDO and held the last
    feedback, while the frame tap (another) logged the TPDO in SYNC ``n``'s window: the record and ``replay
    --verify`` read two different wires (``/ilc/trial lost_feedback is 11, the wire shows 8`` under load).
    """
    from can.interfaces import virtual

    send = virtual.VirtualBus.send
    if getattr(send, "one_order", False):
        return

    def ordered_send(self: virtual.VirtualBus, msg: can.Message, timeout: float | None = None) -> None:
        with virtual.channels_lock:
            send(self, msg, timeout)

    ordered_send.one_order = True  # type: ignore[attr-defined]
    virtual.VirtualBus.send = ordered_send  # type: ignore[method-assign]


class ChannelOrder:
    """The cross-process lock of one ``udp_multicast`` channel (module docstring), held around each send.

    Parameters
    ----------
    group, port
        The channel: its multicast group and UDP port.
    directory
        Where the lock file lives (``/dev/shm`` where it exists: memory, never a disk).
    """

    def __init__(self, group: str, port: int, *, directory: str | None = None) -> None:
        where = directory or ("/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir())
        name = f"foilc-udp-multicast-{group.replace('/', '_')}-{port}.lock"
        self.path = os.path.join(where, name)
        # read-only is enough for flock, so a file another user created serves too
        self._fd = os.open(self.path, os.O_RDONLY | os.O_CREAT | os.O_CLOEXEC, 0o644)
        self._threads = threading.Lock()  # flock does not exclude two threads sharing this descriptor
        self.unordered = 0
        """Sends that went out without the lock (it was held past :data:`WAIT_BOUND`)."""
        self._stuck = False  # the last wait ran out: its holder is taken for stopped (see _acquire)
        self._closer = weakref.finalize(self, os.close, self._fd)

    def close(self) -> None:
        """Release the lock file's descriptor (idempotent)."""
        self._closer()

    def send(self, send: Any, msg: can.Message, timeout: float | None) -> None:
        """``send(msg, timeout)`` under the channel's lock (bounded wait, module docstring)."""
        with self._threads:
            held = self._acquire()
            try:
                send(msg, timeout)
            finally:
                if held:
                    fcntl.flock(self._fd, fcntl.LOCK_UN)
                else:
                    self.unordered += 1

    def _acquire(self) -> bool:
        """Take the lock: spin (no sleep: a wake-up on a loaded host can be late by milliseconds, which a SYNC
        cannot afford) up to :data:`WAIT_BOUND`; False past it. A holder that kept it past the bound once is taken
        for stopped: until the lock is seen free again each send tries once and goes (a SIGSTOPped bench held it
        for 30 ms: a wait at every SYNC meanwhile is no order gained)."""
        try_lock, fd, flags = fcntl.flock, self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB
        try:
            try_lock(fd, flags)
            self._stuck = False
            return True
        except BlockingIOError:
            if self._stuck:
                return False
        deadline = time.perf_counter() + WAIT_BOUND
        while time.perf_counter() < deadline:
            try:
                try_lock(fd, flags)
                return True
            except BlockingIOError:
                continue
        self._stuck = True
        return False


def multicast_channel(bus: can.BusABC) -> tuple[str, int] | None:
    """The group and UDP port of a python-can ``udp_multicast`` bus object; None for any other bus."""
    multicast = getattr(bus, "_multicast", None)  # python-can keeps udp_multicast's group and port there
    if type(bus).__name__ != "UdpMulticastBus" or multicast is None:
        return None
    return str(multicast.group), int(multicast.port)


def order_multicast_sends(bus: can.BusABC) -> ChannelOrder | None:
    """Make every send of a python-can ``udp_multicast`` bus object take its channel's :class:`ChannelOrder`; the
    order, or None when the bus is not one (or the lock file cannot be opened: it then sends as python-can does).
    The order's descriptor is closed with the bus object."""
    channel = multicast_channel(bus)
    if channel is None:
        return None
    try:
        order = ChannelOrder(*channel)
    except OSError:
        return None
    send = bus.send

    def ordered_send(msg: can.Message, timeout: float | None = None) -> None:
        order.send(send, msg, timeout)

    bus.send = ordered_send  # type: ignore[method-assign]
    with contextlib.suppress(TypeError):  # the order lives as long as the bus object
        weakref.finalize(bus, order.close)
    return order
