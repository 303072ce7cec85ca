"""A synchronous in-process CAN transport: python-can's ``BusABC`` with delivery in the sender's thread.

python-can's ``virtual`` interface puts every frame on a queue per receiver; a :class:`can.Notifier` thread per
bus takes it off again. A lockstep loop between the bench and the embedded emulator therefore hands every frame
to another thread and waits for the answer, and those hand-offs were most of a lockstep cycle. This

interface (``inprocess``) keeps the frames, python-can's bus API and the CAN semantics, and removes the hand-offs:

- :class:`InProcessBus` is a ``BusABC``: the shared work (filters, ``recv``, periodic tasks, ``shutdown``) is
  python-can's; the backend fills :meth:`InProcessBus.send` and :meth:`InProcessBus._recv_internal`.
- A frame sent by one end is delivered to every other end of the same channel *before* ``send`` returns, in the
  sender's thread: to the end's :class:`InProcessNotifier` listeners if it has one, else to its receive queue
  (``recv``). Frames sent *during* a delivery (an SDO answer, a TPDO answering a SYNC) are queued and delivered in
  order by the same pump once the current delivery returns -- never recursively. One pump runs at a time per
  channel; a sender in another thread waits for it and then pumps its own frame (nothing is dropped).
- A *lockstep* channel (the default) has a :class:`LockstepClock`: simulated time that passes only when someone
  advances it (the emulator by one cycle period per SYNC, a master by its waits, see :func:`timebase_of`).
  Periodic tasks (``send_periodic``: the heartbeat producers) are timers on that clock, not threads, so a lockstep
  run in one process has no thread on the CAN path at all. A *wall* channel (``lockstep=False``) keeps
  python-can's thread-based periodic tasks and the wall clock.

Lock order: a listener runs in the pumping thread with whatever locks that thread holds, so a thread must not
hold a lock a listener of this channel takes while it waits to send from a *second* thread. In lockstep every
sender is the control thread (timers fire in whichever thread advances the clock), which is why the emulator's
supervision and heartbeat move onto the clock there instead of running in their own threads.

canopen's ``Network.connect`` always starts a thread-based ``can.Notifier``; :func:`connect_network` attaches an
:class:`InProcessNotifier` (python-can's ``Notifier`` with no reader thread) to an in-process bus instead.

The interface is registered for ``can.Bus(interface="inprocess")`` by the ``can.interface`` entry point in
``pyproject.toml``; :func:`drivers.bus.open_bus` builds it directly, so the product never depends on the entry
point being installed.
"""

from __future__ import annotations

import collections
import heapq
import itertools
import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import can
import canopen
from can.broadcastmanager import LimitedDurationCyclicSendTaskABC, ModifiableCyclicTaskABC, RestartableCyclicTaskABC

__all__ = [
    "INTERFACE",
    "WALL_CLOCK",
    "CanopenRoute",
    "InProcessBus",
    "InProcessNotifier",
    "LockstepClock",
    "Timebase",
    "connect_network",
    "subscribe_cyclic",
    "timebase_of",
]

logger = logging.getLogger(__name__)

INTERFACE = "inprocess"
"""The python-can interface name of :class:`InProcessBus`."""


# --- time -------------------------------------------------------------------------------------------------------


