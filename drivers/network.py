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

Thread safety: :meth:`join`, :meth:`sync`, :meth:`listen` and :meth:`close` are called from the one control thread;
the receive callbacks run on the Notifier thread and belong to the drives (see ``drivers.cia402_master``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import can
import canopen

from drivers.bus import FrameTap
from drivers.cia301 import SYNC_COB_ID
from drivers.cyclic_rx import CyclicReceiver
from drivers.errors import ConfigError, DriveError
from drivers.heartbeat import HeartbeatProducer
from drivers.inprocess import connect_network, subscribe_cyclic, timebase_of
from drivers.scan import ScanResult, scan_bus

__all__ = ["DriveNetwork", "UnknownFrameCounter", "received_elsewhere"]

NOTIFIER_CYCLE = 0.1  # s the Notifier blocks in recv(): bounds how long close() waits for its thread


def received_elsewhere(can_id: int, data: bytearray, timestamp: float) -> None:
    """The Notifier's subscriber of a COB-ID the cyclic receiver owns: the frame is known (not counted as
    unknown) and handled on the control thread, not here."""


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

    def sync(self, cycle_period: float) -> None:
        """Start a new cycle on every member, then send one SYNC.

        On a synchronous bus ``cycle_period`` seconds of simulated time pass since the previous SYNC first (the
        drives' and the master's heartbeat timers fire on the way), and the answering TPDOs are in on return.
        """
        timebase = self.timebase
        if timebase.synchronous:
            timebase.sleep(self._sync_at + cycle_period - timebase.now())
            self._sync_at = timebase.now()
        if self.receiver is not None:  # late answers of the old cycle are its own, not the new one's
            self.receiver.drain()
        for begin_cycle in self._members:
            begin_cycle()
        # sent outside any drive's lock: on a synchronous bus the answers are delivered inside send, possibly by
        # another thread's pump, whose listeners take the drives' locks
        with self.network.send_lock:
            self.bus.send(self._sync_message)

    def close(self) -> None:
        """Stop the master heartbeat and the receive path, detach the tap (idempotent); the bus stays open."""
        if self._producer is not None:
            self._producer.stop()
            self._producer = None
            self._master_node_id = None
        if self.network.notifier is not None:
            self.network.notifier.stop(self.network.NOTIFIER_SHUTDOWN_TIMEOUT)
            self.network.notifier = None
        self.tap.detach()
