"""A virtual CiA 402 servo drive: canopen's ``LocalNode`` plus everything a real drive adds to it.

What canopen gives (and is used as is): the object dictionary from the EDS, the SDO server (expedited and
segmented transfers, abort codes for unknown objects / sub-indices / read-only objects / length mismatch), the
NMT slave with its heartbeat producer (0x1017), and the EMCY producer.

What a real drive adds is composed here from service objects, the way canopen composes a node from ``sdo``,
``nmt``, ``emcy`` and ``pdo``; each holds the drive's :class:`~plant_emulator.node.EmulatedNode`:

================================================  ==========================================================
service                                           job
================================================  ==========================================================
:class:`~plant_emulator.node.EmulatedNode`        ``LocalNode`` + post-store hook, typed store access
:class:`~plant_emulator.sdo_guard.SdoGuard`       SDO write validation (abort codes), no SDO in *stopped*
:class:`~plant_emulator.pdo_engine.PdoEngine`     RPDO latch on SYNC, TPDO sync/acyclic/event, rebuilt from
                                                  the OD on every remap
:class:`~plant_emulator.supervision.Supervisor`   heartbeat consumer 0x1016, SYNC loss, TPDO event timers
:class:`~plant_emulator.application.Cia402Application`  controlword -> :mod:`plant_emulator.state_machine`,
                                                  faults, EMCY, 0x6007 / 0x605A reactions, statusword
:class:`~plant_emulator.motion.AxisPhysics`       the physics tick and the realtime clock
:class:`VirtualDrive` (this module)               wiring, life cycle, SYNC consumer, NMT reset services
================================================  ==========================================================

The device itself keeps what ties them together: the SYNC consumer (``LocalNode`` does not subscribe to SYNC),
the dispatch of a stored value to the service that reacts to it, and the NMT reset services (canopen's
``NmtSlave`` only changes its state byte to 0 and stops there): reset node restores every object to its EDS
default, reset communication only 0x1000..0x1FFF; both send the boot-up message and enter pre-operational.

Cycle order at SYNC *n* (lockstep; the one-cycle transport delay of a SYNC-driven loop, errata 6):

1. advance the physics by one cycle period with the command that was active during cycle *n-1*;
2. latch the synchronous RPDO values received since SYNC *n-1*: they become the active command, echoed in the
   demand objects 0x606B / 0x6074 where the EDS has them (:meth:`~plant_emulator.motion.AxisPhysics.publish_demand`);
3. sample the feedback and send the synchronous TPDOs.

So a target sent before SYNC *n* first moves the axis during cycle *n*, and its effect is first reported in the
TPDO of SYNC *n+1*. In realtime mode step 1 runs on the wall clock in its own thread (one cycle period per
tick, whether or not SYNC came); steps 2 and 3 run on SYNC.

Threads: on a wall-clock bus (python-can ``virtual``, ``udp_multicast``, hardware) the drive receives in canopen's
Notifier thread, polls its supervision in a thread and (realtime) ticks its physics in another. On a lockstep
in-process bus (:mod:`drivers.inprocess`, the embedded emulator's) it has no thread at all: frames arrive in the
sender's thread, and the heartbeat producer and the supervision poll are timers on the channel's simulated time.

Units: 0x60FF / 0x606C are counts of the EDS's velocity unit (0.001 rpm in the shipped EDS, 0x2000 = counts per
rpm); 0x6071 / 0x6077 are per mille of rated torque; 0x6064 is encoder increments (the PMSM's resolver counts).
The plant works in its own units; ``velocity_scale`` (counts per plant velocity unit) and ``torque_scale`` (per
mille per plant torque unit) convert, exactly as the master's ``drive.velocity_scale`` / ``drive.torque_scale``
do. A PMSM plant (rpm, N m) defaults to 0x2000 counts per rpm and ``1000 / rated_torque``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import can
import canopen
import numpy as np
from canopen import objectdictionary as cod

from drivers.cia301 import SYNC_COB_ID, CobIdEntry, FunctionCode, NmtCommand, NmtState, check_node_id
from drivers.cia402 import Obj, State402
from drivers.errors import InputError
from drivers.inprocess import InProcessBus, LockstepClock, connect_network, subscribe_cyclic, timebase_of
from drivers.od import DEFAULT_EDS
from drivers.receive_filter import FilteredNetwork
from drivers.timing import TimingMode  # its home is below the loop and the emulator; the old name stays
from plant_emulator.application import APPLICATION_OBJECTS, Cia402Application, FaultKind
from plant_emulator.axis import Axis
from plant_emulator.motion import PHYSICS_THREAD_PREFIX, AxisPhysics, default_units
from plant_emulator.node import EmulatedNode, load_object_dictionary
from plant_emulator.pdo_engine import PDO_AREAS, PdoEngine
from plant_emulator.physics.base import Plant
from plant_emulator.sdo_guard import SdoGuard
from plant_emulator.settings import EmulatorConfig
from plant_emulator.state_machine import MotionKind, PowerStateMachine
from plant_emulator.supervision import MONITOR_PERIOD, Supervisor
from plant_emulator.sync_rx import SyncAnticipatingNotifier

__all__ = [
    "DEFAULT_EDS",
    "DriveSnapshot",
    "FaultKind",
    "TimingMode",
    "VirtualDrive",
    "load_object_dictionary",
]

NOTIFIER_CYCLE = 0.1  # s the notifier blocks in recv(): bounds how long stop() waits (canopen default 1 s)
THREAD_JOIN_TIMEOUT = 2.0  # s stop() waits for each of the drive's threads
_COMMUNICATION_AREA = range(0x1000, 0x2000)


@dataclass
class DriveSnapshot:
    """What the drive shows at one instant (for tests and the emulator's own log)."""

    nmt_state: NmtState
    state: State402
    statusword: int
    mode: int
    velocity: int
    torque: int
    position: int
    error_code: int
    error_register: int
    cycles: int
    plant_time: float
    plant_output: list[float] = field(default_factory=list)


class VirtualDrive:
    """A CiA 402 servo drive on a python-can bus, driving a simulated plant.

    Parameters
    ----------
    plant
        The physics (:func:`plant_emulator.physics.build_plant`); output 0 is the velocity. A PMSM axis
        (``model == "pmsm"``) is switched between velocity and torque input with ``set_input_kind``.
    node_id
        CANopen node id (1..127).
    cycle_period
        Seconds per cycle when 0x1006 is 0 (the master normally writes 0x1006 at start-up).
    settings
        The ``emulator:`` section.
    od
        The object dictionary; default: loaded from ``settings.eds`` or the shipped EDS.
    velocity_scale, torque_scale
        Plant units -> drive units (0x60FF/0x606C physical unit; per mille of rated torque).

    Notes
    -----
    Call :meth:`start` with a bus; the drive takes the bus over (``stop`` shuts it down). All CAN callbacks run
    in canopen's notifier thread (on a lockstep in-process bus: the sender's); the realtime physics thread and
    the supervision thread (or timer) share one lock.
    """

    def __init__(
        self,
        plant: Plant,
        *,
        node_id: int = 1,
        cycle_period: float = 0.01,
        settings: EmulatorConfig | None = None,
        od: cod.ObjectDictionary | None = None,
        velocity_scale: float | None = None,
        torque_scale: float | None = None,
    ) -> None:
        if plant.n_inputs != 1:
            raise InputError(f"the virtual drive drives a single-input plant; this one has {plant.n_inputs}")
        if not (cycle_period > 0 and math.isfinite(cycle_period)):
            raise InputError(f"cycle_period must be positive, got {cycle_period!r}")
        for name, value in (("velocity_scale", velocity_scale), ("torque_scale", torque_scale)):
            if value is not None and not (value > 0 and math.isfinite(value)):
                raise InputError(f"{name} must be positive, got {value!r}")
        self.settings = settings if settings is not None else EmulatorConfig()
        self.node_id = check_node_id(node_id)
        self.plant = plant
        self.timing = TimingMode(self.settings.timing)
        self.od = od if od is not None else load_object_dictionary(self.node_id, self.settings.eds)
        self.node = EmulatedNode(self.node_id, self.od)
        self._lock = threading.RLock()
        self.sdo_guard = SdoGuard(self.node, self._lock)
        self.application = Cia402Application(
            self.node, self.settings, Axis(), default_units(plant, self.od, velocity_scale, torque_scale),
            on_state_change=lambda: self.pdos.send_event_driven(),
        )
        self.pdos = PdoEngine(self.node, self._lock, on_write=self._after_write,
                              on_length_error=self.application.pdo_length_error)
        self.physics = AxisPhysics(plant, self.node, self.application, self.settings,
                                   default_cycle_period=float(cycle_period))
        realtime = self.timing is TimingMode.REALTIME
        self.supervisor = Supervisor(
            self.node, self._lock, self.pdos, on_loss=self._on_loss,
            cycle_period=lambda: self.physics.cycle_period,
            sync_loss_cycles=self.settings.sync_loss_cycles if realtime else None,
        )
        self.node.after_write = self._after_write
        self._sync_cob_id = SYNC_COB_ID
        self._sync_at: float | None = None  # time.perf_counter() of the last SYNC (realtime)
        self._running = False
        self._threads: list[threading.Thread] = []
        self._poll_timer: Callable[[], None] | None = None  # cancels the supervision timer (lockstep bus)
        self._stop_event = threading.Event()
        self._in_process_clock = False  # a lockstep in-process bus: its simulated time is the only clock
        self.sync_count = 0
        self.stale_syncs = 0  # realtime: SYNCs handled a period or more after they arrived, left unanswered
        self.trace: Callable[[DriveSnapshot], None] | None = None  # called after every cycle, if set
        self._reset_application()

    # ---------------------------------------------------------------------------------------------------------
    # life cycle

    def start(self, bus: can.BusABC) -> None:
        """Join ``bus`` (taken over: :meth:`stop` shuts it down), send the boot-up message, enter pre-operational."""
        if self._running:
            raise RuntimeError("the virtual drive is already running")
        clock = timebase_of(bus)
        if isinstance(clock, LockstepClock) and self.timing is TimingMode.REALTIME:
            raise InputError("a realtime drive ticks on the wall clock: give it a wall-clock bus, not a lockstep one")
        self.supervisor.clock = clock.now
        # a wall-clock bus of several nodes: the kernel drops the other nodes' frames before this drive's receive
        # thread wakes for them (drivers.receive_filter); the in-process bus delivers by COB-ID already
        network = canopen.Network(bus) if isinstance(bus, InProcessBus) else FilteredNetwork(bus)
        network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
        self._connect(network)
        self.node.link = network
        network[self.node_id] = self.node
        # Replace canopen's SDO and NMT subscriptions with gated ones (no SDO in stopped, NMT resets handled).
        self.sdo_guard.attach(network)
        network.unsubscribe(FunctionCode.NMT, self.node.nmt.on_command)
        network.subscribe(FunctionCode.NMT, self._on_nmt_command)
        self.node.alive = True
        self._running = True
        self._stop_event.clear()
        with self._lock:
            self._subscribe_sync()
            self.pdos.rebuild()
            self.supervisor.rebuild_heartbeat_consumer()
            self._boot()
        self._in_process_clock = isinstance(clock, LockstepClock)
        if isinstance(clock, LockstepClock):
            self._poll_timer = clock.every(MONITOR_PERIOD, self.supervisor.poll).cancel
        else:
            self._start_thread(lambda: self.supervisor.run(self._stop_event), "drive-supervision")
        if self.timing is TimingMode.REALTIME:
            self._start_thread(lambda: self.physics.run_realtime(self._stop_event, self._lock, self._emit_trace,
                                                                 lambda: self._sync_at), PHYSICS_THREAD_PREFIX)

    def _connect(self, network: canopen.Network) -> None:
        """Start the receive path: realtime on a python-can bus with ``emulator.realtime.sync_anticipation``, a
        thread that is awake when SYNC is due (:mod:`plant_emulator.sync_rx`; the first drive of the process only);
        else canopen's (or the in-process transport's) own."""
        margin = self.settings.realtime.sync_anticipation
        bus = network.bus
        if (self.timing is not TimingMode.REALTIME or not margin or bus is None or isinstance(bus, InProcessBus)
                or SyncAnticipatingNotifier.running()):  # one per process: see plant_emulator.sync_rx
            connect_network(network)
            return
        network.notifier = SyncAnticipatingNotifier(
            bus, network.listeners, NOTIFIER_CYCLE, margin=margin,
            period=lambda: self.physics.cycle_period, sync_id=lambda: self._sync_cob_id,
        )

    def stop(self) -> None:
        """Stop the threads, the heartbeat and the network (the bus is shut down)."""
        if not self._running:
            return
        self._running = False
        self._stop_event.set()
        if self._poll_timer is not None:
            self._poll_timer()
            self._poll_timer = None
        for thread in self._threads:
            thread.join(timeout=THREAD_JOIN_TIMEOUT)
        self._threads.clear()
        self.node.nmt.stop_heartbeat()
        if self.node.link is not None:
            self.node.link.disconnect()
            self.node.link = None

    def __enter__(self) -> VirtualDrive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _on_loss(self, fault: FaultKind) -> None:
        """The supervision found the master's heartbeat (or SYNC) gone: the 0x6007 reaction, and in lockstep on a
        wall-clock bus the drive's own clock from then on, until the reaction is done or SYNC comes back.

        Why: in lockstep the physics advances with each SYNC, and a lost master sends none: the quick-stop ramp of
        the reaction waited for SYNCs that never came, and the drive stayed in QUICK STOP ACTIVE with its power stage
        on (measured after a SIGKILL of the bench: 15 s and counting). A real drive runs its own clock. The same
        after NMT took the drive out of OPERATIONAL (in STOPPED no SYNC reaches it)."""
        self.application.detect(fault)
        self._own_clock_for_the_reaction()

    def _own_clock_for_the_reaction(self) -> None:
        """Lockstep on a wall-clock bus: run the reaction just begun on the drive's own clock (see
        :meth:`_on_loss`); once at a time."""
        lockstep = self.timing is TimingMode.LOCKSTEP and self._running and not self._in_process_clock
        if lockstep and not any(thread.name.startswith("drive-fault-reaction") and thread.is_alive()
                                for thread in self._threads):
            self._start_thread(self._finish_reaction, "drive-fault-reaction")

    def _finish_reaction(self) -> None:
        """Tick the physics on the wall clock (one cycle period a tick) while the reaction ramps the axis down or
        holds it, until the power stage is off, SYNC comes back (the master is there again: SYNC is the clock) or
        the drive stops."""
        syncs = self.sync_count
        motion = self.application.machine.motion
        while not self._stop_event.wait(self.physics.cycle_period):
            with self._lock:
                if self.sync_count != syncs or motion() is MotionKind.TORQUE_OFF:
                    return
                self.physics.tick(self.physics.cycle_period)
                self.pdos.send_event_driven()

    def _start_thread(self, target: Callable[[], None], name: str) -> None:
        thread = threading.Thread(target=target, name=f"{name}-{self.node_id}", daemon=True)
        self._threads.append(thread)
        thread.start()

    # ---------------------------------------------------------------------------------------------------------
    # fault injection (tests and the bench's fault tests)

    def inject_fault(self, kind: FaultKind | str) -> None:
        """Raise fault ``kind`` as the drive would detect it (EMCY, 0x603F, 0x1001, state reaction)."""
        fault = FaultKind(kind)
        with self._lock:
            self.application.detect(fault)

    def begin_trial(self, trial: int) -> None:
        """Start trial ``trial`` (1-based) of the physics: ``plant.reset(trial)``.

        The plant returns to its initial condition and its trial-dependent parts (the disturbance from
        ``plant.disturbance.start_trial`` on, per-trial noise and drift) follow ``trial``. The bench calls this
        between trials of an embedded run, when the axis has settled; a real drive has no such hook, so a
        cross-process run keeps one continuous trial-1 physics.
        """
        with self._lock:
            self.physics.begin_trial(trial)

    def stop_responding(self) -> None:
        """Simulate the drive dying: no heartbeat, no SDO answers, no PDOs, no physics, from now on."""
        with self._lock:
            self.node.alive = False
            self.node.nmt.stop_heartbeat()

    def send_emcy(self, code: int, register: int | None = None, data: bytes = b"") -> None:
        """Send an EMCY frame with ``code`` (and ``register``, default: the present 0x1001) without a state change."""
        with self._lock:
            reg = self.node.read(Obj.ERROR_REGISTER) if register is None else int(register)
            self.application.emcy(int(code), reg, data)

    # ---------------------------------------------------------------------------------------------------------
    # read-only views

    @property
    def state(self) -> State402:
        """The present CiA 402 state."""
        return self.application.machine.state

    @property
    def machine(self) -> PowerStateMachine:
        """The CiA 402 power state machine (replaced by a fresh one at NMT reset node)."""
        return self.application.machine

    @property
    def nmt_state(self) -> NmtState:
        """The present NMT state."""
        return self.node.nmt_state

    @property
    def emcy_log(self) -> list[tuple[int, int]]:
        """Every EMCY (code, register) the drive raised, sent or not (for tests and the CLI)."""
        return self.application.emcy_log

    @property
    def receive_filter(self) -> str:
        """Where frames of COB-IDs the drive does not subscribe to are dropped (:class:`drivers.receive_filter.
        FilterKind`: ``can_raw_filter``, ``bpf``), or ``none``: canopen drops them in Python."""
        link = self.node.link
        return str(link.filter_kind) if isinstance(link, FilteredNetwork) else "none"

    @property
    def cycle_period(self) -> float:
        """Seconds per cycle: 0x1006 (microseconds) when set, else the constructor's ``cycle_period``."""
        return self.physics.cycle_period

    def snapshot(self) -> DriveSnapshot:
        """The drive's present state and feedback."""
        node = self.node
        with self._lock:
            return DriveSnapshot(
                nmt_state=self.nmt_state,
                state=self.state,
                statusword=node.read(Obj.STATUSWORD),
                mode=node.read(Obj.MODES_OF_OPERATION_DISPLAY),
                velocity=node.read(Obj.VELOCITY_ACTUAL_VALUE),
                torque=node.read(Obj.TORQUE_ACTUAL_VALUE) if node.has(Obj.TORQUE_ACTUAL_VALUE) else 0,
                position=node.read(Obj.POSITION_ACTUAL_VALUE) if node.has(Obj.POSITION_ACTUAL_VALUE) else 0,
                error_code=node.read(Obj.ERROR_CODE) if node.has(Obj.ERROR_CODE) else 0,
                error_register=node.read(Obj.ERROR_REGISTER),
                cycles=self.physics.axis.cycles,
                plant_time=float(self.plant.time),
                plant_output=[float(v) for v in np.asarray(self.plant.output()).reshape(-1)],
            )

    # ---------------------------------------------------------------------------------------------------------
    # a value is in the store: who reacts

    def _after_write(self, index: int, subindex: int) -> None:
        """React to a value now in the store (from SDO or from an RPDO)."""
        if index in APPLICATION_OBJECTS:
            self.application.react(index)
        elif index == Obj.COB_ID_SYNC:
            self._subscribe_sync()
        elif index == Obj.CONSUMER_HEARTBEAT_TIME:
            self.supervisor.rebuild_heartbeat_consumer()
        elif any(index in area for area in PDO_AREAS):
            self.pdos.rebuild()

    # ---------------------------------------------------------------------------------------------------------
    # NMT

    def _boot(self) -> None:
        """Boot-up message, then pre-operational with the heartbeat producer of 0x1017 (canopen's NmtSlave)."""
        nmt = self.node.nmt
        nmt.stop_heartbeat()
        nmt.send_command(NmtCommand.RESET_NODE)  # state 0: canopen sends the boot-up frame
        nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)  # 0 -> 127 starts the heartbeat per 0x1017

    def _reset_application(self) -> None:
        self.node.reset_store(None)
        self.application.power_on()

    def _on_nmt_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self.node.alive or len(data) < 2:
            return
        command, target = data[0], data[1]
        if target not in (0, self.node_id):
            return
        with self._lock:
            if command == NmtCommand.RESET_NODE:
                self._reset_application()
                self._after_reset()
            elif command == NmtCommand.RESET_COMMUNICATION:
                self.node.reset_store(_COMMUNICATION_AREA)
                self._after_reset()
            else:
                was_operational = self.nmt_state is NmtState.OPERATIONAL
                self.node.nmt.on_command(can_id, data, timestamp)
                if self.nmt_state is not NmtState.OPERATIONAL:
                    self.pdos.drop_pending()
                    if was_operational:
                        self.application.left_operational()  # the 0x6007 reaction, see there
                        self._own_clock_for_the_reaction()

    def _after_reset(self) -> None:
        self._subscribe_sync()
        self.pdos.rebuild()
        self.supervisor.rebuild_heartbeat_consumer()
        self.supervisor.forget_sync()
        self._boot()

    # ---------------------------------------------------------------------------------------------------------
    # SYNC: the cycle

    def _subscribe_sync(self) -> None:
        network = self.node.link
        if network is None:
            return
        if self._sync_cob_id in network.subscribers and self._on_sync in network.subscribers[self._sync_cob_id]:
            network.unsubscribe(self._sync_cob_id, self._on_sync)
        if self.node.has(Obj.COB_ID_SYNC):
            self._sync_cob_id = CobIdEntry.decode(int(self.node.read(Obj.COB_ID_SYNC))).can_id
        subscribe_cyclic(network, self._sync_cob_id, self._on_sync)

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self.node.alive:
            return
        lockstep = self.timing is TimingMode.LOCKSTEP
        if not lockstep:
            self._sync_at = time.perf_counter()  # the realtime physics keeps its ticks away from this (tick_phase)
        with self._lock:
            self.sync_count += 1
            self.supervisor.sync_received()
            operational = self.node.operational
            stale = not lockstep and _stale(timestamp, self.physics.cycle_period)
            if lockstep:  # (1) physics with the command that was active; operational: its status is published below
                physics = self.physics
                physics.tick(physics.cycle_period, publish=not operational)
            if operational:
                self.pdos.latch()  # (2) the RPDOs received since the last SYNC become the command
                self.physics.publish_demand()  # its echo (0x606B / 0x6074), for the TPDOs below
                self.application.publish_status()
                if stale:  # see _stale: no answer beats one every receiver would take for the next SYNC's
                    self.stale_syncs += 1
                else:
                    self.pdos.send_synchronous()  # (3) sample and send
            if lockstep and self.trace is not None:
                self.trace(self.snapshot())

    def _emit_trace(self) -> None:
        if self.trace is not None:
            self.trace(self.snapshot())


#: the largest age of a SYNC's receive time stamp taken as real: a stamp older than this is not a wall-clock time
#: (an interface that stamps 0, or another clock's) and the SYNC is answered
_STAMP_PLAUSIBLE = 60.0


def _stale(timestamp: float, period: float) -> bool:
    """Whether a SYNC received at ``timestamp`` (the bus's wall-clock receive time) is handled a whole period or
    more late (a stalled emulator process catching up on its queue).

    Why it is not answered: the next SYNC is on the bus already, so the answer would reach every receiver after
    it, and the master, which takes the first complete TPDO set after a SYNC as that SYNC's answer, would take this
    older one for the next SYNC's -- a velocity measured a period or more earlier, and a demand echo of an older
    command (the echo check found three such sets in one run). Unanswered, the master counts a lost feedback and
    holds the last good value, which is the truth. A real drive answers from its SYNC interrupt, on time.
    """
    age = time.time() - timestamp
    return period <= age < _STAMP_PLAUSIBLE

