"""The compiled physics: numba kernels that ARE the plants' equations (there is no second, pure-Python copy).

:class:`~plant_emulator.physics.pmsm.PmsmPlant`, :class:`~plant_emulator.physics.first_order.FirstOrderPlant` and
:class:`~plant_emulator.physics.disturbance.Disturbance` keep their configuration, random streams and the
``Plant`` protocol in Python and call these kernels for the arithmetic of a step. The kernels work on flat
``float64`` arrays whose slots are named below (``PmsmState``, ``PmsmParam``), so one call advances a whole
caller step (all of its internal sub-steps) without returning to the interpreter.

Compilation: every kernel is ``cache=True``, so numba compiles it once per machine (about 2-4 s for all of them,
the first time ``plant_emulator.physics`` is imported after an install or a change of this file) and later
processes load the machine code from ``__pycache__`` (tens of milliseconds). :func:`warm_up` runs each kernel
once at import, so neither compilation nor loading ever lands in a control loop's first cycle. No ``fastmath``:
results are IEEE-exact and reproducible bit for bit for a seed.

Per caller step and per trial: :func:`scalar_plant_step` and :func:`pmsm_step` are a plant's whole step (the
scalar first-order plant's ZOH step with ``Delta``; the PMSM's sub-steps, the resolver's velocity and its filter),
called once per step by the plant classes and inside the compiled trial loop of
:mod:`plant_emulator.physics.trial`. :func:`variation_values` and :func:`disturbance_values` give ``Delta(t)``
and ``d(t)`` over consecutive steps: one step per call for the plant classes, a whole trial at once for the trial
loop (the same numbers: the same arithmetic in the same order).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numba import njit, types

__all__ = [
    "DisturbanceCode",
    "PmsmParam",
    "PmsmState",
    "VariationCode",
    "disturbance_value",
    "disturbance_values",
    "pmsm_advance",
    "pmsm_step",
    "pmsm_step_compiled",
    "scalar_plant_step",
    "scalar_zoh_step",
    "variation_values",
    "warm_up",
]

_RAD_PER_S_PER_RPM = 2.0 * math.pi / 60.0


@enum.unique
class DisturbanceCode(enum.IntEnum):
    """``plant.disturbance.kind`` as the kernels see it (``NONE`` also while the disturbance is not armed)."""

    NONE = 0
    CONSTANT = 1
    STEP = 2
    SINE = 3
    SQUARE = 4


@enum.unique
class VariationCode(enum.IntEnum):
    """``plant.variation.a`` / ``.b`` kind as the kernels see it."""

    NONE = 0
    SINE = 1
    RANDOM_WALK = 2


@enum.unique
class PmsmState(enum.IntEnum):
    """Slots of the PMSM kernel's state vector (SI units; flags are 0.0 / 1.0)."""

    THETA = 0  # unwrapped mechanical angle, rad
    OMEGA = 1  # mechanical speed, rad/s
    ID = 2
    IQ = 3
    INT_D = 4  # current-loop integrators, V
    INT_Q = 5
    INT_VELOCITY = 6  # velocity-loop integrator, N m
    OMEGA_ESTIMATE = 7  # the drive's own low-passed velocity estimate, rad/s
    COUNT = 8  # resolver count (an integer held exactly in a float64 up to 2**53)
    TORQUE = 9  # electromagnetic torque at the end of the last sub-step, N m
    TORQUE_COMMAND = 10  # torque command of the last sub-step, after the limit, N m
    TIME = 11  # seconds since the trial's reset
    TORQUE_LIMITED = 12  # the torque command was clipped during the last caller step
    OVER_SPEED = 13  # |w| exceeded speed_limit during the last caller step


