"""One frame order across processes on ``udp_multicast`` (:mod:`drivers.send_order`): the channel's lock.

Every check here holds the lock file from a descriptor of its own -- as another process would -- and reads what a
send did: whether it ran with the lock held (a try-lock from a third descriptor is refused during it), and whether
it was counted unordered. No clock is read: the bound is a property of the code, not asserted as a speed.
"""

from __future__ import annotations

import fcntl
import itertools
import os
from pathlib import Path

import can
import pytest

from drivers.bus import FrameTap
from drivers.send_order import WAIT_BOUND, ChannelOrder, order_multicast_sends

_PORTS = itertools.count(47000)


def _locked_elsewhere(path: str) -> bool:
    """Whether another holder has ``path``'s lock (a try from a descriptor of our own is refused)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


@pytest.fixture
def order(tmp_path: Path) -> ChannelOrder:
    return ChannelOrder("239.74.163.20", next(_PORTS), directory=str(tmp_path))


def test_a_send_runs_with_the_channel_locked_and_releases_it(order: ChannelOrder) -> None:
    during: list[bool] = []
    order.send(lambda msg, timeout: during.append(_locked_elsewhere(order.path)), can.Message(), None)
    assert during == [True]
    assert not _locked_elsewhere(order.path)
    assert order.unordered == 0


def test_a_lock_held_past_the_bound_lets_the_frame_out_unordered_and_counted(order: ChannelOrder) -> None:
    holder = os.open(order.path, os.O_RDONLY)  # another process's hold, stopped (SIGSTOP) with it held
    fcntl.flock(holder, fcntl.LOCK_EX)
    sent: list[can.Message] = []
    try:
        order.send(lambda msg, timeout: sent.append(msg), can.Message(arbitration_id=0x80), None)
    finally:
        os.close(holder)  # the kernel releases a holder's lock with its descriptor (a process that died)
    assert [m.arbitration_id for m in sent] == [0x80] and order.unordered == 1
    order.send(lambda msg, timeout: sent.append(msg), can.Message(arbitration_id=0x201), None)
    assert len(sent) == 2 and order.unordered == 1  # released: ordered again
    assert 0 < WAIT_BOUND < 1e-3  # a quarter of a 1 kHz period at most on a SYNC


def test_after_a_wait_ran_out_the_next_sends_try_once_until_the_lock_is_free(
        order: ChannelOrder, monkeypatch: pytest.MonkeyPatch) -> None:
    tries: list[int] = []
    real = fcntl.flock

    def counted(fd: int, operation: int) -> None:
        if operation & fcntl.LOCK_EX:
            tries.append(fd)
        real(fd, operation)

    monkeypatch.setattr(fcntl, "flock", counted)
    holder = os.open(order.path, os.O_RDONLY)  # a holder stopped with the lock held
    real(holder, fcntl.LOCK_EX)
    try:
        order.send(lambda msg, timeout: None, can.Message(), None)
        first = len(tries)
        order.send(lambda msg, timeout: None, can.Message(), None)
        second = len(tries) - first
    finally:
        os.close(holder)
    assert first > 1 and second == 1 and order.unordered == 2  # the first waited (spun), the second did not
    order.send(lambda msg, timeout: None, can.Message(), None)
    assert order.unordered == 2  # seen free again: ordered
    holder = os.open(order.path, os.O_RDONLY)
    real(holder, fcntl.LOCK_EX)
    try:
        before = len(tries)
        order.send(lambda msg, timeout: None, can.Message(), None)
    finally:
        os.close(holder)
    assert len(tries) - before > 1  # and a new hold is waited for again


def test_an_exception_in_the_send_releases_the_lock(order: ChannelOrder) -> None:
    def failing(msg: can.Message, timeout: float | None) -> None:
        raise can.CanOperationError("failed to send via socket")

    with pytest.raises(can.CanOperationError):
        order.send(failing, can.Message(), None)
    assert not _locked_elsewhere(order.path)


def test_two_channels_have_two_locks(tmp_path: Path) -> None:
    a = ChannelOrder("239.74.163.20", 47100, directory=str(tmp_path))
    b = ChannelOrder("239.74.163.21", 47100, directory=str(tmp_path))
    c = ChannelOrder("239.74.163.20", 47101, directory=str(tmp_path))
    assert len({a.path, b.path, c.path}) == 3
    seen: list[bool] = []
    a.send(lambda msg, timeout: seen.append(_locked_elsewhere(b.path)), can.Message(), None)
    assert seen == [False]


def test_other_interfaces_are_left_as_python_can_made_them() -> None:
    with can.Bus(interface="virtual", channel="send-order-virtual") as bus:
        send = bus.send
        assert order_multicast_sends(bus) is None
        assert bus.send == send


def test_the_frame_tap_keeps_the_order_wrapper_when_it_detaches() -> None:
    with can.Bus(interface="virtual", channel="send-order-tap") as bus:
        calls: list[int] = []
        plain = bus.send

        def wrapper(msg: can.Message, timeout: float | None = None) -> None:  # as order_multicast_sends installs
            calls.append(msg.arbitration_id)
            plain(msg, timeout)

        bus.send = wrapper  # type: ignore[method-assign]
        tap = FrameTap()
        tap.attach(bus)
        tap.detach()
        assert bus.send is wrapper
        bus.send(can.Message(arbitration_id=0x80))
        assert calls == [0x80]