class Timebase(Protocol):
    """Where a CAN end's waits come from: the wall clock, or a lockstep channel's simulated time."""

    @property
    def synchronous(self) -> bool:
        """True when every answer to a frame is there once ``send`` returned (nothing arrives by waiting)."""
        ...

    def now(self) -> float:
        """Seconds, monotonic."""
        ...

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` pass."""
        ...


class _WallClock:
    """``time.monotonic`` / ``time.sleep``: frames arrive from other threads while one waits."""

    synchronous = False

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


WALL_CLOCK: Timebase = _WallClock()
"""The wall clock, for every bus but a lockstep in-process one."""


@dataclass(order=True)
class _Timer:
    due: float
    order: int
    period: float = field(compare=False)
    callback: Callable[[], None] = field(compare=False)
    cancelled: bool = field(default=False, compare=False)

    def cancel(self) -> None:
        """Never fire again."""
        self.cancelled = True


class LockstepClock:
    """Simulated time of a lockstep channel: it passes only in :meth:`advance_to` (and :meth:`sleep`).

    Timers (:meth:`every`) fire in due order, in the thread that advances the clock, with :meth:`now` equal to
    their due time; a timer that sends a frame therefore sends it synchronously (see the module docstring).
    """

    synchronous = True

    def __init__(self) -> None:
        self._now = 0.0
        self._timers: list[_Timer] = []
        self._order = itertools.count()
        self._lock = threading.Lock()  # guards the heap and _now; never held while a timer fires

    def now(self) -> float:
        """The simulated time, seconds since the channel opened."""
        return self._now

    def every(self, period: float, callback: Callable[[], None], *, first: float | None = None) -> _Timer:
        """Call ``callback()`` every ``period`` seconds of simulated time, first at ``first`` (default now+period)."""
        if not period > 0:
            raise ValueError(f"timer period must be positive, got {period!r}")
        with self._lock:
            timer = _Timer(self._now + period if first is None else first, next(self._order), period, callback)
            heapq.heappush(self._timers, timer)
        return timer

    def advance_to(self, when: float) -> None:
        """Let simulated time reach ``when`` (no-op if it is already later), firing every timer due by then."""
        while True:
            with self._lock:
                while self._timers and self._timers[0].cancelled:
                    heapq.heappop(self._timers)
                if not self._timers or self._timers[0].due > when:
                    if when > self._now:  # not max(): the common exit, once a cycle
                        self._now = when
                    return
                timer = heapq.heappop(self._timers)
                self._now = max(self._now, timer.due)
                timer.due += timer.period  # re-armed before it fires, so a callback may cancel it
                heapq.heappush(self._timers, timer)
            timer.callback()

    def sleep(self, seconds: float) -> None:
        """Advance by ``seconds`` (a wait in lockstep is time passing, not the host's)."""
        self.advance_to(self._now + max(seconds, 0.0))

    def wait_until(self, ready: Callable[[], bool], timeout: float) -> bool:
        """Advance timer by timer until ``ready()`` or ``timeout`` seconds of simulated time passed; ``ready()``."""
        deadline = self._now + timeout
        while not ready():
            if self._now >= deadline:
                return False
            with self._lock:
                live = [timer.due for timer in self._timers if not timer.cancelled]
            self.advance_to(min([deadline, *live]))
        return True


# --- the channel ------------------------------------------------------------------------------------------------


class _Channel:
    """The ends of one channel, the pump that delivers between them, and the channel's clock."""

    def __init__(self, name: str, clock: LockstepClock | None) -> None:
        self.name = name
        self.clock = clock
        self.ends: tuple[InProcessBus, ...] = ()  # replaced, never mutated: iterated without a lock
        self._pending: collections.deque[tuple[InProcessBus, can.Message]] = collections.deque()
        self._pump = threading.Lock()
        self._pumping: int | None = None  # the thread delivering right now

    def transmit(self, sender: InProcessBus, msg: can.Message) -> None:
        """Deliver ``msg`` to the other ends before returning (queued behind the delivery in progress, if any).

        What receivers get is one copy per frame (the sender may reuse or change its message), stamped now. Every
        slot of ``can.Message`` is set here without ``Message.__init__``, whose argument checks cost more than the
        copy itself on the hot path, and inline (four frames a cycle, a call each saved);

        ``tests/drivers/test_inprocess_bus.py`` fails if python-can adds a slot.
        """
        frame = _new_message(can.Message)
        frame.timestamp = _time()
        frame.arbitration_id = msg.arbitration_id
        frame.is_extended_id = msg.is_extended_id
        frame.is_remote_frame = msg.is_remote_frame
        frame.is_error_frame = msg.is_error_frame
        frame.channel = self.name
        frame.dlc = msg.dlc
        frame.data = bytearray(msg.data)
        frame.is_fd = msg.is_fd
        frame.is_rx = True
        frame.bitrate_switch = msg.bitrate_switch
        frame.error_state_indicator = msg.error_state_indicator
        me = _get_ident()
        if self._pumping == me:
            self._pending.append((sender, frame))  # sent by a listener: the running pump delivers it next
            return
        with self._pump:
            self._pumping = me
            try:
                # the frame itself first, then whatever its listeners sent meanwhile: the queue is for those only
                source, item = sender, frame
                pending = self._pending
                while True:
                    for end in self.ends:
                        if end is not source or end.receive_own_messages:
                            end._deliver(item)
                    if not pending:
                        break
                    source, item = pending.popleft()
            finally:
                self._pumping = None


_get_ident = threading.get_ident  # module-level names: the pump runs four times a cycle
_time = time.time
_new_message = can.Message.__new__


_channels: dict[str, _Channel] = {}
_channels_lock = threading.Lock()


# --- the bus ----------------------------------------------------------------------------------------------------


class InProcessBus(can.BusABC):
    """One end of an in-process channel (python-can interface ``inprocess``).

    Parameters
    ----------
    channel
        The channel name; every end opened with the same name in this process shares the frames.
    receive_own_messages
        Deliver this end's own frames back to it too.
    lockstep
        Used by the end that creates the channel: True (default) gives the channel a :class:`LockstepClock`
        (simulated time, periodic tasks on it); False keeps the wall clock and thread-based periodic tasks. An end
        joining an existing channel must ask for the same, or :class:`ValueError` says so.
    """

    def __init__(
        self, channel: str = "inprocess", receive_own_messages: bool = False, lockstep: bool = True, **kwargs: Any
    ) -> None:
        super().__init__(channel=channel, **kwargs)
        name = str(channel)
        with _channels_lock:
            shared = _channels.get(name)
            if shared is None:
                shared = _channels[name] = _Channel(name, LockstepClock() if lockstep else None)
            elif (shared.clock is not None) != lockstep:
                raise ValueError(f"in-process channel {name!r} is {'' if shared.clock else 'not '}lockstep")
            shared.ends = (*shared.ends, self)
        self._channel = shared
        self.channel_info = f"in-process channel {name}"
        self.receive_own_messages = receive_own_messages
        self._queue: collections.deque[can.Message] = collections.deque()
        self._arrived = threading.Condition()
        self._notifier: InProcessNotifier | None = None
        self._open = True

    @property
    def clock(self) -> LockstepClock | None:
        """The channel's simulated time (None on a wall-clock channel)."""
        return self._channel.clock

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Deliver ``msg`` to the other ends of the channel; they have it when this returns."""
        if not self._open:
            raise can.CanOperationError("Cannot operate on a closed bus")
        self._channel.transmit(self, msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._open:
            raise can.CanOperationError("Cannot operate on a closed bus")
        with self._arrived:
            if not self._queue and (timeout is None or timeout > 0):
                self._arrived.wait(timeout)
            return (self._queue.popleft() if self._queue else None), True  # filtered on delivery

    def _deliver(self, msg: can.Message) -> None:
        """Called by the pump: frames that pass the bus's filters (python-can's ``_matches_filters``, applied here
        as a controller's acceptance filter would) go to the notifier (a direct route of its, or its listeners),
        or onto the receive queue."""
        if self._filters is not None and not self._matches_filters(msg):
            return
        notifier = self._notifier
        if notifier is not None:
            route = notifier.routes.get(msg.arbitration_id)
            if route is None or msg.is_remote_frame or msg.is_error_frame:
                notifier.deliver(msg)
            elif not notifier._stopped:
                # InProcessNotifier.deliver_to, inlined: the cyclic frames (4 a cycle) save a call each
                try:
                    route(msg)
                except Exception as exc:
                    notifier.listener_failed(exc)
            return
        with self._arrived:
            self._queue.append(msg)
            self._arrived.notify()

    def _send_periodic_internal(
        self,
        msgs: Sequence[can.Message] | can.Message,
        period: float,
        duration: float | None = None,
        autostart: bool = True,
        modifier_callback: Callable[[can.Message], None] | None = None,
    ) -> can.broadcastmanager.CyclicSendTaskABC:
        clock = self._channel.clock
        if clock is None:
            return super()._send_periodic_internal(msgs, period, duration, autostart, modifier_callback)
        return LockstepCyclicTask(self, clock, msgs, period, duration, autostart, modifier_callback)

    def shutdown(self) -> None:
        """Stop the periodic tasks and leave the channel (the last end closes it)."""
        super().shutdown()
        if not self._open:
            return
        self._open = False
        with _channels_lock:
            self._channel.ends = tuple(end for end in self._channel.ends if end is not self)
            if not self._channel.ends and _channels.get(self._channel.name) is self._channel:
                del _channels[self._channel.name]


class LockstepCyclicTask(LimitedDurationCyclicSendTaskABC, ModifiableCyclicTaskABC, RestartableCyclicTaskABC):
    """``send_periodic`` on a lockstep channel: a timer on its clock, no thread (python-can's semantics: the first
    frame goes out at start, then one every ``period``; several messages take turns; ``duration`` bounds it)."""

    def __init__(
        self,
        bus: InProcessBus,
        clock: LockstepClock,
        messages: Sequence[can.Message] | can.Message,
        period: float,
        duration: float | None,
        autostart: bool,
        modifier_callback: Callable[[can.Message], None] | None,
    ) -> None:
        super().__init__(messages, period, duration)
        self._bus = bus
        self._clock = clock
        self._modifier = modifier_callback
        self._timer: _Timer | None = None
        self._index = 0
        if autostart:
            self.start()

    def start(self) -> None:
        """(Re)start: send now, then every period."""
        if self._timer is not None:
            return
        self.end_time = self._clock.now() + self.duration if self.duration else None
        self._timer = self._clock.every(self.period, self._fire, first=self._clock.now() + self.period)
        self._fire()

    def stop(self) -> None:
        """Send no more."""
        timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()

    def _fire(self) -> None:
        if self.end_time is not None and self._clock.now() >= self.end_time:
            self.stop()
            return
        message = self.messages[self._index]
        self._index = (self._index + 1) % len(self.messages)
        if self._modifier is not None:
            self._modifier(message)
        try:
            self._bus.send(message)
        except can.CanError as exc:  # a closed bus: the task ends, as python-can's thread does
            logger.debug("periodic 0x%X stopped: %s", self.arbitration_id, exc)
            self.stop()


# --- notifier ---------------------------------------------------------------------------------------------------


class InProcessNotifier(can.Notifier):
    """python-can's ``Notifier`` (listeners, one notifier per bus, ``on_error``, ``stop``) with no reader thread:
    the channel's pump calls :meth:`deliver` in the sending thread.

    A listener exception that no listener's ``on_error`` handles is kept in :attr:`exception` and ends the
    notification, as it ends python-can's reader thread; later frames go to the bus's receive queue.

    :attr:`routes` are the direct receive paths of the cyclic COB-IDs (:func:`subscribe_cyclic`): a data frame
    whose COB-ID has one goes to that one handler instead of through every listener; remote and error frames
    always take the listeners. Routes live as long as the notifier.
    """

    def __init__(self, bus: can.BusABC | list[can.BusABC], listeners: Iterable[can.notifier.MessageRecipient],
                 timeout: float = 1.0) -> None:
        self.routes: dict[int, Callable[[can.Message], None]] = {}
        super().__init__(bus, listeners, timeout)

    def add_bus(self, bus: can.BusABC) -> None:
        """Attach to an :class:`InProcessBus` (:class:`TypeError` for any other bus)."""
        if not isinstance(bus, InProcessBus):
            raise TypeError(f"InProcessNotifier serves in-process buses only, not {type(bus).__name__}")
        can.Notifier._registry.register(bus, self)
        self._bus_list.append(bus)
        bus._notifier = self

    def deliver(self, msg: can.Message) -> None:
        """Call every listener with ``msg`` (the pump's thread)."""
        self.deliver_to(self._on_message_received, msg)

    def deliver_to(self, handler: Callable[[can.Message], object], msg: can.Message) -> None:
        """Call ``handler(msg)`` (a route, or every listener) with the notifier's error handling."""
        if self._stopped:
            return
        try:
            handler(msg)
        except Exception as exc:  # a listener's bug must not break the sender: kept, like python-can's thread
            self.listener_failed(exc)

    def listener_failed(self, exc: Exception) -> None:
        """A listener or route raised ``exc``: keep it; unless an ``on_error`` handles it, stop notifying."""
        self.exception = exc
        if not self._on_error(exc):
            logger.error("in-process notifier stopped by a listener error: %r", exc)
            self._detach()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop notifying and call ``stop()`` on the listeners (``timeout`` unused: there is no thread)."""
        self._detach()
        super().stop(timeout)

    def _detach(self) -> None:
        self._stopped = True
        self.routes = {}
        for bus in self._bus_list:
            if isinstance(bus, InProcessBus) and bus._notifier is self:
                bus._notifier = None


def connect_network(network: canopen.Network) -> None:
    """``network.connect()``, but with an :class:`InProcessNotifier` (no thread) when its bus is in-process."""
    bus = network.bus
    if isinstance(bus, InProcessBus):
        # canopen types Network.listeners as list[MessageListener]; the Notifier takes any can.Listener
        network.notifier = InProcessNotifier(bus, network.listeners)
    else:
        network.connect()


class CanopenRoute:
    """A direct receive path into a canopen ``Network``: the frame to ``observer`` (the frame tap: traces stay
    causal, as with the tap first among the listeners), then to the callbacks subscribed to its COB-ID -- what
    canopen's ``Network.notify`` does, without the Notifier's listener chain, canopen's ``MessageListener`` and its
    node scanner on the way."""

    __slots__ = ("observer", "subscribers")

    def __init__(self, network: canopen.Network, observer: Callable[[can.Message], None] | None = None) -> None:
        self.subscribers = network.subscribers
        self.observer = observer

    def __call__(self, msg: can.Message) -> None:
        if self.observer is not None:
            self.observer(msg)
        can_id = msg.arbitration_id
        for callback in self.subscribers.get(can_id, ()):
            callback(can_id, msg.data, msg.timestamp)


def subscribe_cyclic(network: canopen.Network, can_id: int, callback: Callable[[int, bytearray, float], None],
                     *, observer: Callable[[can.Message], None] | None = None) -> None:
    """``network.subscribe(can_id, callback)`` for a cyclic COB-ID (PDO, SYNC): on a listening in-process bus the
    frames also get a direct route (:class:`CanopenRoute`), the rest of the traffic keeps the listeners.

    On any other bus, or before the network listens, this is ``network.subscribe``: the frames take canopen's
    generic path, with the same result. ``observer`` must be what the network's listeners show a frame to before
    canopen (the frame tap), so that nothing but the route changes.
    """
    network.subscribe(can_id, callback)
    notifier = network.notifier
    if isinstance(notifier, InProcessNotifier) and can_id not in notifier.routes:
        notifier.routes[can_id] = CanopenRoute(network, observer)


def timebase_of(bus: can.BusABC) -> Timebase:
    """The clock a CAN end waits on: the channel's :class:`LockstepClock` on a lockstep in-process bus, else
    :data:`WALL_CLOCK`."""
    clock = bus.clock if isinstance(bus, InProcessBus) else None
    return clock if clock is not None else WALL_CLOCK