@enum.unique
class PmsmParam(enum.IntEnum):
    """Slots of the PMSM kernel's parameter vector: the nominal tuning of the drive and the drawn motor."""

    POLE_PAIRS = 0
    SPEED_CAP = 1  # rated speed, rad/s
    VELOCITY_KP = 2
    VELOCITY_KI = 3
    SETPOINT_WEIGHT = 4
    TORQUE_LIMIT = 5
    TORQUE_CONSTANT = 6  # nominal Kt: the drive's iq reference
    INDUCTANCE_D_NOMINAL = 7
    INDUCTANCE_Q_NOMINAL = 8
    PSI_NOMINAL = 9
    KP_D = 10
    KP_Q = 11
    KI_CURRENT = 12
    V_MAX = 13
    PSI = 14  # drawn flux linkage
    RESISTANCE = 15  # drawn
    INDUCTANCE_D = 16  # drawn
    INDUCTANCE_Q = 17  # drawn
    INERTIA = 18  # drawn
    VISCOUS = 19  # drawn
    COULOMB = 20  # drawn
    COULOMB_SCALE = 21  # rad/s
    COGGING_AMPLITUDE = 22
    COGGING_PERIODS = 23
    DRIFT_AMPLITUDE = 24
    DRIFT_FREQUENCY = 25
    DRIFT_PHASE_PER_TRIAL = 26
    COUNT_ANGLE = 27  # rad per resolver count
    VELOCITY_LOOP_FILTER = 28  # s
    SPEED_LIMIT = 29  # rad/s
    DISTURBANCE_CODE = 30  # a DisturbanceCode, NONE while not armed
    DISTURBANCE_AMPLITUDE = 31
    DISTURBANCE_FREQUENCY = 32
    DISTURBANCE_START = 33
    HOLDING_TORQUE = 34  # the holding brake's torque while it is closed, N m; 0.0 while it is open (or absent)
    DRIFT_PHASE = 35  # rad, the inertia drift's phase at t = 0 of trial 1 (pmsm.drift.phase)
    DISTURBANCE_PHASE = 36  # rad (plant.disturbance.phase)
    # Derived from the slots above and the internal step h by pmsm_advance itself (_derive), kept for the next call
    # with the same h: a function of h and of slots that stay fixed once the plant is built (not of the per-trial
    # disturbance code or the brake's torque)
    DERIVED_STEP = 37  # the h the slots below hold for; any other value (0.0 in a new vector): not derived yet
    DECAY_D = 38  # exp(-R h / Ld)
    DECAY_Q = 39  # exp(-R h / Lq)
    LOOP_SMOOTHING = 40  # 1 - exp(-h / velocity_loop_filter); 1.0 without the filter
    COUNT_RATE = 41  # count_angle / h
    DRIFT_COSINE = 42  # cos(drift_frequency h): the drift's phase turns by drift_frequency h per internal step
    DRIFT_SINE = 43  # sin(drift_frequency h)
    TORQUE_CONSTANT_INVERSE = 44  # 1 / torque_constant
    COULOMB_SCALE_INVERSE = 45  # 1 / coulomb_scale
    COUNT_ANGLE_INVERSE = 46  # 1 / count_angle


PMSM_STATE_SIZE = len(PmsmState)
PMSM_PARAM_SIZE = len(PmsmParam)

_S = PmsmState
_P = PmsmParam
_D = DisturbanceCode


@njit(cache=True)
def disturbance_value(
    code: int, amplitude: float, frequency: float, phase: float, start_time: float, t: float
) -> float:
    """``d(t)`` of :class:`~plant_emulator.config.DisturbanceConfig` (``code`` is its kind, ``NONE`` if not armed;
    ``phase`` in rad moves the sine and the square wave)."""
    if code == _D.NONE:
        return 0.0
    if code == _D.CONSTANT:
        return amplitude
    elapsed = t - start_time
    if elapsed < 0:
        return 0.0
    if code == _D.STEP:
        return amplitude
    x = frequency * elapsed + phase  # + 0.0 is exact: phase 0 gives the same doubles as before the phase existed
    if code == _D.SINE:
        return amplitude * math.sin(x)
    # The square wave is the sign of sin(x). Away from its zeros (beyond 1e-6 of a period) the half period that x
    # falls in decides that sign for certain (x / 2 pi is off by under 1e-9 periods for |x / 2 pi| < 1e6), and a
    # libm call less per PMSM internal step; near a zero, or for a huge or non-finite x, sin itself decides.
    turns = x * (0.5 / math.pi)
    fraction = turns - math.floor(turns)
    if abs(turns) < 1e6 and 1e-6 < fraction < 0.5 - 1e-6:
        return amplitude
    if abs(turns) < 1e6 and 0.5 + 1e-6 < fraction < 1.0 - 1e-6:
        return -amplitude
    return amplitude if math.sin(x) >= 0 else -amplitude  # square


@njit(cache=True)
def disturbance_values(
    code: int, amplitude: float, frequency: float, phase: float, start_time: float, t0: float, dt: float,
    out: np.ndarray,
) -> None:
    """``d`` held over each of ``len(out)`` consecutive steps of ``dt`` from ``t0``, sampled at the step's midpoint
    (:meth:`~plant_emulator.physics.disturbance.Disturbance.over_step`); the time accumulates step by step as the
    plant's clock does."""
    t = t0
    for k in range(out.shape[0]):
        out[k] = disturbance_value(code, amplitude, frequency, phase, start_time, t + 0.5 * dt)
        t = t + dt


