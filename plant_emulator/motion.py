"""The physics tick of the virtual drive and its realtime clock.

Each cycle the power stage turns the 402 state and the mode's target into one plant input (velocity or torque),
advances the plant from :mod:`plant_emulator.physics` by one cycle period, and writes the feedback (0x606C,
0x6077, 0x6064) back to the store; at each SYNC, after the latch, :meth:`AxisPhysics.publish_demand` writes the
demand echo (0x606B / 0x6074, where the EDS has them). Torque limiting held too long and the plant's over-speed
flag are faults; the quick stop ramp ends when the axis is at rest. While the power stage is off the drive keeps the
axis's holding brake closed (``plant.pmsm.brake_torque``; a plant without one coasts, under its load if it has one).

In lockstep mode the device calls :meth:`AxisPhysics.tick` at each SYNC; in realtime mode
:meth:`AxisPhysics.run_realtime` calls it on the wall clock, one cycle period per tick, SYNC or not: absolute
deadlines (no drift), ``time.sleep`` between them under the host setup of ``emulator.realtime``
(:mod:`drivers.realtime`: timer slack 1 ns, optionally SCHED_FIFO for this thread and the CAN receive thread, so a
tick is not tens of microseconds late by design), a tick late by less than :data:`REALTIME_MAX_LAG` periods is
caught up at once, a longer stall restarts the clock instead of bursting. The physics is reached only through
:meth:`Plant.step` (one step per tick, whatever the plant's implementation).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import numpy as np
from canopen import objectdictionary as cod

from drivers.cia402 import Obj, OperationMode, QuickStopOption
from drivers.realtime import NOTIFIER_THREAD_PREFIX, RealtimeConfig, RealtimeSession, collect_young
from plant_emulator.application import Cia402Application, FaultKind
from plant_emulator.axis import Axis, Units, toward
from plant_emulator.node import EmulatedNode
from plant_emulator.physics.base import Plant
from plant_emulator.settings import EmulatorConfig
from plant_emulator.state_machine import MotionKind

__all__ = ["PHASE_MEMORY", "AxisPhysics", "default_units", "phased_tick"]

VELOCITY_RESOLUTION_INDEX = 0x2000  # manufacturer object of the shipped EDS: counts of 0x606C per rpm
RAMP_SETTLE_TIME = 3.0  # s a finished quick-stop ramp waits at most for the axis to come to rest
REALTIME_MAX_LAG = 10  # periods behind the wall clock after which the clock restarts instead of catching up
PHASE_MEMORY = 10  # periods after the last SYNC during which the realtime ticks stay phased to the SYNCs
GC_EVERY_TICKS = 1000  # realtime: collect the young generations this often (automatic gc is off, drivers.realtime)
_SLOW_QUICK_STOP = (QuickStopOption.SLOW_DOWN_RAMP_THEN_DISABLE, QuickStopOption.SLOW_DOWN_RAMP_STAY)


def default_units(
    plant: Plant, od: cod.ObjectDictionary, velocity_scale: float | None, torque_scale: float | None
) -> Units:
    """The given scales, else the drive's defaults: a PMSM counts 0x2000 per rpm and per mille of rated torque."""
    if velocity_scale is None:
        velocity_scale = 1.0
        if hasattr(plant, "set_input_kind") and VELOCITY_RESOLUTION_INDEX in od:
            resolution = od[VELOCITY_RESOLUTION_INDEX]
            default = resolution.default if isinstance(resolution, cod.ODVariable) else None
            velocity_scale = float(default) if isinstance(default, (int, float)) and default > 0 else 1.0
    if torque_scale is None:
        rated_torque = getattr(plant, "rated_torque", None)
        torque_scale = 1000.0 / float(rated_torque) if rated_torque is not None else 1.0  # N m -> per mille
    return Units(float(velocity_scale), float(torque_scale))


