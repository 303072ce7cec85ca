"""The master's cyclic path: RPDO (controlword + target), SYNC, and the TPDO feedback answering it.

Never SDO. :meth:`CyclicPath.set_target` encodes the RPDO with a precomputed :class:`~drivers.pdo.PdoCodec` and sends
it; :meth:`CyclicPath.sync` has the network send its prebuilt SYNC (DLC 0) after every member's
:meth:`CyclicPath.begin_cycle`; TPDOs are decoded on the Notifier thread (:meth:`CyclicPath.on_tpdo`) and handed to
:meth:`CyclicPath.wait_feedback` through the inbox's condition, or, with a :class:`~drivers.cyclic_rx.CyclicReceiver`,
received and decoded on the control thread inside the wait (same decoding, counters and errors).

On a synchronous (lockstep) bus frames are delivered inside ``send``: an unanswered SYNC is known when ``sync``
returns, and the wait raises :class:`~drivers.errors.FeedbackTimeoutError` at once, with no deadline.

SYNC from a clock (:meth:`drivers.network.DriveNetwork.start_clock`): a SYNC's echo begins the cycle
(:meth:`CyclicPath.begin_cycle`, on the control thread as it reads the bus), a wait for feedback ends with a
:class:`~drivers.errors.FeedbackTimeoutError` when the next SYNC came first (a TPDO after it answers that SYNC, as on
the wire), and the echo of the drive's own RPDO (:meth:`CyclicPath.on_rpdo_echo`) is what the drive latches at the
next SYNC: :attr:`CyclicPath.latched`, from the bus, for the bench's log and law.

Errors: before any error but ``FeedbackTimeoutError`` leaves :meth:`CyclicPath.wait_feedback`, the path commands quick
stop (controlword 0x02, target 0, one SYNC); one unanswered SYNC leaves the command as it was, for the caller to judge.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable

import can

from drivers.cia402 import Command402, Obj, OperationMode, State402, Statusword, decode_state
from drivers.cyclic_rx import CyclicReceiver
from drivers.drive import Feedback
from drivers.errors import (
    DriveError,
    DriveFaultError,
    FeedbackTimeoutError,
    HeartbeatLostError,
    ProductError,
    ProtocolError,
)
from drivers.heartbeat import HeartbeatMonitor
from drivers.master.inbox import Inbox
from drivers.master.link import MasterLink
from drivers.master.plan import REQUIRED_FEEDBACK, demand_object
from drivers.pdo import PdoCodec, PdoLayout, data_frame

__all__ = ["FEEDBACK_POLL", "RECEIVE_POLL", "CyclicPath"]

logger = logging.getLogger("drivers.cia402_master")  # the master's log, as before the split into services

FEEDBACK_POLL = 0.05  # s: a wait for feedback looks at the heartbeat deadline at least this often
#: s: with a cyclic receiver, a wait for feedback sees the Notifier's errors (EMCY, heartbeat) at least this often
#: (it blocks in recv, not on the condition they notify); short against the drive's reaction, long against 1 cycle
RECEIVE_POLL = 0.005

_FAULT_BIT = int(Statusword.FAULT)  # a plain int: IntFlag's operators are Python code, and this is every cycle
_STATES: dict[int, State402] = {}
"""Statuswords seen so far and their 402 state (``decode_state`` is pure; a handful of words recur every cycle)."""


class CyclicPath:
    """The RPDO out, SYNC, and the TPDO set in, of one drive.

    Parameters
    ----------
    link, inbox
        The drive; the inbox whose condition also guards the feedback, and whose errors a wait raises.
    monitor
        The drive's heartbeat (a wait raises its loss).
    sample_time
        Seconds per cycle: the bench's sample time, the period of SYNC (its one home on the master's side; start-up
        writes it to the drive as 0x1006 and 0x60C2, :func:`~drivers.master.plan.settings_rows`).

    Attributes
    ----------
    cycle
        The master's SYNC counter (written by the control thread under ``inbox.lock``).
    feedback
        The latest complete feedback, whatever cycle it answered (under ``inbox.lock``).
    mode
        What ``configure`` set up (None before).
    controlword, target_raw
        What the next RPDO carries.
    tpdo_frames
        TPDOs decoded (under ``inbox.lock``).
    rpdo_sync_count
        The network's count of SYNCs sent when the last RPDO went out (in the bus object's send order); with a
        clock counted on its echoes (the broadcast manager, a producer process), from the RPDO's echo: the SYNCs
        read so far, plus one when a SYNC's echo came before it (:meth:`DriveNetwork.echo_before_sync`).
    latched_raw
        The target of the last RPDO echo before the last SYNC echo: what the drive latched at that SYNC (SYNC from
        a clock only; the control thread writes it).
    """

    def __init__(self, link: MasterLink, inbox: Inbox, monitor: HeartbeatMonitor, *, sample_time: float) -> None:
        self._link = link
        self._inbox = inbox
        self._monitor = monitor
        self._cv = inbox.cv
        self._lock = inbox.lock
        self._errors = inbox.errors  # the same deque for the inbox's life (cleared in place)
        self.cycle = 0
        self._parts: dict[int, tuple[int, ...]] = {}
        self.feedback: Feedback | None = None
        self.tpdo_frames = 0
        self.mode: OperationMode | None = None
        self.sample_time = sample_time
        self.rpdo: PdoLayout | None = None
        self.rpdo_codec: PdoCodec | None = None
        self.tpdo_codecs: dict[int, PdoCodec] = {}
        self._feedback_at: dict[int, tuple[int, int]] = {}  # object index -> (TPDO COB-ID, slot)
        self._demand_at: tuple[int, int] | None = None  # where the mode's demand echo sits; None: not mapped
        self._target_limits = (0, 0)
        self.controlword = int(Command402.DISABLE_VOLTAGE)
        self.target_raw = 0
        self.rpdo_sync_count = 0
        self.latched_raw = 0
        self._echoed_raw = 0  # the target of the last RPDO echo seen on the bus
        self._rpdos_sent = self._rpdo_echoes = 0  # RPDOs sent and their echoes seen (SYNC counted on its echo)

    # --- set-up (configure) -------------------------------------------------------------------------------------

    def install(self, mode: OperationMode, rpdos: Iterable[PdoLayout], tpdos: Iterable[PdoLayout]) -> None:
        """The codecs of the configured PDOs, the TPDOs subscribed; the RPDO carries disable voltage and target 0."""
        net = self._link.net
        for cob in list(self.tpdo_codecs):
            net.unsubscribe_cyclic(cob, self.on_tpdo)
        rpdo = next(iter(rpdos))
        codec = rpdo.codec()
        target = codec.variables[1]
        tpdo_codecs = {layout.cob_id: layout.codec() for layout in tpdos}
        mapped = {variable.index for c in tpdo_codecs.values() for variable in c.variables}
        missing = [f"0x{index:04X}" for index in REQUIRED_FEEDBACK if index not in mapped]
        if missing:
            raise DriveError(f"TPDO mapping lacks {', '.join(missing)}")
        # where each feedback object sits: (TPDO COB-ID, position in the decoded values); the last mapping wins
        feedback_at = {variable.index: (cob, slot) for cob, c in tpdo_codecs.items()
                       for slot, variable in enumerate(c.variables)}
        with self._cv:
            self.tpdo_codecs = tpdo_codecs
            self._feedback_at = feedback_at
            self._demand_at = feedback_at.get(demand_object(mode))
            self._parts.clear()
            self.feedback = None
        self.rpdo, self.rpdo_codec = rpdo, codec
        self._target_limits = (target.minimum, target.maximum)
        for cob in tpdo_codecs:
            net.subscribe_cyclic(cob, self.on_tpdo)
        self.mode = mode
        self.controlword = int(Command402.DISABLE_VOLTAGE)
        self.target_raw = 0

    # --- the cycle -----------------------------------------------------------------------------------------------

    def set_target(self, value: float) -> float:
        """Clamp to the mode's limit, scale, round and send the RPDO (controlword + target); the value sent."""
        link = self._link
        codec, rpdo = self.rpdo_codec, self.rpdo
        if link.closed or not link.operational or codec is None or rpdo is None:
            codec = self.require_codec()  # raises the reason (the checks above, inlined: this runs every cycle)
        cob = rpdo.cob_id if rpdo is not None else self.rpdo_cob()
        if not math.isfinite(value):
            raise DriveError(f"target {value} is not finite; not sent")
        cfg = link.cfg
        if self.mode is OperationMode.CYCLIC_SYNC_TORQUE:
            limit, scale = cfg.torque_limit, cfg.torque_scale
        else:
            limit, scale = cfg.velocity_limit, cfg.velocity_scale
        clamped = -limit if value < -limit else limit if value > limit else value
        low, high = self._target_limits
        raw = round(clamped * scale)
        raw = low if raw < low else high if raw > high else raw
        self.target_raw = raw
        self.rpdo_sync_count = link.send(data_frame(cob, codec.encode(self.controlword, raw)))
        net = link.net
        if net.counts_on_echo:  # SYNCs not read yet may have gone out before it: its echo's place among them says
            self._rpdos_sent += 1
            seen, number = net.syncs_seen, self._rpdos_sent
            # this RPDO's own echo: earlier ones (a burst after a stall) may still be queued before it
            before = net.echo_before_sync(lambda: self._rpdo_echoes >= number)
            if before is not None:
                self.rpdo_sync_count = seen if before else seen + 1
        return raw / scale

    def sync(self) -> int:
        """Send SYNC (through the network: every member starts a new cycle first); the cycle it opens."""
        if self._link.closed:  # require_open's test, inlined: every cycle
            self._link.require_open()
        self._link.net.sync(self.sample_time)
        return self.cycle  # only this thread changes it (in begin_cycle, just now)

    def begin_cycle(self) -> None:
        """The network is about to send SYNC: TPDOs received from now on answer the next cycle."""
        # the cyclic path takes the condition's lock itself: Condition.__enter__/__exit__ are Python-level wrappers
        # of it, calls every cycle that are all overhead (holding the lock is holding the condition)
        with self._lock:
            self.cycle += 1
            self._parts.clear()
            self.latched_raw = self._echoed_raw  # SYNC from a clock: the last RPDO on the bus before this SYNC

    def wait_feedback(self, timeout: float) -> Feedback:
        """The TPDO set answering the last SYNC (see :meth:`drivers.drive.Drive.wait_feedback`)."""
        try:
            return self.await_feedback(timeout, raise_on_fault=True)
        except FeedbackTimeoutError:
            # not a stop: the caller decides whether one unanswered SYNC is fatal (the bench counts a lost feedback
            # and holds the last good one); the drive keeps its last command meanwhile
            raise
        except (ProductError, can.CanError) as exc:
            self._inbox.delivered(exc)
            self.fail_safe()
            raise

    def exchange(self, controlword: int, *, ignore_errors: bool = False) -> Feedback:
        """One cycle with ``controlword``: RPDO, SYNC, feedback (paced at the cycle period); ``ignore_errors``: the
        errors pending do not interrupt it."""
        timebase = self._link.timebase
        start = timebase.now()
        self.controlword = controlword
        codec = self.require_codec()
        self._link.send(data_frame(self.rpdo_cob(), codec.encode(controlword, self.target_raw)))
        self.sync()
        feedback = self.await_feedback(self.exchange_timeout(), raise_on_fault=False, raise_errors=not ignore_errors)
        timebase.sleep(self.sample_time - (timebase.now() - start))
        return feedback

    def exchange_timeout(self) -> float:
        """How long one exchange of the state machine waits for its feedback."""
        return min(self._link.cfg.state_timeout, max(0.2, 10 * self.sample_time))

    def fail_safe(self, command: Command402 = Command402.QUICK_STOP) -> None:
        """Best effort: command ``command`` with target 0 and apply it with one SYNC; never raises."""
        link = self._link
        self.controlword = int(command)
        self.target_raw = 0
        if link.closed or self.rpdo_codec is None or not link.operational:
            return
        try:
            link.send(data_frame(self.rpdo_cob(), self.rpdo_codec.encode(self.controlword, 0)))
            self.sync()
        except Exception as exc:  # called while another error propagates; must not replace it
            # info: the stop that follows reads the drive back and says what it reached, in the command's one line
            logger.info("could not command %s on node %d: %s", command.name, link.node_id, exc)

    # --- the wait ------------------------------------------------------------------------------------------------

    def await_feedback(self, timeout: float, *, raise_on_fault: bool, raise_errors: bool = True) -> Feedback:
        """This cycle's feedback within ``timeout``, after raising what is pending (``raise_errors``) and, with
        ``raise_on_fault``, a :class:`DriveFaultError` for a statusword with the fault bit."""
        receiver = self._link.net.receiver
        if receiver is not None:
            return self._receive_feedback(receiver, timeout, raise_on_fault=raise_on_fault, raise_errors=raise_errors)
        synchronous = self._link.timebase.synchronous
        deadline = time.monotonic() + timeout
        with self._lock:
            cycle = self.cycle
            while True:
                feedback = self._answer(cycle, raise_on_fault=raise_on_fault, raise_errors=raise_errors)
                if feedback is not None:
                    return feedback
                remaining = deadline - time.monotonic()
                if remaining <= 0 or synchronous:
                    raise self._no_answer(cycle, "on the synchronous bus" if synchronous else f"within {timeout:.3f} s")
                self._cv.wait(min(remaining, FEEDBACK_POLL))

    def _receive_feedback(self, receiver: CyclicReceiver, timeout: float, *, raise_on_fault: bool,
                          raise_errors: bool) -> Feedback:
        """:meth:`await_feedback` with the TPDOs received on this thread (:mod:`drivers.cyclic_rx`).

        The lock is taken only to look at the shared state, never across a ``recv``: the Notifier thread posts its
        errors (EMCY, heartbeat) meanwhile, and they are seen after at most :data:`RECEIVE_POLL`.
        """
        start = time.monotonic()
        deadline = start + timeout
        spin_until = start + receiver.spin
        cycle = self.cycle  # only this thread changes it
        while True:
            with self._lock:
                feedback = self._answer(cycle, raise_on_fault=raise_on_fault, raise_errors=raise_errors)
            if feedback is not None:
                return feedback
            if self.cycle != cycle:  # SYNC from a clock: the next SYNC came first; what follows answers it
                with self._lock:
                    raise self._no_answer(cycle, "before the next SYNC")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if receiver.drain():  # frames already received count, as the Notifier would have dispatched them
                    continue
                with self._lock:
                    raise self._no_answer(cycle, f"within {timeout:.3f} s")
            receiver.poll(min(remaining, RECEIVE_POLL), spin_until)

    def _answer(self, cycle: int, *, raise_on_fault: bool, raise_errors: bool) -> Feedback | None:
        """This cycle's feedback if it is in, after raising what is pending (caller holds the lock)."""
        if self._errors and raise_errors:
            raise self._errors.popleft()
        try:
            self._monitor.check()
        except HeartbeatLostError:
            self._inbox.heartbeat_fault = True
            raise
        feedback = self.feedback
        if feedback is not None and feedback.cycle == cycle:
            if raise_on_fault and feedback.statusword & _FAULT_BIT:
                raise DriveFaultError(
                    f"node {self._link.node_id} reports a fault: statusword 0x{feedback.statusword:04X} "
                    f"({feedback.state.name})"
                )
            return feedback
        return None

    def _no_answer(self, cycle: int, waited: str) -> DriveError:
        """The error of an unanswered SYNC: the receive thread's own failure if it stopped, else a timeout."""
        notifier = self._link.network.notifier
        if notifier is not None and notifier.exception is not None:
            return DriveError(f"the CAN receive thread stopped: {notifier.exception}")
        return FeedbackTimeoutError(f"no TPDO set from node {self._link.node_id} answered SYNC {cycle} {waited}")

    # --- the receive side (Notifier thread, or the control thread with a cyclic receiver) ------------------------

    def on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """A TPDO of the drive: decoded into this cycle's set; the complete set is the feedback."""
        received = time.monotonic()
        codec = self.tpdo_codecs.get(can_id)
        if codec is None:
            return
        try:
            values = codec.decode(data)
        except ProtocolError as exc:
            self._inbox.post(exc, bad_frame=True)
            return
        with self._lock:
            self.tpdo_frames += 1
            answered = self.feedback
            if answered is not None and answered.cycle == self.cycle:
                # the cycle's first complete set is its answer, as replay --verify takes it: a later frame in the
                # same SYNC window (the rest of a set that straddled the SYNC, then the cycle's own) must not
                # replace it, or what the loop reads would depend on when its thread looked
                return
            self._parts[can_id] = values
            if len(self._parts) < len(self.tpdo_codecs):
                return
            try:
                feedback = self._assemble(received)
            except ProtocolError as exc:
                self._inbox.post(exc, bad_frame=True)  # the inbox's condition is reentrant (an RLock)
            else:
                self.feedback = feedback
            if not self._link.timebase.synchronous:  # on a synchronous bus nobody waits: the answer is in before
                self._cv.notify_all()

    def _assemble(self, received: float) -> Feedback:
        """Feedback from the complete TPDO set of the current cycle (caller holds the lock)."""
        parts = self._parts
        where = self._feedback_at
        cob, slot = where[Obj.STATUSWORD]
        statusword = parts[cob][slot]
        state = _STATES.get(statusword)
        if state is None:
            try:
                state = _STATES[statusword] = decode_state(statusword)
            except ValueError as exc:
                raise ProtocolError(f"node {self._link.node_id}: {exc}") from exc
        cob, slot = where[Obj.VELOCITY_ACTUAL_VALUE]
        velocity = parts[cob][slot]
        torque: float = math.nan  # NaN: not mapped
        position = 0  # 0: not mapped
        if Obj.TORQUE_ACTUAL_VALUE in where:
            cob, slot = where[Obj.TORQUE_ACTUAL_VALUE]
            torque = parts[cob][slot]
        if Obj.POSITION_ACTUAL_VALUE in where:
            cob, slot = where[Obj.POSITION_ACTUAL_VALUE]
            position = parts[cob][slot]
        cfg = self._link.cfg
        demand = math.nan  # NaN: no echo mapped
        if self._demand_at is not None:  # in the target's scale, as set_target and latched divide
            cob, slot = self._demand_at
            demand = parts[cob][slot] / (cfg.torque_scale if self.mode is OperationMode.CYCLIC_SYNC_TORQUE
                                         else cfg.velocity_scale)
        return Feedback(
            cycle=self.cycle,
            statusword=statusword,
            state=state,
            velocity=velocity / cfg.velocity_scale,
            torque=torque / cfg.torque_scale,
            position=position,
            timestamp=received,
            demand=demand,
        )

    # --- SYNC from a clock: what the drive latched ---------------------------------------------------------------

    def clock_routes(self) -> dict[int, Callable[[int, bytearray, float], None]]:
        """The RPDO's echo handler by COB-ID, for :meth:`drivers.network.DriveNetwork.start_clock`; the drive holds
        the last RPDO sent until an echo says otherwise."""
        self._echoed_raw = self.latched_raw = self.target_raw
        self._rpdos_sent = self._rpdo_echoes = 0  # the clock's receiver dropped what came before (start_clock)
        return {self.rpdo_cob(): self.on_rpdo_echo}

    def on_rpdo_echo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """The echo of this master's RPDO on the bus (control thread): its target is what the drive latches at the
        next SYNC, unless another RPDO follows before it."""
        codec = self.rpdo_codec
        if codec is None:
            return
        self._rpdo_echoes += 1
        try:
            self._echoed_raw = codec.decode(data)[1]
        except ProtocolError:  # not ours to judge (the tap logged it): the drive keeps what it had
            return

    @property
    def echoes_demand(self) -> bool:
        """The installed TPDOs map the mode's demand echo (``drive.demand_echo``): :attr:`Feedback.demand` is it."""
        return self._demand_at is not None

    @property
    def latched(self) -> float:
        """:attr:`latched_raw` in plant units (the scale of the mode's target, as :meth:`set_target` divides)."""
        cfg = self._link.cfg
        scale = cfg.torque_scale if self.mode is OperationMode.CYCLIC_SYNC_TORQUE else cfg.velocity_scale
        return self.latched_raw / scale

    # --- the RPDO ------------------------------------------------------------------------------------------------

    @property
    def pdo_codecs(self) -> dict[int, PdoCodec]:
        """The configured PDO codecs by COB-ID (RPDO and TPDOs)."""
        codecs = dict(self.tpdo_codecs)
        if self.rpdo is not None and self.rpdo_codec is not None:
            codecs[self.rpdo.cob_id] = self.rpdo_codec
        return codecs

    def rpdo_cob(self) -> int:
        """The RPDO's COB-ID; a :class:`DriveError` before ``configure``."""
        if self.rpdo is None:
            raise DriveError(f"node {self._link.node_id} is not configured; call configure() first")
        return self.rpdo.cob_id

    def require_codec(self) -> PdoCodec:
        """The RPDO's codec; a :class:`DriveError` saying why there is none to use (closed, not started)."""
        self._link.require_operational()
        if self.rpdo_codec is None:
            raise DriveError(f"node {self._link.node_id} is not configured; call configure() first")
        return self.rpdo_codec