@njit(cache=True)
def variation_values(
    code: int,
    amplitude: float,
    frequency: float,
    phase: float,
    t0: float,
    dt: float,
    normals: np.ndarray,
    walk: float,
    out: np.ndarray,
) -> float:
    """``Delta`` held over each of ``len(out)`` consecutive steps of ``dt`` from ``t0``; returns the random walk's
    value after them.

    A sine, ``amplitude sin(frequency t + phase)``, is sampled at each step's midpoint; a random walk is an
    Ornstein-Uhlenbeck process (rate ``frequency``,
    stationary standard deviation ``amplitude / 2``) clipped to ``[-amplitude, amplitude]``, advanced once per step
    by ``normals[k]`` (a standard normal draw per step; unused for the other kinds).
    """
    decay = math.exp(-frequency * dt)
    sigma = 0.5 * amplitude * math.sqrt(max(0.0, 1.0 - decay * decay))
    t = t0
    for k in range(out.shape[0]):
        if code == VariationCode.SINE:
            out[k] = amplitude * math.sin(frequency * (t + 0.5 * dt) + phase)
        elif code == VariationCode.RANDOM_WALK:
            walk = min(max(decay * walk + sigma * normals[k], -amplitude), amplitude)
            out[k] = walk
        else:
            out[k] = 0.0
        t = t + dt
    return walk


@njit(cache=True)
def scalar_plant_step(
    x: float,
    a: float,
    b: np.ndarray,
    b_pattern: np.ndarray,
    u: np.ndarray,
    variation: tuple[float, float],
    d: float,
    h: float,
) -> float:
    """One step of the scalar first-order plant ``x' = (a + Da) x + (b + Db on) u + d`` with ``u``, ``variation =
    (Da, Db)`` and ``d`` held over ``h`` (``on`` = ``b_pattern``: which inputs ``Db`` acts on)."""
    delta_a, delta_b = variation
    bu = 0.0
    for j in range(u.shape[0]):
        bu += (b[j] + delta_b * b_pattern[j]) * u[j]
    return scalar_zoh_step(x, a + delta_a, bu, d, h)


@njit(cache=True)
def scalar_zoh_step(x: float, a: float, bu: float, d: float, h: float) -> float:
    """``x(h)`` of ``x' = a x + bu + d`` from ``x`` with ``bu`` and ``d`` held: the exact zero-order-hold step.

    ``integral_0^h e^(a s) ds = h expm1(a h) / (a h)`` (``h`` when ``a h = 0``), computed with ``expm1`` so a
    small ``a h`` loses no digits.
    """
    z = a * h
    integral = h * (math.expm1(z) / z if z != 0.0 else 1.0)
    return math.exp(z) * x + integral * (bu + d)


class _Motor(NamedTuple):
    """The :class:`PmsmParam` vector as one immutable record, a field per slot (:func:`_motor`).

    Why a record and not the array: :func:`pmsm_advance` unpacks the vector once per call, and the per-step helpers
    take this record, which numba passes by value. Handed the array instead, every helper call counted a reference
    to it (an atomic increment and decrement per call, several per internal step) and numba did not inline the
    larger helpers, so the loop's state went through memory between them.
    """

    pole_pairs: float
    speed_cap: float
    velocity_kp: float
    velocity_ki: float
    setpoint_weight: float
    torque_limit: float
    torque_constant: float
    inductance_d_nominal: float
    inductance_q_nominal: float
    psi_nominal: float
    kp_d: float
    kp_q: float
    ki_current: float
    v_max: float
    psi: float
    resistance: float
    inductance_d: float
    inductance_q: float
    inertia: float
    viscous: float
    coulomb: float
    coulomb_scale: float
    cogging_amplitude: float
    cogging_periods: float
    drift_amplitude: float
    drift_frequency: float
    drift_phase_per_trial: float
    drift_phase: float
    count_angle: float
    velocity_loop_filter: float
    speed_limit: float
    disturbance_code: float
    disturbance_amplitude: float
    disturbance_frequency: float
    disturbance_start: float
    disturbance_phase: float
    holding_torque: float
    derived_step: float
    decay_d: float
    decay_q: float
    loop_smoothing: float
    count_rate: float
    drift_cosine: float
    drift_sine: float
    # Reciprocals: a division on the loop's critical path costs about four multiplications (13 cycles against 3)
    torque_constant_inverse: float
    coulomb_scale_inverse: float
    count_angle_inverse: float