class AxisPhysics:
    """One cycle of the power stage and the plant, and the wall clock that drives it in realtime mode.

    Parameters
    ----------
    plant
        The physics; output 0 is the velocity. A PMSM (``set_input_kind``) is switched between velocity and
        torque input.
    node
        The drive's node (targets in, feedback out).
    application
        The 402 application: its state decides the motion, its faults and statusword are raised here.
    settings
        The ``emulator:`` section (limits, standstill).
    default_cycle_period
        Seconds per cycle while 0x1006 is 0.
    """

    def __init__(
        self,
        plant: Plant,
        node: EmulatedNode,
        application: Cia402Application,
        settings: EmulatorConfig,
        *,
        default_cycle_period: float,
    ) -> None:
        self.plant = plant
        self.node = node
        self.application = application
        self.settings = settings
        self.axis: Axis = application.axis
        self.units: Units = application.units
        self._default_cycle_period = default_cycle_period
        self._is_pmsm = hasattr(plant, "set_input_kind")
        self._has_brake = hasattr(plant, "set_brake")
        self._brake_closed = False  # a plant starts with its brake open (set_brake is called on a change only)
        # the object dictionary never changes while the drive runs: whether it has 0x1006 is asked once
        self._has_cycle_period = node.has(Obj.COMMUNICATION_CYCLE_PERIOD)
        self._has_demand = node.has(Obj.VELOCITY_DEMAND_VALUE) or node.has(Obj.TORQUE_DEMAND)
        self._trial = 1  # the trial whose initial condition the plant restarts from after a divergence

    @property
    def cycle_period(self) -> float:
        """Seconds per cycle: 0x1006 (microseconds) when set, else the default."""
        micros = self.node.read(Obj.COMMUNICATION_CYCLE_PERIOD) if self._has_cycle_period else 0
        return micros * 1e-6 if micros > 0 else self._default_cycle_period

    def tick(self, dt: float, *, publish: bool = True) -> None:
        """Advance the plant one cycle with the active command; update feedback, limits, ramps, and (``publish``)
        the statusword -- the SYNC consumer, which publishes it anyway once the RPDOs are latched, says not to."""
        motion = self.application.machine.motion()
        kind, u = self._plant_input(motion, dt)
        plant, units = self.plant, self.units
        if self._is_pmsm and kind != plant.input_kind:  # type: ignore[attr-defined]
            plant.set_input_kind(kind)  # type: ignore[attr-defined]  # a bumpless switch, when it changes
        elif motion is MotionKind.TORQUE_OFF:
            u = 0.0
        brake_closed = motion is MotionKind.TORQUE_OFF  # the drive closes the holding brake with its power stage
        if self._has_brake and brake_closed is not self._brake_closed:
            plant.set_brake(brake_closed)  # type: ignore[attr-defined]
            self._brake_closed = brake_closed
        # On the plant's class, not the instance: a wrapper that delegates attributes keeps its own step (ScalarPlant)
        step_scalar: Callable[[Plant, float, float], float] | None = getattr(type(plant), "step_scalar", None)
        if step_scalar is not None:
            y = step_scalar(plant, u, dt)
        else:
            out = plant.step(np.array([u]), dt)
            # a 1-d float array (every plant here) is read as it is; anything else is converted first
            y = float(out[0]) if type(out) is np.ndarray and out.ndim == 1 else float(
                np.asarray(out, dtype=float).reshape(-1)[0])
        if not math.isfinite(y):
            y = self._diverged()
        axis = self.axis
        axis.cycles += 1
        axis.velocity = units.counts(y)
        plant_position = getattr(plant, "position_counts", None)
        if plant_position is not None:
            axis.position = float(plant_position)
        else:
            axis.position += y * dt  # no encoder in the model: the integral of the output
        plant_torque = getattr(plant, "torque", None)
        if plant_torque is not None:
            axis.torque = float(plant_torque) * units.torque_scale
        else:
            axis.torque = u * units.torque_scale if kind == "torque" else 0.0
        self._check_limits(motion, dt)
        produce = self.node.produce
        produce(Obj.VELOCITY_ACTUAL_VALUE, axis.velocity)
        produce(Obj.TORQUE_ACTUAL_VALUE, axis.torque)
        produce(Obj.POSITION_ACTUAL_VALUE, axis.position)
        if publish:
            self.application.publish_status()

    def publish_demand(self) -> None:
        """The demand echo, where the EDS has it: 0x606B (CSV, PV) or 0x6074 (CST) = the target latched at this
        SYNC, which the power stage follows from now on (the SYNC consumer calls it after the latch, before the TPDOs
        sample the store), as a real drive reports the demand it applies.

        Why at the SYNC and not in :meth:`tick`: in realtime the physics ticks on its own clock, and the TPDO set
        answering SYNC ``k`` must carry the demand latched at SYNC ``k`` (the bench compares it with what it knows it
        sent). The emulator applies no limit of its own to the target (its plant saturates), so the latched target
        is the demand; off OPERATION ENABLED it is the quick stop ramp's velocity, else 0.
        """
        if not self._has_demand:
            return
        node = self.node
        motion = self.application.machine.motion()
        following = motion is MotionKind.FOLLOW_TARGET
        if int(node.read(Obj.MODES_OF_OPERATION_DISPLAY)) == OperationMode.CYCLIC_SYNC_TORQUE:
            node.produce(Obj.TORQUE_DEMAND, node.read(Obj.TARGET_TORQUE) if following else 0)
            return
        if following:
            demand = node.read(Obj.TARGET_VELOCITY)
        else:
            demand = self.axis.ramp_velocity if motion is MotionKind.QUICK_STOP_RAMP else 0
        node.produce(Obj.VELOCITY_DEMAND_VALUE, demand)

    def _plant_input(self, motion: MotionKind, dt: float) -> tuple[str, float]:
        """The plant's input kind ("velocity" / "torque") and value for this cycle, in plant units."""
        axis, units, node = self.axis, self.units, self.node
        if motion is MotionKind.FOLLOW_TARGET:
            mode = int(node.read(Obj.MODES_OF_OPERATION_DISPLAY))
            if mode == OperationMode.CYCLIC_SYNC_TORQUE:
                return "torque", units.plant_torque(float(node.read(Obj.TARGET_TORQUE)))
            if mode == OperationMode.PROFILE_VELOCITY:
                axis.profile_velocity = self._profile_step(axis.profile_velocity, dt)
                return "velocity", units.plant_velocity(axis.profile_velocity)
            return "velocity", units.plant_velocity(float(node.read(Obj.TARGET_VELOCITY)))
        if motion is MotionKind.QUICK_STOP_RAMP:
            axis.ramp_velocity = toward(axis.ramp_velocity, 0.0, self._quick_stop_deceleration() * dt)
            return "velocity", units.plant_velocity(axis.ramp_velocity)
        if motion is MotionKind.HOLD_STANDSTILL:
            axis.ramp_velocity = 0.0
            return "velocity", units.plant_velocity(axis.ramp_velocity)
        return "torque", 0.0

    def _check_limits(self, motion: MotionKind, dt: float) -> None:
        """Torque limit held too long and over-speed are faults; a finished quick stop ramp ends at rest."""
        axis = self.axis
        torque_limited = bool(getattr(self.plant, "torque_limited", False))
        over_speed = bool(getattr(self.plant, "over_speed", False))
        axis.internal_limit = torque_limited
        axis.torque_limited_cycles = axis.torque_limited_cycles + 1 if torque_limited else 0
        energised = motion is not MotionKind.TORQUE_OFF
        if energised and over_speed:
            self.application.raise_fault(FaultKind.OVER_SPEED)
        limit_cycles = self.settings.torque_limit_fault_cycles
        if energised and limit_cycles and axis.torque_limited_cycles >= limit_cycles:
            self.application.raise_fault(FaultKind.OVER_CURRENT)
        if motion is MotionKind.QUICK_STOP_RAMP and axis.ramp_velocity == 0.0:
            axis.ramp_zero_time += dt
            standstill = abs(axis.velocity) <= self.units.counts(self.settings.standstill_velocity)
            if standstill or axis.ramp_zero_time >= RAMP_SETTLE_TIME:
                self.application.machine.ramp_finished()

    def _profile_step(self, current: float, dt: float) -> float:
        target = float(self.node.read(Obj.TARGET_VELOCITY))
        speeding_up = abs(target) > abs(current) and (target * current >= 0)
        index = Obj.PROFILE_ACCELERATION if speeding_up else Obj.PROFILE_DECELERATION
        rate = float(self.node.read(index)) if self.node.has(index) else math.inf
        return toward(current, target, rate * dt if rate > 0 else math.inf)

    def _quick_stop_deceleration(self) -> float:
        slow = self.application.machine.quick_stop_option in _SLOW_QUICK_STOP
        index = Obj.PROFILE_DECELERATION if slow else Obj.QUICK_STOP_DECELERATION
        rate = float(self.node.read(index)) if self.node.has(index) else 0.0
        return rate if rate > 0 else math.inf

    def _diverged(self) -> float:
        """The plant's output is not finite (its physics diverged: a config the checks let through, a drift): the
        drive faults as a real one does on an impossible measurement (EMCY 0x6100, torque off), and the plant
        starts again from the current trial's initial condition, so the drive stays readable and can be stopped.
        Why not raise: inside the bus's send it reached the bench as a traceback, again in its stop."""
        self.application.raise_fault(FaultKind.PLANT_DIVERGED)
        self.plant.reset(self._trial)
        return float(np.asarray(self.plant.output(), dtype=float).reshape(-1)[0])

    def begin_trial(self, trial: int) -> None:
        """``plant.reset(trial)`` and the feedback of the plant's initial condition (see ``VirtualDrive``)."""
        self._trial = trial
        self.plant.reset(trial)
        y = np.asarray(self.plant.output(), dtype=float).reshape(-1)
        axis = self.axis
        axis.velocity = self.units.counts(float(y[0]))
        axis.profile_velocity = axis.ramp_velocity = axis.velocity
        plant_position = getattr(self.plant, "position_counts", None)
        axis.position = float(plant_position) if plant_position is not None else 0.0
        self.node.produce(Obj.VELOCITY_ACTUAL_VALUE, axis.velocity)
        self.node.produce(Obj.POSITION_ACTUAL_VALUE, axis.position)

    def run_realtime(self, stop: threading.Event, lock: threading.RLock, after_tick: Callable[[], None],
                     last_sync: Callable[[], float | None] | None = None) -> None:
        """Tick on the wall clock until ``stop`` is set (the drive's physics thread), ``after_tick`` each time.

        ``last_sync()``: the ``time.perf_counter()`` of the last SYNC, if any; with ``emulator.realtime.tick_phase``
        the ticks are kept that fraction of a period after the SYNCs (:func:`phased_tick`).
        """
        phase = self.settings.realtime.tick_phase
        with physics_session(self.settings.realtime):
            next_tick = time.perf_counter()
            ticks = 0
            while not stop.is_set():
                period = self.cycle_period
                next_tick += period
                if phase is not None and last_sync is not None:
                    next_tick = phased_tick(next_tick, last_sync(), period, phase)
                delay = next_tick - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)  # not stop.wait(): a sleep honours the 1 ns timer slack; stop is seen next tick
                elif delay < -REALTIME_MAX_LAG * period:
                    next_tick = time.perf_counter()  # fell far behind (debugger, overload): do not burst
                with lock:
                    if self.node.alive:
                        self.tick(period)
                        after_tick()
                ticks += 1
                if ticks % GC_EVERY_TICKS == 0:
                    collect_young()


