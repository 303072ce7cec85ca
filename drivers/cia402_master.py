"""CiA 402 master over python-can + canopen: :class:`Cia402Drive`, the bench's :class:`~drivers.drive.Drive`.

Start-up follows what real CANopen masters do, using only standard objects, so any CiA 402 drive works:

0. Construction (``Cia402Drive.open``, or ``Cia402Drive.on_network`` for one of several drives sharing a
   :class:`~drivers.network.DriveNetwork`: one receive path, one SYNC, one master heartbeat per bus) is inert, like
   canopen's ``Network()``: no thread, nothing on the bus.
1. ``connect``: ``listen`` (Notifier, frame tap, heartbeat watchdog); NMT reset communication, wait for the
   boot-up, NMT pre-operational, read 0x1000 (must be a 402 device), 0x1018:1..4 and 0x6502 over SDO.
2. ``configure``: :meth:`Cia402Drive.preflight` first (mode in 0x6502, :func:`pdo_plan`: the PDOs and objects
   the drive's EDS has); start the master's heartbeat producer; for every RPDO/TPDO 1..4: disable it (COB-ID
   bit 31), and for those the plan uses: transmission type 1, mapping count 0, mapping entries, count, COB-ID
   enabled; then 0x6060 mode, 0x605A, 0x6007 (optional in CiA 402), 0x1006 (cycle period in us; optional in
   CiA 301), 0x60C2 (interpolation time period), 0x1017 (drive heartbeat), 0x1016:1 (drive watches the master;
   optional in CiA 301). An optional object the EDS lacks is not written (a warning and a plan note say so); one
   the EDS has but the drive refuses with "no object" is skipped with a warning. Read all of it back (0x6061 must
   show the mode); NMT start; wait for the operational heartbeat. Torque (0x6077) and position (0x6064) feedback
   are mapped only when the drive has them (then :class:`~drivers.drive.Feedback` has NaN torque / position 0).
3. ``enable``: controlword 0x06 / 0x07 / 0x0F through the RPDO, one SYNC each, until the TPDO statusword shows
   OPERATION_ENABLED.

Cyclic path (never SDO): ``set_target`` encodes the RPDO with a precomputed :class:`~drivers.pdo.PdoCodec` and
sends it; ``sync`` sends a prebuilt SYNC (DLC 0: no counter, so no drive needs 0x1019) and advances the master's
cycle counter; TPDOs are decoded on the Notifier thread and handed to ``wait_feedback`` through a condition
variable, or, with a :class:`~drivers.cyclic_rx.CyclicReceiver` (the realtime bench), received and decoded by
``wait_feedback`` itself on the control thread (same decoding, counters and errors; the Notifier still shows them
to the frame tap).

Waiting: every wait of the master (feedback, heartbeats, state changes, pacing) runs on the bus's timebase
(:func:`drivers.inprocess.timebase_of`). On a lockstep in-process bus (the embedded emulator) frames are delivered
inside ``send``, so nothing arrives by waiting: an unanswered SYNC is known when ``sync`` returns and
``wait_feedback`` raises :class:`~drivers.errors.FeedbackTimeoutError` at once, with no deadline; an SDO answer is
there or never comes (no response timeout); and time is the channel's simulated time, one cycle period per SYNC
(``sync`` advances it) plus the master's own pauses, so heartbeat supervision never reads a busy host as a lost
drive. On any other bus they are wall-clock waits.

Units: ``set_target`` takes plant units and sends ``round(value * scale)`` after clamping ``|value|`` to
``velocity_limit`` (CSV, PV; scale ``velocity_scale``) or ``torque_limit`` (CST; scale ``torque_scale``); feedback
is divided by the same scales. The shipped EDS counts velocity in 0.001 rpm, so a plant in rpm needs
``velocity_scale: 1000``, the ``DriveConfig`` default. Torque is per mille of rated torque (CiA 402).

Errors: EMCY -> :class:`~drivers.errors.EmergencyError` (code decoded), statusword fault bit ->
:class:`~drivers.errors.DriveFaultError`, no heartbeat for ``heartbeat_timeout_factor x 0x1017`` ->
:class:`~drivers.errors.HeartbeatLostError` (checked by ``wait_feedback`` and by a watchdog thread), no TPDO set
in time -> :class:`~drivers.errors.FeedbackTimeoutError`, SDO abort -> :class:`~drivers.errors.SdoError`
(abort code decoded), no SDO answer -> :class:`~drivers.errors.DriveTimeoutError`.
Before any of these but ``FeedbackTimeoutError`` leaves ``wait_feedback`` the master commands quick stop (controlword
0x02, target 0, one SYNC); one unanswered SYNC leaves the command as it was, for the caller to judge.
Received frames: a TPDO/EMCY/heartbeat of the drive that does not decode (wrong DLC, impossible statusword) is
counted in :attr:`Cia402Drive.stats` (``bad_frames``); with ``fatal_bad_frames`` (the default) it is also a
:class:`~drivers.errors.BadFrameError` (a run-time error, exit 1) raised by the next ``wait_feedback``, otherwise
it is only counted (a TPDO set left incomplete by it then simply never answers its SYNC). A frame with a COB-ID
nobody subscribed to (another node's traffic) is ignored and counted (``unknown_frames``).

NMT supervision: once the drive's heartbeat has reported OPERATIONAL after ``configure`` (the heartbeat is armed),
a heartbeat reporting any other NMT state while the master is operational is a
:class:`~drivers.errors.DriveNmtStateError` raised by the next ``wait_feedback``: a drive out of OPERATIONAL
ignores RPDOs, so the cyclic path no longer reaches it. The master's own NMT commands disarm the heartbeat first.

Services
--------
:class:`Cia402Drive` is a composition of the service objects of :mod:`drivers.master` (its table says which does
what), as canopen's ``RemoteNode`` is of ``sdo``, ``nmt``, ``emcy`` and ``pdo`` and the emulator's ``VirtualDrive``
of its own: it builds and wires them (the receive callbacks, the network membership), runs the life cycle
(``connect``, ``listen``, ``close``) and delegates every other public method to the service that owns it.

Thread safety
-------------
- Public methods are called from ONE control thread (the bench's). canopen's SDO client is not re-entrant.
- The Notifier thread runs the receive callbacks (TPDO, EMCY, heartbeat; with a cyclic receiver the TPDO callback
  runs on the control thread instead, inside ``wait_feedback`` and ``sync``). They touch only the state guarded by
  the inbox's condition (:class:`~drivers.master.inbox.Inbox`): the current cycle's partial TPDO set, the latest
  feedback, the counters and the queue of pending errors. The control thread reads that state only under the same
  lock.
- The heartbeat watchdog thread only posts a pending error to the inbox.
- Frames are sent under canopen's ``network.send_lock``, shared with canopen's own sends; python-can's
  periodic heartbeat task has its own lock (the interfaces' ``send`` is thread-safe).
- Frame listeners (:meth:`Cia402Drive.add_frame_listener`) run on the sending thread and the Notifier thread.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from drivers.bus import FrameListener
from drivers.cia301 import NMT_COB_ID, FunctionCode, NmtCommand, check_node_id, cob_id
from drivers.cia402 import Obj, OperationMode
from drivers.config import DriveConfig
from drivers.cyclic_rx import CyclicReceiver
from drivers.drive import DeviceInfo, Drive, Feedback, StopReport
from drivers.errors import ConfigError, DriveError
from drivers.heartbeat import HeartbeatMonitor
from drivers.master.cyclic import CyclicPath
from drivers.master.emergency import EmcyConsumer
from drivers.master.inbox import Inbox
from drivers.master.link import MasterLink
from drivers.master.nmt_client import NmtClient
from drivers.master.plan import PdoPlan, interpolation_time_period, pdo_plan
from drivers.master.safe_stop import SafeStop
from drivers.master.sdo_client import U32, SdoClient
from drivers.master.startup import CIA402_PROFILE, MASTER_HEARTBEATS_PER_CONSUMER_TIME, StartUp
from drivers.master.state402 import PowerStateCommands
from drivers.master.supervision import DriveSupervision
from drivers.network import DriveNetwork, SyncSeen
from drivers.od import load_od, object_address
from drivers.pdo import PdoCodec

__all__ = [
    "CIA402_PROFILE",
    "MASTER_HEARTBEATS_PER_CONSUMER_TIME",
    "Cia402Drive",
    "PdoPlan",
    "RxStats",
    "interpolation_time_period",
    "pdo_plan",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RxStats:
    """Counters of the receive side (read with :attr:`Cia402Drive.stats`)."""

    tpdo_frames: int
    emcy_frames: int
    heartbeat_frames: int
    bad_frames: int  # wrong DLC or impossible content: counted, and raised as BadFrameError when fatal
    unknown_frames: int  # COB-ID nobody subscribed to: ignored


class Cia402Drive(Drive):
    """A CiA 402 drive on a python-can bus, driven through canopen's SDO client and NMT master.

    Build it with :meth:`open` (a drive alone on its bus: it owns a private :class:`~drivers.network.DriveNetwork`)
    or :meth:`on_network` (one of several drives sharing a network's receive path, SYNC and master heartbeat).
    The bus belongs to the caller: :meth:`close` of a drive that owns its network releases the Notifier, the
    heartbeat producer and the frame tap, never the bus; a drive on a shared network only leaves it (the network's
    owner closes it).

    Parameters
    ----------
    bus
        The python-can bus the drive is on.
    cfg
        The ``drive:`` section (node id, mode, scales, limits, heartbeats, EDS).
    sample_time
        The cycle period in seconds: the period of SYNC, written to the drive as 0x1006 and 0x60C2 by
        :meth:`configure`. It enters the master here, once, and lives in :attr:`cyclic` (:attr:`sample_time`).
    od
        The drive's object dictionary (:func:`drivers.od.load_od`).
    network
        A shared :class:`~drivers.network.DriveNetwork` on ``bus``; ``None``: a private one.
    receiver
        A private network's cyclic receiver (realtime); ``None``: the Notifier dispatches the TPDOs.

    Attributes
    ----------
    link, inbox, sdo, nmt, supervision, emcy, cyclic, startup, power, stopper
        The service objects (:mod:`drivers.master`).
    """

    def __init__(
        self,
        bus: can.BusABC,
        cfg: DriveConfig,
        *,
        sample_time: float,
        od: ObjectDictionary,
        network: DriveNetwork | None = None,
        receiver: CyclicReceiver | None = None,
    ) -> None:
        if not (sample_time > 0 and math.isfinite(sample_time)):
            raise ConfigError(f"must be a positive number of seconds, got {sample_time}", key="sample_time")
        if cfg.master_node_id == cfg.node_id:
            raise ConfigError(f"must differ from drive.node_id ({cfg.node_id}): both would send heartbeats on "
                              f"0x{cob_id(FunctionCode.HEARTBEAT, cfg.node_id):03X}", key="drive.master_node_id")
        self.cfg = cfg
        self.node_id = check_node_id(cfg.node_id)
        self.od = od
        if network is not None and network.bus is not bus:
            raise DriveError(f"node {cfg.node_id}: the shared network is on another bus")
        if network is not None and receiver is not None:
            raise DriveError(f"node {cfg.node_id}: a shared network has its own cyclic receiver (DriveNetwork)")
        # the tap and the Notifier start with listen(): construction starts nothing
        net = DriveNetwork(bus, receiver) if network is None else network
        self.network = net.network
        if self.node_id in self.network:
            raise ConfigError(f"node {self.node_id} is already on this bus's network", key="drive.node_id")
        self.node = canopen.RemoteNode(self.node_id, od)
        self.link = MasterLink(cfg, self.node, net, owns_network=network is None)
        self.inbox = Inbox()
        self.sdo = SdoClient(self.link)
        self.supervision = DriveSupervision(self.link, self.inbox, forward=self.node.nmt.on_heartbeat)
        self.heartbeat: HeartbeatMonitor = self.supervision.monitor
        self.nmt = NmtClient(self.link, self.heartbeat)
        self.emcy = EmcyConsumer(self.node_id, self.inbox)
        self.cyclic = CyclicPath(self.link, self.inbox, self.heartbeat, sample_time=sample_time)
        self.startup = StartUp(self.link, self.sdo, self.nmt, self.supervision, self.cyclic, self.inbox)
        self.power = PowerStateCommands(self.link, self.cyclic, self.sdo, self.inbox,
                                        restore_communication=self._restore_communication)
        self.stopper = SafeStop(self.link, self.cyclic, self.power, self.nmt, self.heartbeat, self.sdo, self.inbox)
        self.network.add_node(self.node)
        self._listening = False
        self._begin_cycle = self.cyclic.begin_cycle  # one bound method: the network's leave() compares identity
        self._wire()

    def _wire(self) -> None:
        """The receive callbacks replace canopen's, and the drive joins its network's cycle.

        canopen's EMCY consumer unpacks without a length check and would stop the callbacks of a short frame: ours
        replaces it. canopen's NMT state tracking unpacks heartbeats and NMT commands unchecked too: ours replace its
        subscriptions and pass it the well-formed frames only.
        """
        network, master_nmt = self.network, self.nmt.master
        emcy_cob = cob_id(FunctionCode.EMCY, self.node_id)
        network.unsubscribe(emcy_cob, self.node.emcy.on_emcy)
        network.subscribe(emcy_cob, self.emcy.on_emcy)
        heartbeat_cob = cob_id(FunctionCode.HEARTBEAT, self.node_id)
        network.unsubscribe(heartbeat_cob, master_nmt.on_heartbeat)
        network.subscribe(heartbeat_cob, self.supervision.on_heartbeat)
        network.unsubscribe(NMT_COB_ID, master_nmt.on_command)
        network.subscribe(NMT_COB_ID, self.nmt.on_command)
        self.link.net.join(self._begin_cycle)

    # --- construction -----------------------------------------------------------------------------------------

    @classmethod
    def open(cls, bus: can.BusABC, cfg: DriveConfig, *, sample_time: float,
             receiver: CyclicReceiver | None = None) -> Cia402Drive:
        """A master for drive ``cfg.node_id`` on ``bus`` with the EDS ``cfg.eds`` (default: the shipped one).

        ``receiver``: the TPDOs are received on the thread that waits for them (:mod:`drivers.cyclic_rx`; it
        stays the caller's, as the bus does). Raises :class:`~drivers.errors.EdsError` for a bad EDS. Nothing
        is sent until :meth:`connect`.
        """
        od = load_od(cfg.eds, cfg.node_id)
        return cls(bus, cfg, sample_time=sample_time, od=od, receiver=receiver)

    @classmethod
    def on_network(cls, network: DriveNetwork, cfg: DriveConfig, *, sample_time: float) -> Cia402Drive:
        """A master for drive ``cfg.node_id`` sharing ``network`` (its bus, receive path, SYNC, master heartbeat).

        Each drive keeps its own SDO client, NMT commands, PDO codecs, heartbeat supervision and errors: frames
        reach it by COB-ID through the network's one receive path. :meth:`sync` of any member sends the one SYNC
        and starts a new cycle on every member. Raises :class:`~drivers.errors.ConfigError` for a node id
        already on the network and :class:`~drivers.errors.EdsError` for a bad EDS.
        """
        od = load_od(cfg.eds, cfg.node_id)
        return cls(network.bus, cfg, sample_time=sample_time, od=od, network=network)

    # --- life cycle -------------------------------------------------------------------------------------------

    def connect(self) -> DeviceInfo:
        """NMT reset communication, wait for boot-up, NMT pre-operational, read identity (see module docstring).

        Starts the listening side first (:meth:`listen`). If the drive never answered (no boot-up), a failed connect
        stops it again, so no thread outlives the failure; once it answered, the listening side stays for
        :meth:`safe_stop` (the drive is there to be stopped) until :meth:`close`.

        Returns
        -------
        DeviceInfo
            Identity (0x1018), device type (0x1000, a 402 drive), NMT state and supported modes (0x6502).

        Raises
        ------
        DriveTimeoutError
            No boot-up or no SDO answer: no drive with this node id on the bus.
        DriveError
            Not a CiA 402 drive, or an SDO abort on a mandatory object.
        """
        self.listen()
        try:
            return self.startup.identify()
        except BaseException:
            if not self.link.connected:
                self._stop_listening()
            raise

    def listen(self) -> None:
        """Attach the frame tap, start the Notifier (canopen's listener, the tap, the counter) and the watchdog.

        :meth:`connect` calls it; commissioning, which talks SDO and NMT to a drive it must not reset, calls it
        instead. Idempotent; :meth:`close` stops it all.
        """
        self.link.require_open()
        if self._listening:
            return
        self.link.net.listen()
        self._listening = True
        self.supervision.start_watchdog()

    def _stop_listening(self) -> None:
        """Undo :meth:`listen` (safe when it never ran); a shared network keeps listening for the other drives."""
        self.supervision.stop_watchdog()
        self._listening = False
        if self.link.owns_network:
            self.link.net.close()

    def _restore_communication(self) -> None:
        """After a heartbeat fault: NMT reset communication, boot-up, and the last :meth:`configure` again (reset
        communication restores the drive's 0x1000..0x1FFF defaults)."""
        mode = self.cyclic.mode
        if mode is None:
            return
        self.heartbeat.disarm()
        self.link.operational = False
        self.nmt.reset_communication()
        self.startup.configure(mode)

    def close(self) -> None:
        """NMT pre-operational and consumer heartbeat off (best effort), then release the Notifier, producer, tap."""
        link = self.link
        if link.closed:
            return
        self.heartbeat.disarm()  # our own NMT command below is not a drive leaving OPERATIONAL
        if link.operational:
            try:
                self.nmt.send(NmtCommand.ENTER_PRE_OPERATIONAL)
                self.sdo.write(Obj.CONSUMER_HEARTBEAT_TIME, 1, U32, 0)
            except Exception as exc:  # the drive may be gone; closing must still release everything
                logger.info("close: could not park node %d: %s", self.node_id, exc)
        link.operational = False
        link.closed = True
        link.net.leave(self._begin_cycle)
        self._stop_listening()

    def add_frame_listener(self, listener: FrameListener) -> None:
        """Call ``listener(message, "tx" | "rx")`` for every frame on the bus (on a shared network: every drive's);
        runs on the sending and the Notifier thread."""
        self.link.net.tap.add_listener(listener)

    # --- Drive: start-up (drivers.master.startup) -------------------------------------------------------------

    def preflight(self, mode: OperationMode) -> PdoPlan:
        """What :meth:`configure` checks before it writes anything (:meth:`StartUp.preflight`); ``commission
        enable`` runs it too, so a drive ``run`` would refuse is refused there as well."""
        return self.startup.preflight(mode)

    def configure(self, mode: OperationMode) -> None:
        """Configure PDOs, mode, timing (:attr:`sample_time`) and heartbeats over SDO, verify by reading back,
        then NMT start.

        Parameters
        ----------
        mode
            The CiA 402 mode of operation (``drive_cfg.operation_mode``: CSV, CST or PV).

        Raises
        ------
        DriveError
            The drive lacks the mode or an object the plan maps, refuses a write, or reads back another value.
        """
        self.startup.configure(mode)

    def settings(self, mode: OperationMode) -> list[tuple[int, int, int, bool]]:
        """The objects :meth:`configure` writes after the PDOs, in order, as ``(index, sub-index, value,
        optional)``: ``commission check`` reads them and ``commission info --dcf`` records them."""
        return [(index, sub, value, optional)
                for index, sub, _, value, optional in self.startup.settings(mode)]

    # --- Drive: CiA 402 state machine (drivers.master.state402) -----------------------------------------------

    def enable(self) -> None:
        """Controlword 0x06 / 0x07 / 0x0F until OPERATION_ENABLED (target held at 0)."""
        self.power.enable()

    def disable(self) -> None:
        """Disable voltage until SWITCH_ON_DISABLED (or FAULT, which disable voltage does not leave)."""
        self.power.disable()

    def quick_stop(self) -> None:
        """Quick stop until QUICK_STOP_ACTIVE, or SWITCH_ON_DISABLED (quick stop options 0..4, or not enabled)."""
        self.power.quick_stop()

    def fault_reset(self) -> None:
        """Rising edge on controlword bit 7 until the drive leaves FAULT, communication restored first after a
        heartbeat fault (EMCY 0x8130 from the drive, or the master lost the drive's heartbeat)."""
        self.power.fault_reset()

    # --- Drive: cyclic path (drivers.master.cyclic) -----------------------------------------------------------

    def set_target(self, value: float) -> float:
        """Clamp to the mode's limit, scale, round and send RPDO1 (controlword + target); no SDO."""
        return self.cyclic.set_target(value)

    def sync(self) -> int:
        """Send SYNC; TPDOs received from now on answer the returned cycle.

        On a synchronous bus one cycle period of simulated time passes since the previous SYNC first (the drive's
        and the master's heartbeat timers fire on the way), and the answering TPDOs are in when this returns.
        """
        return self.cyclic.sync()

    def wait_feedback(self, timeout: float) -> Feedback:
        """Block until the TPDO set answering the last SYNC arrived (see :class:`~drivers.drive.Drive`)."""
        return self.cyclic.wait_feedback(timeout)

    # --- SYNC from a clock (realtime; drivers.sync_clock) -------------------------------------------------------

    def start_clock(self, *, spin_margin: float = 0.0) -> str | None:
        """SYNC from a clock on this drive's network from now on (:meth:`DriveNetwork.start_clock`, at the cycle
        period :attr:`sample_time`); the clock's name (``"thread"``, ``"bcm"``), or None where the network has no
        cyclic receiver to read the bus on (the loop then sends SYNC itself)."""
        net = self.link.net
        if net.receiver is None:
            return None
        return net.start_clock(self.cyclic.sample_time, self.cyclic.clock_routes(), spin_margin=spin_margin).name

    def stop_clock(self) -> None:
        """Stop the network's SYNC clock (idempotent)."""
        self.link.net.stop_clock()

    def await_sync(self, after: int, timeout: float) -> SyncSeen:
        """The next SYNC of the clock after SYNC ``after``, read from the bus (:meth:`DriveNetwork.await_sync`)."""
        return self.link.net.await_sync(after, timeout)

    @property
    def sample_time(self) -> float:
        """The cycle period in seconds, as the master was made with it (:attr:`cyclic` holds it)."""
        return self.cyclic.sample_time

    @property
    def latched(self) -> float:
        """The target the drive latched at the last SYNC read from the bus, plant units (SYNC from a clock)."""
        return self.cyclic.latched

    @property
    def rpdo_sync_count(self) -> int:
        """The network's count of SYNCs sent when the last RPDO went out."""
        return self.cyclic.rpdo_sync_count

    @property
    def syncs_seen(self) -> int:
        """SYNC from a clock: the network's count of the SYNCs read from the bus so far (the number
        :meth:`await_sync` counts from)."""
        return self.link.net.syncs_seen

    def safe_stop(self) -> StopReport:
        """Quick stop, zero target, disable voltage, confirmed by reading the drive's statusword; never raises
        (:mod:`drivers.master.safe_stop`).

        Returns
        -------
        StopReport
            Whether the stop was commanded and confirmed, the state and statusword read back, the path it took
            (PDO or SDO) and any fault the drive reported.
        """
        return self.stopper.run()

    # --- SDO access for commissioning (not for the cyclic path) ----------------------------------------------

    def sdo_upload(self, index: int, subindex: int) -> bytes:
        """Raw SDO upload (start-up and commissioning, never the cyclic path); failures as product errors."""
        return self.sdo.upload(index, subindex)

    def sdo_download(self, index: int, subindex: int, data: bytes) -> None:
        """Raw SDO download (start-up and commissioning, never the cyclic path); failures as product errors."""
        self.sdo.download(index, subindex, data)

    def read_object(self, obj: int | str, subindex: int | str = 0) -> int:
        """SDO upload of an integer object, typed by the EDS (or the CiA 402 standard).

        Parameters
        ----------
        obj
            The index (``0x6041``) or the EDS's name of the object (``"Statusword"``).
        subindex
            The sub-index, or its EDS name (``"Vendor-ID"`` of ``"Identity object"``).

        Returns
        -------
        int
            The value, signed or not as the object's type says.

        Raises
        ------
        InputError
            A name the EDS does not have.
        EdsError
            An index neither the EDS nor the CiA 402 standard types (nothing is sent).
        SdoError
            The drive aborted the transfer (the abort code decoded).
        DriveTimeoutError
            No answer.
        """
        return self.sdo.read_object(*object_address(self.od, obj, subindex))

    def write_object(self, obj: int | str, subindex: int | str, value: int) -> None:
        """SDO download of an integer object, typed by the EDS (or the CiA 402 standard).

        Parameters
        ----------
        obj
            The index or the EDS's name of the object (``"Producer heartbeat time"``).
        subindex
            The sub-index, or its EDS name.
        value
            The value; one that does not fit the object's type is a ``ConfigError`` and nothing is sent.

        Raises
        ------
        InputError
            A name the EDS does not have.
        EdsError
            An index neither the EDS nor the CiA 402 standard types (nothing is sent).
        SdoError
            The drive aborted the transfer (the abort code decoded).
        DriveTimeoutError
            No answer.
        """
        self.sdo.write_object(*object_address(self.od, obj, subindex), value)

    # --- observation ------------------------------------------------------------------------------------------

    @property
    def fatal_bad_frames(self) -> bool:
        """A frame from the drive that does not decode is raised (BadFrameError) by the next wait_feedback; False:
        only counted in stats.bad_frames (the bench's ``bench.faults.bad_frame: count``)."""
        return self.inbox.fatal_bad_frames

    @fatal_bad_frames.setter
    def fatal_bad_frames(self, fatal: bool) -> None:
        self.inbox.fatal_bad_frames = fatal

    @property
    def stats(self) -> RxStats:
        """Receive-side counters."""
        with self.inbox.cv:
            return RxStats(self.cyclic.tpdo_frames, self.emcy.frames, self.supervision.frames, self.inbox.bad_frames,
                           self.link.net.unknown.count)

    @property
    def bad_frames(self) -> int:
        """Frames from the drive that did not decode (:attr:`RxStats.bad_frames`)."""
        with self.inbox.cv:
            return self.inbox.bad_frames

    @property
    def pdo_codecs(self) -> dict[int, PdoCodec]:
        """The configured PDO codecs by COB-ID (RPDO and TPDOs), e.g. to decode a capture."""
        return self.cyclic.pdo_codecs

    @property
    def last_feedback(self) -> Feedback | None:
        """The latest complete feedback, whatever cycle it answered."""
        with self.inbox.cv:
            return self.cyclic.feedback

    @property
    def controlword(self) -> int:
        """The controlword the master sends with every RPDO."""
        return self.cyclic.controlword

    @property
    def cycle(self) -> int:
        """The master's SYNC counter."""
        with self.inbox.cv:
            return self.cyclic.cycle