@njit(cache=True, inline="always")
def _motor(p: np.ndarray) -> _Motor:
    """The parameter vector ``p`` as a :class:`_Motor`.

    Element by element: numba's ``to_fixed_tuple`` builds the tuple through memory, and the compiled loop then kept
    more of it on the stack.
    """
    return _Motor(
        pole_pairs=p[_P.POLE_PAIRS],
        speed_cap=p[_P.SPEED_CAP],
        velocity_kp=p[_P.VELOCITY_KP],
        velocity_ki=p[_P.VELOCITY_KI],
        setpoint_weight=p[_P.SETPOINT_WEIGHT],
        torque_limit=p[_P.TORQUE_LIMIT],
        torque_constant=p[_P.TORQUE_CONSTANT],
        inductance_d_nominal=p[_P.INDUCTANCE_D_NOMINAL],
        inductance_q_nominal=p[_P.INDUCTANCE_Q_NOMINAL],
        psi_nominal=p[_P.PSI_NOMINAL],
        kp_d=p[_P.KP_D],
        kp_q=p[_P.KP_Q],
        ki_current=p[_P.KI_CURRENT],
        v_max=p[_P.V_MAX],
        psi=p[_P.PSI],
        resistance=p[_P.RESISTANCE],
        inductance_d=p[_P.INDUCTANCE_D],
        inductance_q=p[_P.INDUCTANCE_Q],
        inertia=p[_P.INERTIA],
        viscous=p[_P.VISCOUS],
        coulomb=p[_P.COULOMB],
        coulomb_scale=p[_P.COULOMB_SCALE],
        cogging_amplitude=p[_P.COGGING_AMPLITUDE],
        cogging_periods=p[_P.COGGING_PERIODS],
        drift_amplitude=p[_P.DRIFT_AMPLITUDE],
        drift_frequency=p[_P.DRIFT_FREQUENCY],
        drift_phase_per_trial=p[_P.DRIFT_PHASE_PER_TRIAL],
        drift_phase=p[_P.DRIFT_PHASE],
        count_angle=p[_P.COUNT_ANGLE],
        velocity_loop_filter=p[_P.VELOCITY_LOOP_FILTER],
        speed_limit=p[_P.SPEED_LIMIT],
        disturbance_code=p[_P.DISTURBANCE_CODE],
        disturbance_amplitude=p[_P.DISTURBANCE_AMPLITUDE],
        disturbance_frequency=p[_P.DISTURBANCE_FREQUENCY],
        disturbance_start=p[_P.DISTURBANCE_START],
        disturbance_phase=p[_P.DISTURBANCE_PHASE],
        holding_torque=p[_P.HOLDING_TORQUE],
        derived_step=p[_P.DERIVED_STEP],
        decay_d=p[_P.DECAY_D],
        decay_q=p[_P.DECAY_Q],
        loop_smoothing=p[_P.LOOP_SMOOTHING],
        count_rate=p[_P.COUNT_RATE],
        drift_cosine=p[_P.DRIFT_COSINE],
        drift_sine=p[_P.DRIFT_SINE],
        torque_constant_inverse=p[_P.TORQUE_CONSTANT_INVERSE],
        coulomb_scale_inverse=p[_P.COULOMB_SCALE_INVERSE],
        count_angle_inverse=p[_P.COUNT_ANGLE_INVERSE],
    )


@njit(cache=True)
def _derive(p: np.ndarray, h: float) -> None:
    """Fill the derived slots of ``p`` (from ``DERIVED_STEP`` on) for the internal step ``h``.

    Why kept in the vector: they were computed on every call, i.e. every caller step (three exp, six divisions), and
    they change only with ``h``, which is fixed by the caller's period; the same expressions, so the same values.
    """
    p[_P.DECAY_D] = math.exp(-p[_P.RESISTANCE] * h / p[_P.INDUCTANCE_D])
    p[_P.DECAY_Q] = math.exp(-p[_P.RESISTANCE] * h / p[_P.INDUCTANCE_Q])
    loop_filter = p[_P.VELOCITY_LOOP_FILTER]
    p[_P.LOOP_SMOOTHING] = 1.0 - math.exp(-h / loop_filter) if loop_filter > 0 else 1.0
    p[_P.COUNT_RATE] = p[_P.COUNT_ANGLE] / h
    p[_P.DRIFT_COSINE] = math.cos(p[_P.DRIFT_FREQUENCY] * h)
    p[_P.DRIFT_SINE] = math.sin(p[_P.DRIFT_FREQUENCY] * h)
    p[_P.TORQUE_CONSTANT_INVERSE] = 1.0 / p[_P.TORQUE_CONSTANT]
    p[_P.COULOMB_SCALE_INVERSE] = 1.0 / p[_P.COULOMB_SCALE]
    p[_P.COUNT_ANGLE_INVERSE] = 1.0 / p[_P.COUNT_ANGLE]
    p[_P.DERIVED_STEP] = h