#: the name of each drive's physics thread begins with this (``VirtualDrive`` names it ``drive-physics-NODE``)
PHYSICS_THREAD_PREFIX = "drive-physics"


def physics_session(config: RealtimeConfig) -> RealtimeSession:
    """The host setup a physics thread enters: the cyclic priority for itself, every receive thread AND every other
    drive's physics thread of the process, the helper priority for the rest.

    Why the physics threads: a process of several drives (``plant-emulator --node-id 1,2,3,4``) enters one session
    per drive, and a session demotes every thread it does not name cyclic: the fourth drive's session demoted the
    first three drives' physics threads to the helper priority, below every cyclic thread of the host, where one
    preempted while holding its drive's lock holds that drive's SYNC handling with it (priority inversion). Runs of
    that process failed on node 1 alone (no TPDO for 21 SYNCs; its SYNC-loss EMCY) while nodes 2-4 answered."""
    cyclic = [thread for thread in threading.enumerate()
              if thread.name.startswith((PHYSICS_THREAD_PREFIX, NOTIFIER_THREAD_PREFIX))]
    return RealtimeSession(config, cyclic_threads=cyclic)


def phased_tick(tick: float, sync: float | None, period: float, phase: float) -> float:
    """The tick time nearest to ``tick`` that lies ``phase`` periods after a SYNC grid through ``sync``.

    The SYNC handler and the physics tick both need the GIL and the drive's lock; a tick that falls on a SYNC delays
    its answer by a whole tick. Keeping the ticks mid-cycle moves them out of its way. The shift is at most half a
    period (one tick interval between 0.5 and 1.5 periods; the physics still advances one period per tick), and none
    without a SYNC in the last :data:`PHASE_MEMORY` periods: then the physics keeps its own grid.
    """
    if sync is None or tick - sync > PHASE_MEMORY * period:
        return tick
    target = sync + phase * period
    return target + round((tick - target) / period) * period
