"""One CAN bus shared by several CiA 402 drives: :class:`DriveNetwork`.

A bus carries one receive path (python-can allows one Notifier per bus), one SYNC producer and one master
heartbeat, whatever the number of drives on it. :class:`DriveNetwork` owns those: one canopen ``Network`` (its
Notifier, or the thread-less :class:`~drivers.inprocess.InProcessNotifier` on the in-process transport, dispatches
every received frame by COB-ID to the node that subscribed to it), one :class:`~drivers.bus.FrameTap`, one counter of
frames nobody subscribed to, one SYNC and one :class:`~drivers.heartbeat.HeartbeatProducer`. Drives join it with
:meth:`drivers.cia402_master.Cia402Drive.on_network`; a drive built alone (``Cia402Drive.open``) gets a private one,
so the single-drive path is the one-member case of the same code.

Cyclic receiver (realtime bench): with a :class:`~drivers.cyclic_rx.CyclicReceiver` the members' TPDOs are received
on the control thread that waits for them (see :mod:`drivers.cyclic_rx`) instead of being dispatched by the
Notifier, which still shows them to the frame tap; their COB-IDs stay subscribed (to :func:`received_elsewhere`) so
the count of unknown frames is unchanged.

SYNC: :meth:`DriveNetwork.sync` first starts a new cycle on every member (each drive's TPDO set from then on answers
it), then sends one SYNC frame. On a synchronous (lockstep) bus one cycle period of simulated time passes since the
previous SYNC first, as for a single drive.

SYNC from a clock (realtime, :mod:`drivers.sync_clock`): between :meth:`DriveNetwork.start_clock` and
:meth:`DriveNetwork.stop_clock` a producer of its own sends SYNC (the kernel's broadcast manager on ``socketcan``, a
process of its own on ``udp_multicast``, :mod:`drivers.sync_process`, a thread elsewhere) and
:meth:`DriveNetwork.sync` sends none. The control thread reads the bus instead, on its cyclic
receiver, in the order the bus delivered it: each SYNC's echo starts a new cycle on every member (so a TPDO answers
the SYNC before it on the wire, as ``replay --verify`` cuts the log), and each member's own RPDO echo is what the
drive latches at the next SYNC (:attr:`drivers.master.cyclic.CyclicPath.latched`). :meth:`DriveNetwork.await_sync`
waits for the next SYNC's echo. Every SYNC goes out under canopen's send lock, as every RPDO of the master does, and
is counted there (:attr:`DriveNetwork.syncs_sent`): the count an RPDO was sent at says whether it went out before or
after the next SYNC.

Thread safety: :meth:`join`, :meth:`sync`, :meth:`listen` and :meth:`close` are called from the one control thread;
the receive callbacks run on the Notifier thread and belong to the drives (see ``drivers.cia402_master``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import can
import canopen

from drivers.bus import FrameTap
from drivers.cia301 import SYNC_COB_ID
from drivers.cyclic_rx import CyclicReceiver
from drivers.errors import ConfigError, DriveError
from drivers.heartbeat import HeartbeatProducer
from drivers.inprocess import connect_network, subscribe_cyclic, timebase_of
from drivers.scan import ScanResult, scan_bus
from drivers.send_order import multicast_channel
from drivers.sync_clock import BroadcastSync, SyncClock, SyncProducer
from drivers.sync_process import ProcessSync

__all__ = ["DriveNetwork", "SyncSeen", "UnknownFrameCounter", "received_elsewhere"]

Callback = Callable[[int, bytearray, float], None]

NOTIFIER_CYCLE = 0.1  # s the Notifier blocks in recv(): bounds how long close() waits for its thread


def received_elsewhere(can_id: int, data: bytearray, timestamp: float) -> None:
    """The Notifier's subscriber of a COB-ID the cyclic receiver owns: the frame is known (not counted as
    unknown) and handled on the control thread, not here."""


class SyncSeen(NamedTuple):
    """One SYNC of the clock, as the control thread read it from the bus (:meth:`DriveNetwork.await_sync`).

    Attributes
    ----------
    number
        The network's count of SYNCs, this one included (the members' cycle it began).
    time
        When it went out (``perf_counter`` seconds): the producer's record, else its echo's bus timestamp.
    due
        Its deadline (``perf_counter``); NaN where the producer keeps none (the broadcast manager).
    skipped
        Slots the producer passed over just before it.
    """

    number: int
    time: float
    due: float
    skipped: int


class UnknownFrameCounter(can.Listener):
    """Counts received frames whose COB-ID no canopen subscriber handles (ignored otherwise)."""

    def __init__(self, network: canopen.Network) -> None:
        self._network = network
        self.count = 0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id not in self._network.subscribers and not msg.is_error_frame:
            self.count += 1


class DriveNetwork:
    """One bus, one receive path, one SYNC producer and one master heartbeat for any number of drives.

    Construction is inert (nothing is sent, no thread starts); :meth:`listen` starts the receive path. The bus
    belongs to the caller: :meth:`close` stops the receive path and the heartbeat, never the bus.

    Parameters
    ----------
    bus
        The python-can bus every member drive is on.
    receiver
        Receives the members' TPDOs on the control thread (realtime bench); None: the Notifier dispatches them.
        It belongs to the caller, as the bus does.
    """

    def __init__(self, bus: can.BusABC, receiver: CyclicReceiver | None = None) -> None:
        self.bus = bus
        self.receiver = receiver
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
        self.tap = FrameTap()
        self.unknown = UnknownFrameCounter(self.network)
        # canopen annotates Network.listeners as list[MessageListener]; the Notifier takes any can.Listener.
        # The tap goes first so a received frame is shown before canopen dispatches it: traces stay causal.
        self.network.listeners.insert(0, self.tap)  # type: ignore[arg-type]
        self.network.listeners.append(self.unknown)  # type: ignore[arg-type]
        self.timebase = timebase_of(bus)
        self._members: list[Callable[[], None]] = []
        self._sync_message = can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)
        self._sync_at = -math.inf  # lockstep: the simulated time of the last SYNC
        self._producer: HeartbeatProducer | None = None
        self._master_node_id: int | None = None
        #: SYNCs sent on this network (by :meth:`sync` or the clock), counted under canopen's send lock
        self.syncs_sent = 0
        #: SYNC echoes the control thread read while the clock runs, on the numbering of :attr:`syncs_sent`
        self.syncs_seen = 0
        self._clock: SyncClock | None = None
        self._echo_routes: tuple[int, ...] = ()
        self._seen_time = math.nan  # the last SYNC echo's time (perf_counter), from its bus timestamp
        self._process_sync: ProcessSync | None = None  # started with the receive path, waiting for start_clock
        self._last_due = math.nan  # the slot of the last SYNC a producer process sent (await_sync)

    @property
    def listening(self) -> bool:
        """True between :meth:`listen` and :meth:`close`."""
        return self.network.notifier is not None

    def subscribe_cyclic(self, can_id: int, callback: Callable[[int, bytearray, float], None]) -> None:
        """``network.subscribe`` for a cyclic COB-ID (a member's TPDO): on a listening in-process bus its frames
        take a direct route to the frame tap and the subscribers (:func:`drivers.inprocess.subscribe_cyclic`); with
        a cyclic receiver they are received on the control thread (the Notifier only shows them to the tap)."""
        if self.receiver is not None:
            self.receiver.route(can_id, callback)
            self.network.subscribe(can_id, received_elsewhere)
            return
        subscribe_cyclic(self.network, can_id, callback, observer=self.tap.on_message_received)

    def unsubscribe_cyclic(self, can_id: int, callback: Callable[[int, bytearray, float], None]) -> None:
        """Undo :meth:`subscribe_cyclic` (the frames with ``can_id`` no longer reach ``callback``)."""
        if self.receiver is not None and can_id in self.receiver.routes:
            self.receiver.unroute(can_id)
            self.network.unsubscribe(can_id, received_elsewhere)
        else:
            self.network.unsubscribe(can_id, callback)

    def join(self, begin_cycle: Callable[[], None]) -> None:
        """Register a member: ``begin_cycle()`` runs before every SYNC (the member's new cycle starts)."""
        self._members.append(begin_cycle)

    def leave(self, begin_cycle: Callable[[], None]) -> None:
        """Unregister a member (idempotent)."""
        self._members = [member for member in self._members if member is not begin_cycle]

    def listen(self) -> None:
        """Attach the frame tap and start the one receive path (idempotent).

        Raises :class:`~drivers.errors.DriveError` when the bus already has a Notifier (another owner).
        """
        if self.listening:
            return
        self.tap.attach(self.bus)
        try:
            connect_network(self.network)
        except ValueError as exc:  # python-can allows one active Notifier per bus
            self.tap.detach()
            raise DriveError(f"cannot listen on the bus: {exc}; one DriveNetwork must own the bus's Notifier "
                             "(drives share it with Cia402Drive.on_network; add_frame_listener sees frames)") from exc
        if self.receiver is not None and self._process_sync is None:  # a realtime bench's: see drivers.sync_process
            self._process_sync = self._spawn_process_sync()

    def scan(self, nodes: Sequence[int] = range(1, 128), *, listen: float = 1.2, nmt_reset: bool = False,
             sdo_timeout: float = 0.3) -> ScanResult:
        """Discover the CANopen nodes on this network's bus (:func:`drivers.scan.scan_bus`), before it listens.

        Parameters
        ----------
        nodes
            Node ids to look for (1..127).
        listen
            Seconds to listen to heartbeats and boot-ups (lockstep time on the embedded emulator's bus).
        nmt_reset
            Broadcast NMT reset communication first (resets every node's communication parameters).
        sdo_timeout
            Seconds to wait for the SDO probe's answers and each identity read.

        Returns
        -------
        ScanResult
            Every node found, sorted by node id, with identity and NMT state.

        Raises
        ------
        DriveError
            The network already listens (python-can allows one receive path per bus: scan first), or a frame
            cannot be sent.
        """
        if self.listening:
            raise DriveError("scan before listen: the network's receive path owns the bus")
        return scan_bus(self.bus, nodes=nodes, listen=listen, nmt_reset=nmt_reset, sdo_timeout=sdo_timeout)

    def start_master_heartbeat(self, master_node_id: int, period: float) -> None:
        """Start the master's heartbeat once for the whole bus (idempotent for the same master node id).

        Raises :class:`~drivers.errors.ConfigError` when a member asks for another master node id: one master
        sends one heartbeat.
        """
        if self._producer is not None:
            if master_node_id != self._master_node_id:
                raise ConfigError(f"must be the same for every drive on one bus ({self._master_node_id}), got "
                                  f"{master_node_id}", key="drive.master_node_id")
            return
        self._producer = HeartbeatProducer(self.bus, master_node_id, period)
        self._master_node_id = master_node_id
        self._producer.start()

    def sync(self, sample_time: float) -> None:
        """Start a new cycle on every member, then send one SYNC.

        On a synchronous bus ``sample_time`` seconds of simulated time pass since the previous SYNC first (the
        drives' and the master's heartbeat timers fire on the way), and the answering TPDOs are in on return.
        """
        if self._clock is not None:  # the clock sends SYNC: its next one latches what was sent meanwhile
            return
        timebase = self.timebase
        if timebase.synchronous:
            timebase.sleep(self._sync_at + sample_time - timebase.now())
            self._sync_at = timebase.now()
        if self.receiver is not None:  # late answers of the old cycle are its own, not the new one's
            self.receiver.drain()
        for begin_cycle in self._members:
            begin_cycle()
        # sent outside any drive's lock: on a synchronous bus the answers are delivered inside send, possibly by
        # another thread's pump, whose listeners take the drives' locks
        with self.network.send_lock:
            self.bus.send(self._sync_message)
            self.syncs_sent += 1

    # --- SYNC from a clock (realtime) --------------------------------------------------------------------------

    @property
    def clock(self) -> SyncClock | None:
        """The running SYNC clock, or None."""
        return self._clock

    def start_clock(self, period: float, echoes: Mapping[int, Callback], *, spin_margin: float = 0.0) -> SyncClock:
        """SYNC from a clock from now on (module docstring): the broadcast manager on ``socketcan``, a producer
        process on ``udp_multicast`` (:class:`~drivers.sync_process.ProcessSync`), else a thread.

        Parameters
        ----------
        period
            Seconds between SYNCs.
        echoes
            The members' RPDO COB-IDs and each one's echo handler (what its drive latches at the next SYNC).
        spin_margin
            The producer thread's spin before each SYNC is due, seconds (0: it sleeps to the deadline; its spin holds
            the GIL the other threads of the process wait for).

        Raises
        ------
        DriveError
            Without a cyclic receiver (the control thread reads the bus on it), or with a clock already running.
        """
        receiver = self.receiver
        if receiver is None:
            raise DriveError("SYNC from a clock needs the control thread's own receiver "
                             "(bench.realtime.cyclic_receive: loop, and no injected bus fault)")
        if self._clock is not None:
            raise DriveError("the SYNC clock is already running")
        receiver.drain()  # what came before is the old cycles' (the echoes of the SYNCs sent so far are dropped)
        receiver.route(SYNC_COB_ID, self._on_sync_echo)
        for cob, callback in echoes.items():
            receiver.route(cob, callback)
        self._echo_routes = tuple(echoes)
        self.syncs_seen = self.syncs_sent
        clock: SyncClock
        process, self._process_sync = self._process_sync, None
        if process is None:
            process = self._spawn_process_sync()
        if type(self.bus).__name__ == "SocketcanBus":  # python-can's socketcan bus: the kernel holds the period
            clock = BroadcastSync(self.bus, self._sync_message, period)
        elif process is not None:  # across processes: a process of its own
            process.start(period)
            clock = process
            self._last_due = math.nan
        else:
            producer = SyncProducer(self._clock_send, period, spin_margin=spin_margin)
            producer.start()
            clock = producer
        self._clock = clock
        return clock

    @property
    def counts_on_echo(self) -> bool:
        """True while the running clock's SYNCs are counted as their echoes are read (the broadcast manager, a
        process): a frame sent now goes out after SYNCs this process has not read yet, so which SYNC it follows is
        known only from its own echo's place among them (:meth:`echo_before_sync`)."""
        return isinstance(self._clock, BroadcastSync | ProcessSync)

    def echo_before_sync(self, echoed: Callable[[], bool]) -> bool | None:
        """Whether the echo of a frame just sent (``echoed()`` turns true once its handler saw it) came before the
        next SYNC on the bus: the frames before it are dispatched in bus order, a SYNC echo before it is kept for
        :meth:`await_sync` (none is read past, so every cycle still begins at its own SYNC); None when its echo is
        not in yet. On the loopback of ``udp_multicast`` and ``vcan`` a frame sent is queued on every socket before
        its send returns."""
        if self.receiver is None:
            return None
        return self.receiver.dispatch_until(echoed, SYNC_COB_ID)

    def _spawn_process_sync(self) -> ProcessSync | None:
        """A SYNC producer process on this network's ``udp_multicast`` channel, ready and not started; None on any
        other interface."""
        channel = multicast_channel(self.bus)
        if channel is None:
            return None
        group, port = channel
        return ProcessSync("udp_multicast", group, port=port)

    def stop_clock(self) -> None:
        """Stop the clock (idempotent): no SYNC goes out after this returns, and :meth:`sync` sends them again."""
        clock, self._clock = self._clock, None
        if clock is None:
            return
        clock.stop()
        receiver = self.receiver
        if receiver is not None:
            receiver.unroute(SYNC_COB_ID)
            for cob in self._echo_routes:
                receiver.unroute(cob)
        self._echo_routes = ()

    def await_sync(self, after: int, timeout: float) -> SyncSeen:
        """The SYNC after SYNC ``after``, read from the bus on the control thread (frames before it dispatched in
        order: the members' TPDOs and RPDO echoes). Blocks in the kernel's receive, never spins: the producer thread
        needs the GIL when the SYNC is due, and the loop has the rest of the period after it.

        Raises :class:`DriveError` when none came within ``timeout`` seconds (the clock stopped; its error if it
        failed).
        """
        clock, receiver = self._clock, self.receiver
        if clock is None or receiver is None:
            raise DriveError("await_sync: the SYNC clock is not running")
        end = time.perf_counter() + timeout
        if isinstance(clock, ProcessSync) and clock.error is not None:  # a child's fault: at once, not at timeout
            raise DriveError(f"SYNC stopped after SYNC {after}: {clock.error}")
        while self.syncs_seen <= after:
            left = end - time.perf_counter()
            if left <= 0.0:
                failed = getattr(clock, "error", None)
                why = f": the producer failed: {failed}" if failed is not None else ""
                raise DriveError(f"no SYNC on the bus for {timeout:.3f} s after SYNC {after}{why}")
            receiver.poll(left)
        number = after + 1
        record = clock.record(number)
        if record is not None:
            return SyncSeen(number, record.sent, record.due, record.skipped)
        if isinstance(clock, ProcessSync):  # its grid is known: the slot this SYNC was sent in, from its echo
            due = clock.slot_of(self._seen_time)
            skipped = max(0, round((due - self._last_due) / clock.period) - 1) if math.isfinite(self._last_due) else 0
            self._last_due = due
            return SyncSeen(number, self._seen_time, due, skipped)
        return SyncSeen(number, self._seen_time, math.nan, 0)

    def _clock_send(self, stamp: Callable[[int], None]) -> int:
        """The producer's send: one SYNC under canopen's send lock, counted there."""
        with self.network.send_lock:
            number = self.syncs_sent + 1
            stamp(number)
            self.bus.send(self._sync_message)
            self.syncs_sent = number
        return number

    def _on_sync_echo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """A SYNC on the bus (control thread): every member's new cycle begins."""
        self.syncs_seen += 1
        if isinstance(self._clock, BroadcastSync | ProcessSync):  # the kernel or a process sent it: counted as seen
            with self.network.send_lock:
                self.syncs_sent += 1
        # its bus timestamp is wall-clock (python-can): only its age is used, on this process's perf_counter
        self._seen_time = time.perf_counter() - max(0.0, time.time() - timestamp)
        for begin_cycle in self._members:
            begin_cycle()

    def close(self) -> None:
        """Stop the SYNC clock, the master heartbeat and the receive path, detach the tap (idempotent); the bus
        stays open."""
        self.stop_clock()
        process, self._process_sync = self._process_sync, None
        if process is not None:
            process.stop()
        if self._producer is not None:
            self._producer.stop()
            self._producer = None
            self._master_node_id = None
        if self.network.notifier is not None:
            self.network.notifier.stop(self.network.NOTIFIER_SHUTDOWN_TIMEOUT)
            self.network.notifier = None
        self.tap.detach()