# The per-step helpers below are inlined into pmsm_advance's loop by numba (inline="always"), so the compiler sees
# one loop body and keeps the state in registers; their arithmetic is written out in the same order as before,
# so the results are the same bit for bit.


class _StepStart(NamedTuple):
    """What an internal step's mechanics need that does not wait for the step's torque (:func:`_step_start`)."""

    load: float  # the disturbance torque held over the step, N m
    inertia_inverse: float  # 1 / J at the step's midpoint (with the drift)
    losses: float  # friction and cogging at the step's start, N m
    cogging_predicted: float  # cogging at Heun's predicted angle theta + h w, N m (0.0 without cogging)


@njit(cache=True, inline="always")
def _friction(m: _Motor, omega: float) -> float:
    """Viscous and Coulomb friction torque (N m) opposing the motion at ``omega``."""
    losses = m.viscous * omega
    if m.coulomb > 0:
        losses += m.coulomb * math.tanh(omega * m.coulomb_scale_inverse)
    return losses


@njit(cache=True, inline="always")
def _cogging(m: _Motor, theta: float) -> float:
    """Cogging torque (N m) at the angle ``theta``."""
    return m.cogging_amplitude * math.sin(m.cogging_periods * theta)


@njit(cache=True, inline="always")
def _drift_phasor(m: _Motor, t: float, h: float, trial: int) -> tuple[float, float]:
    """``(sin, cos)`` of the inertia drift's phase at the midpoint of the internal step that starts at ``t``."""
    if m.drift_amplitude > 0:
        phase = m.drift_frequency * (t + 0.5 * h) + m.drift_phase + m.drift_phase_per_trial * (trial - 1)
        return math.sin(phase), math.cos(phase)
    return 0.0, 1.0


@njit(cache=True, inline="always")
def _drift_turn(m: _Motor, phasor: tuple[float, float]) -> tuple[float, float]:
    """The drift's phasor one internal step later: turned by ``drift_frequency h`` (the angle-sum identities).

    Why not ``sin`` of the phase each step: a libm call per internal step, against four multiplications; the phasor
    starts from the exact phase at every call of :func:`pmsm_advance` (every caller step), so its rounding does not
    build up over a trial (a few ulps after a caller step's internal steps).
    """
    if m.drift_amplitude > 0:
        sine, cosine = phasor
        return sine * m.drift_cosine + cosine * m.drift_sine, cosine * m.drift_cosine - sine * m.drift_sine
    return phasor


@njit(cache=True, inline="always")
def _step_start(m: _Motor, theta: float, omega: float, t: float, h: float, drift_sine: float) -> _StepStart:
    """The mechanics' terms that depend only on the step's start ``(theta, w, t)`` (``drift_sine``: the sine of
    the drift's phase at the step's midpoint, :func:`_drift_phasor`).

    Why apart: they are libm calls (the load's and the drift's sines, tanh, the two cogging sines), and each call
    spills the loop's registers. Made first, they do not wait for the current loop and the electrical step, and the
    processor runs them alongside that chain; the sums are the same, in the same order.
    """
    load = disturbance_value(
        int(m.disturbance_code),
        m.disturbance_amplitude,
        m.disturbance_frequency,
        m.disturbance_phase,
        m.disturbance_start,
        t + 0.5 * h,
    )
    inertia = m.inertia
    if m.drift_amplitude > 0:
        inertia *= 1.0 + m.drift_amplitude * drift_sine
    losses = _friction(m, omega)
    cogging_predicted = 0.0
    if m.cogging_amplitude > 0:
        losses += _cogging(m, theta)
        cogging_predicted = _cogging(m, theta + h * omega)
    return _StepStart(load, 1.0 / inertia, losses, cogging_predicted)


@njit(cache=True, inline="always")
def _torque_command(
    m: _Motor, reference: float, command: float, omega_est: float, integral: float, h: float, velocity_mode: bool
) -> tuple[float, float, bool]:
    """The drive's torque command after the limit, the velocity integrator, and whether the limit clipped it.

    Velocity mode (CSV): ``T* = kp (beta w* - w_est) + ki integral(w* - w_est)`` with conditional-integration
    anti-windup, ``reference`` = ``w*`` (the command in rad/s, capped at the rated speed); torque mode (CST):
    ``T* = command``.
    """
    limit = m.torque_limit
    if velocity_mode:
        kp = m.velocity_kp
        error = reference - omega_est
        wanted = kp * (m.setpoint_weight * reference - omega_est) + integral
        torque = min(max(wanted, -limit), limit)
        # Conditional integration: stop integrating into the limit (anti-windup).
        if torque == wanted or (error > 0) != (wanted > 0):
            bound = limit + kp * abs(omega_est)
            integral = min(max(integral + m.velocity_ki * error * h, -bound), bound)
    else:
        wanted = command
        torque = min(max(wanted, -limit), limit)
    return torque, integral, torque != wanted


@njit(cache=True, inline="always")
def _current_loop(
    m: _Motor,
    torque_command: float,
    omega_est: float,
    currents: tuple[float, float],
    integrals: tuple[float, float],
    h: float,
) -> tuple[float, float, float, float]:
    """The current PI with decoupling on nominal parameters and the voltage-vector limit (integrators frozen while
    limited): ``(vd, vq, int_d, int_q)``."""
    i_d, i_q = currents
    int_d, int_q = integrals
    we_est = m.pole_pairs * omega_est
    error_d = -i_d
    error_q = torque_command * m.torque_constant_inverse - i_q
    vd = m.kp_d * error_d + int_d - we_est * m.inductance_q_nominal * i_q
    vq = m.kp_q * error_q + int_q + we_est * (m.inductance_d_nominal * i_d + m.psi_nominal)
    # hypot is a libm call (and every call spills the loop's registers); the squared magnitude settles the usual
    # case, far inside the limit, and hypot still decides within 1e-9 of it, so the outcome is hypot's own.
    if not vd * vd + vq * vq < m.v_max * m.v_max * (1.0 - 1e-9):
        magnitude = math.hypot(vd, vq)
        if magnitude > m.v_max:
            scale = m.v_max / magnitude
            return vd * scale, vq * scale, int_d, int_q
    return vd, vq, int_d + m.ki_current * error_d * h, int_q + m.ki_current * error_q * h


@njit(cache=True, inline="always")
def _electrical(
    m: _Motor,
    omega: float,
    currents: tuple[float, float],
    voltages: tuple[float, float],
    decays: tuple[float, float],
) -> tuple[float, float, float]:
    """Each dq axis exact over the step with the voltages and cross-coupling held (``decays`` are
    ``exp(-R h / L)`` per axis): ``(id, iq, mean torque over the step)``."""
    r, ld, lq, psi = m.resistance, m.inductance_d, m.inductance_q, m.psi
    i_d, i_q = currents
    vd, vq = voltages
    decay_d, decay_q = decays
    we = m.pole_pairs * omega
    id_new = decay_d * i_d + (1.0 - decay_d) / r * (vd + we * lq * i_q)
    iq_new = decay_q * i_q + (1.0 - decay_q) / r * (vq - we * (ld * i_d + psi))
    id_mean = 0.5 * (i_d + id_new)
    iq_mean = 0.5 * (i_q + iq_new)
    return id_new, iq_new, 1.5 * m.pole_pairs * (psi * iq_mean + (ld - lq) * id_mean * iq_mean)


@njit(cache=True, inline="always")
def _mechanics(
    m: _Motor, theta: float, omega: float, torque: float, h: float, start: _StepStart
) -> tuple[float, float]:
    """Heun's method on ``J(t) w' = Te + d - losses``, ``theta' = w``, with ``Te`` and the load held over ``h``:
    ``(theta, w)`` at ``t + h`` (``start``: the step's terms that :func:`_step_start` made)."""
    drive = torque + start.load
    if m.holding_torque > 0:
        return _braked_mechanics(m, theta, omega, drive, h, start)
    accel0 = (drive - start.losses) * start.inertia_inverse
    omega_pred = omega + h * accel0
    losses_predicted = _friction(m, omega_pred)  # at Heun's predicted state (theta + h w, omega_pred)
    if m.cogging_amplitude > 0:
        losses_predicted += start.cogging_predicted
    accel1 = (drive - losses_predicted) * start.inertia_inverse
    omega_new = omega + 0.5 * h * (accel0 + accel1)
    return theta + 0.5 * h * (omega + omega_new), omega_new


@njit(cache=True, inline="always")
def _braked_mechanics(
    m: _Motor, theta: float, omega: float, drive: float, h: float, start: _StepStart
) -> tuple[float, float]:
    """The mechanics with the holding brake closed: a dry friction of up to ``holding_torque``.

    At rest the brake holds the axis while the net torque (``Te + d - losses``) is within its torque, as a real
    holding brake holds a vertical load; a moving axis is braked by the full torque against the motion (Heun's
    method with the brake's direction fixed over the step) and stops, rather than reverses, where the speed would
    cross zero.
    """
    holding = m.holding_torque
    net0 = drive - start.losses
    if omega == 0.0:
        if abs(net0) <= holding:
            return theta, 0.0
        direction = 1.0 if net0 > 0 else -1.0  # breaks away in the direction of the net torque
    else:
        direction = 1.0 if omega > 0 else -1.0
    accel0 = (net0 - direction * holding) * start.inertia_inverse
    omega_pred = omega + h * accel0
    losses_predicted = _friction(m, omega_pred)  # at Heun's predicted state (theta + h w, omega_pred)
    if m.cogging_amplitude > 0:
        losses_predicted += start.cogging_predicted
    accel1 = (drive - losses_predicted - direction * holding) * start.inertia_inverse
    omega_new = omega + 0.5 * h * (accel0 + accel1)
    if omega_new * direction < 0:
        omega_new = 0.0  # the brake stopped the axis within the step
    return theta + 0.5 * h * (omega + omega_new), omega_new


@njit(cache=True, inline="always")
def _sense(m: _Motor, theta: float, count: float, omega_est: float) -> tuple[float, float]:
    """The quantised angle, differentiated over the step (``count_rate = count_angle / h``) and low-passed
    (``loop_smoothing = 1 - exp(-h / filter)``): the drive's own velocity estimate. Returns ``(count, w_est)``."""
    # np.floor stays a float (math.floor gives an int: two conversions more on the loop's critical path)
    new_count = np.floor(theta * m.count_angle_inverse)
    raw = (new_count - count) * m.count_rate
    if m.velocity_loop_filter > 0:
        return new_count, omega_est + m.loop_smoothing * (raw - omega_est)
    return new_count, raw


@njit(cache=True)
def pmsm_advance(
    s: np.ndarray, p: np.ndarray, command: float, h: float, steps: int, velocity_mode: bool, trial: int
) -> None:
    """Advance the PMSM state ``s`` by ``steps`` internal steps of ``h`` seconds with ``command`` held.

    Each internal step: the torque command (velocity loop or direct), the current loop, the electrical plant
    (exact per axis), the mechanics (Heun), then sensing. ``TORQUE_LIMITED`` and ``OVER_SPEED`` say whether a
    limit was hit during these steps. The parameters are read once into a :class:`_Motor` and the state lives in
    locals during the loop (so the compiler keeps both in registers); the state is written back once. The first
    call with a new ``h`` writes the derived slots of ``p`` (:func:`_derive`).
    """
    if p[_P.DERIVED_STEP] != h:
        _derive(p, h)
    m = _motor(p)
    theta, omega, t = s[_S.THETA], s[_S.OMEGA], s[_S.TIME]
    currents = (s[_S.ID], s[_S.IQ])
    integrals = (s[_S.INT_D], s[_S.INT_Q])
    int_velocity, omega_est, count = s[_S.INT_VELOCITY], s[_S.OMEGA_ESTIMATE], s[_S.COUNT]
    torque_command = s[_S.TORQUE_COMMAND]
    limited = False
    over_speed = False
    decays = (m.decay_d, m.decay_q)
    reference = min(max(command * _RAD_PER_S_PER_RPM, -m.speed_cap), m.speed_cap)  # constant over the call
    drift = _drift_phasor(m, t, h, trial)
    for _ in range(steps):
        start = _step_start(m, theta, omega, t, h, drift[0])
        drift = _drift_turn(m, drift)
        torque_command, int_velocity, clipped = _torque_command(
            m, reference, command, omega_est, int_velocity, h, velocity_mode
        )
        limited = limited or clipped
        vd, vq, int_d, int_q = _current_loop(m, torque_command, omega_est, currents, integrals, h)
        integrals = (int_d, int_q)
        i_d, i_q, torque = _electrical(m, omega, currents, (vd, vq), decays)
        currents = (i_d, i_q)
        theta, omega = _mechanics(m, theta, omega, torque, h, start)
        t += h
        count, omega_est = _sense(m, theta, count, omega_est)
        over_speed = over_speed or abs(omega) > m.speed_limit
    _store(s, p, (theta, omega, t), currents, integrals, (int_velocity, omega_est, count, torque_command))
    s[_S.TORQUE_LIMITED] = 1.0 if limited else 0.0
    s[_S.OVER_SPEED] = 1.0 if over_speed else 0.0


@njit(cache=True)
def _store(
    s: np.ndarray,
    p: np.ndarray,
    mechanical: tuple[float, float, float],
    currents: tuple[float, float],
    integrals: tuple[float, float],
    drive: tuple[float, float, float, float],
) -> None:
    """Write the loop's locals back into the state vector, with the torque at the end of the last step."""
    s[_S.THETA], s[_S.OMEGA], s[_S.TIME] = mechanical
    s[_S.ID], s[_S.IQ] = currents
    s[_S.INT_D], s[_S.INT_Q] = integrals
    s[_S.INT_VELOCITY], s[_S.OMEGA_ESTIMATE], s[_S.COUNT], s[_S.TORQUE_COMMAND] = drive
    i_d, i_q = currents
    psi, ld, lq = p[_P.PSI], p[_P.INDUCTANCE_D], p[_P.INDUCTANCE_Q]
    s[_S.TORQUE] = 1.5 * p[_P.POLE_PAIRS] * (psi * i_q + (ld - lq) * i_d * i_q)


@njit(cache=True)
def pmsm_step(
    s: np.ndarray,
    p: np.ndarray,
    command: float,
    dt: float,
    steps: int,
    velocity_mode: bool,
    trial: int,
    smoothing: float,
    reported: float,
) -> float:
    """One caller step of ``dt`` seconds of the PMSM (``steps`` internal steps, :func:`pmsm_advance`) and its
    reported velocity in rpm: the resolver counts over ``dt``, low-passed from the previous ``reported`` with
    ``smoothing = 1 - exp(-dt / tau)`` (``tau`` = ``pmsm.velocity_filter``), or unfiltered when ``smoothing`` is
    NaN (no filter)."""
    count_start = s[_S.COUNT]
    pmsm_advance(s, p, command, dt / steps, steps, velocity_mode, trial)
    measured = (s[_S.COUNT] - count_start) * p[_P.COUNT_ANGLE] / dt / _RAD_PER_S_PER_RPM
    if math.isnan(smoothing):
        return measured
    return reported + smoothing * (measured - reported)


def warm_up() -> None:
    """Run every kernel once (compiling it, or loading it from numba's cache) so that no control loop pays it."""
    disturbance_value(int(DisturbanceCode.SQUARE), 1.0, 1.0, 0.0, 0.0, 0.5)
    values = np.zeros(2)
    disturbance_values(int(DisturbanceCode.SQUARE), 1.0, 1.0, 0.0, 0.0, 0.0, 1e-3, values)
    variation_values(int(VariationCode.RANDOM_WALK), 1.0, 1.0, 0.0, 0.0, 1e-3, np.zeros(2), 0.0, values)
    scalar_zoh_step(0.0, -1.0, 1.0, 0.0, 1e-3)
    scalar_plant_step(0.0, -1.0, np.ones(1), np.ones(1), np.ones(1), (0.0, 0.0), 0.0, 1e-3)
    state = np.zeros(PMSM_STATE_SIZE)
    params = np.ones(PMSM_PARAM_SIZE)
    pmsm_advance(state, params, 0.0, 1e-5, 1, True, 1)
    pmsm_step(state, params, 0.0, 1e-5, 1, True, 1, math.nan, 0.0)


warm_up()  # at import: compiled (first run) or loaded from the cache, never inside a control loop

#: The argument types of :func:`pmsm_step` as the plant calls it (and as :func:`warm_up` compiled it): the state and
#: parameter vectors (C-contiguous ``float64``), ``command``, ``dt``, ``steps``, ``velocity_mode``, ``trial``,
#: ``smoothing``, ``reported``.
PMSM_STEP_SIGNATURE = (
    types.float64[::1],
    types.float64[::1],
    types.float64,
    types.float64,
    types.int64,
    types.boolean,
    types.int64,
    types.float64,
    types.float64,
)
#: :func:`pmsm_step`'s machine code for :data:`PMSM_STEP_SIGNATURE`, called without numba's dispatcher. The
#: dispatcher works out the types of all nine arguments on every call to pick an overload, which for the plant's
#: per-step call is always this one (a sizeable share of a cycle's Python time). Scalars are converted as by

#: ``float()`` / ``int()``; the two vectors must be C-contiguous ``float64`` (the plant's own).
# (numba's CompileResult declares its fields at run time, so mypy does not see entry_point)
pmsm_step_compiled: Callable[..., float] = pmsm_step.overloads[PMSM_STEP_SIGNATURE].entry_point  # type: ignore[attr-defined]
