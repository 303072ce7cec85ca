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


PMSM_STATE_SIZE = len(PmsmState)
PMSM_PARAM_SIZE = len(PmsmParam)

_S = PmsmState
_P = PmsmParam
_D = DisturbanceCode


@njit(cache=True)
def disturbance_value(code: int, amplitude: float, frequency: float, start_time: float, t: float) -> float:
    """``d(t)`` of :class:`~plant_emulator.config.DisturbanceConfig` (``code`` is its kind, ``NONE`` if not armed)."""
    if code == _D.NONE:
        return 0.0
    if code == _D.CONSTANT:
        return amplitude
    elapsed = t - start_time
    if elapsed < 0:
        return 0.0
    if code == _D.STEP:
        return amplitude
    phase = math.sin(frequency * elapsed)
    if code == _D.SINE:
        return amplitude * phase
    return amplitude if phase >= 0 else -amplitude  # square


@njit(cache=True)
def disturbance_values(
    code: int, amplitude: float, frequency: float, start_time: float, t0: float, dt: float, out: np.ndarray
) -> None:
    """``d`` held over each of ``len(out)`` consecutive steps of ``dt`` from ``t0``, sampled at the step's midpoint
    (:meth:`~plant_emulator.physics.disturbance.Disturbance.over_step`); the time accumulates step by step as the
    plant's clock does."""
    t = t0
    for k in range(out.shape[0]):
        out[k] = disturbance_value(code, amplitude, frequency, start_time, t + 0.5 * dt)
        t = t + dt


@njit(cache=True)
def variation_values(
    code: int,
    amplitude: float,
    frequency: float,
    t0: float,
    dt: float,
    normals: np.ndarray,
    walk: float,
    out: np.ndarray,
) -> float:
    """``Delta`` held over each of ``len(out)`` consecutive steps of ``dt`` from ``t0``; returns the random walk's
    value after them.

    A sine is sampled at each step's midpoint; a random walk is an Ornstein-Uhlenbeck process (rate ``frequency``,
    stationary standard deviation ``amplitude / 2``) clipped to ``[-amplitude, amplitude]``, advanced once per step
    by ``normals[k]`` (a standard normal draw per step; unused for the other kinds).
    """
    decay = math.exp(-frequency * dt)
    sigma = 0.5 * amplitude * math.sqrt(max(0.0, 1.0 - decay * decay))
    t = t0
    for k in range(out.shape[0]):
        if code == VariationCode.SINE:
            out[k] = amplitude * math.sin(frequency * (t + 0.5 * dt))
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


@njit(cache=True)
def _losses(p: np.ndarray, theta: float, omega: float) -> float:
    """Friction and cogging torque (N m) opposing the motion at (theta, omega)."""
    losses = p[_P.VISCOUS] * omega
    if p[_P.COULOMB] > 0:
        losses += p[_P.COULOMB] * math.tanh(omega / p[_P.COULOMB_SCALE])
    if p[_P.COGGING_AMPLITUDE] > 0:
        losses += p[_P.COGGING_AMPLITUDE] * math.sin(p[_P.COGGING_PERIODS] * theta)
    return losses


@njit(cache=True)
def _torque_command(
    p: np.ndarray, command: float, omega_est: float, integral: float, h: float, velocity_mode: bool
) -> tuple[float, float, bool]:
    """The drive's torque command after the limit, the velocity integrator, and whether the limit clipped it.

    Velocity mode (CSV): ``T* = kp (beta w* - w_est) + ki integral(w* - w_est)`` with conditional-integration
    anti-windup; torque mode (CST): ``T* = command``.
    """
    limit = p[_P.TORQUE_LIMIT]
    if velocity_mode:
        kp = p[_P.VELOCITY_KP]
        reference = min(max(command * _RAD_PER_S_PER_RPM, -p[_P.SPEED_CAP]), p[_P.SPEED_CAP])
        error = reference - omega_est
        wanted = kp * (p[_P.SETPOINT_WEIGHT] * reference - omega_est) + integral
        torque = min(max(wanted, -limit), limit)
        # Conditional integration: stop integrating into the limit (anti-windup).
        if torque == wanted or (error > 0) != (wanted > 0):
            bound = limit + kp * abs(omega_est)
            integral = min(max(integral + p[_P.VELOCITY_KI] * error * h, -bound), bound)
    else:
        wanted = command
        torque = min(max(wanted, -limit), limit)
    return torque, integral, torque != wanted


@njit(cache=True)
def _current_loop(
    p: np.ndarray,
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
    we_est = p[_P.POLE_PAIRS] * omega_est
    error_d = -i_d
    error_q = torque_command / p[_P.TORQUE_CONSTANT] - i_q
    vd = p[_P.KP_D] * error_d + int_d - we_est * p[_P.INDUCTANCE_Q_NOMINAL] * i_q
    vq = p[_P.KP_Q] * error_q + int_q + we_est * (p[_P.INDUCTANCE_D_NOMINAL] * i_d + p[_P.PSI_NOMINAL])
    magnitude = math.hypot(vd, vq)
    if magnitude > p[_P.V_MAX]:
        scale = p[_P.V_MAX] / magnitude
        return vd * scale, vq * scale, int_d, int_q
    return vd, vq, int_d + p[_P.KI_CURRENT] * error_d * h, int_q + p[_P.KI_CURRENT] * error_q * h


@njit(cache=True)
def _electrical(
    p: np.ndarray,
    omega: float,
    currents: tuple[float, float],
    voltages: tuple[float, float],
    decays: tuple[float, float],
) -> tuple[float, float, float]:
    """Each dq axis exact over the step with the voltages and cross-coupling held (``decays`` are
    ``exp(-R h / L)`` per axis): ``(id, iq, mean torque over the step)``."""
    r, ld, lq, psi = p[_P.RESISTANCE], p[_P.INDUCTANCE_D], p[_P.INDUCTANCE_Q], p[_P.PSI]
    i_d, i_q = currents
    vd, vq = voltages
    decay_d, decay_q = decays
    we = p[_P.POLE_PAIRS] * omega
    id_new = decay_d * i_d + (1.0 - decay_d) / r * (vd + we * lq * i_q)
    iq_new = decay_q * i_q + (1.0 - decay_q) / r * (vq - we * (ld * i_d + psi))
    id_mean = 0.5 * (i_d + id_new)
    iq_mean = 0.5 * (i_q + iq_new)
    return id_new, iq_new, 1.5 * p[_P.POLE_PAIRS] * (psi * iq_mean + (ld - lq) * id_mean * iq_mean)


@njit(cache=True)
def _mechanics(
    p: np.ndarray, theta: float, omega: float, torque: float, t: float, h: float, trial: int
) -> tuple[float, float]:
    """Heun's method on ``J(t) w' = Te + d - losses``, ``theta' = w``, with ``Te`` and the load held over ``h``:
    ``(theta, w)`` at ``t + h``."""
    load = disturbance_value(
        int(p[_P.DISTURBANCE_CODE]),
        p[_P.DISTURBANCE_AMPLITUDE],
        p[_P.DISTURBANCE_FREQUENCY],
        p[_P.DISTURBANCE_START],
        t + 0.5 * h,
    )
    drive = torque + load
    inertia = p[_P.INERTIA]
    if p[_P.DRIFT_AMPLITUDE] > 0:
        phase = p[_P.DRIFT_FREQUENCY] * (t + 0.5 * h) + p[_P.DRIFT_PHASE_PER_TRIAL] * (trial - 1)
        inertia *= 1.0 + p[_P.DRIFT_AMPLITUDE] * math.sin(phase)
    if p[_P.HOLDING_TORQUE] > 0:
        return _braked_mechanics(p, theta, omega, drive, inertia, h)
    accel0 = (drive - _losses(p, theta, omega)) / inertia
    omega_pred = omega + h * accel0
    theta_pred = theta + h * omega
    accel1 = (drive - _losses(p, theta_pred, omega_pred)) / inertia
    omega_new = omega + 0.5 * h * (accel0 + accel1)
    return theta + 0.5 * h * (omega + omega_new), omega_new


@njit(cache=True)
def _braked_mechanics(
    p: np.ndarray, theta: float, omega: float, drive: float, inertia: float, h: float
) -> tuple[float, float]:
    """The mechanics with the holding brake closed: a dry friction of up to ``HOLDING_TORQUE``.

    At rest the brake holds the axis while the net torque (``Te + d - losses``) is within its torque, as a real
    holding brake holds a vertical load; a moving axis is braked by the full torque against the motion (Heun's
    method with the brake's direction fixed over the step) and stops, rather than reverses, where the speed would
    cross zero.
    """
    holding = p[_P.HOLDING_TORQUE]
    net0 = drive - _losses(p, theta, omega)
    if omega == 0.0:
        if abs(net0) <= holding:
            return theta, 0.0
        direction = 1.0 if net0 > 0 else -1.0  # breaks away in the direction of the net torque
    else:
        direction = 1.0 if omega > 0 else -1.0
    accel0 = (net0 - direction * holding) / inertia
    omega_pred = omega + h * accel0
    accel1 = (drive - _losses(p, theta + h * omega, omega_pred) - direction * holding) / inertia
    omega_new = omega + 0.5 * h * (accel0 + accel1)
    if omega_new * direction < 0:
        omega_new = 0.0  # the brake stopped the axis within the step
    return theta + 0.5 * h * (omega + omega_new), omega_new


@njit(cache=True)
def _sense(
    p: np.ndarray, theta: float, count: float, omega_est: float, h: float, smoothing: float
) -> tuple[float, float]:
    """The quantised angle, differentiated over ``h`` and low-passed (``smoothing = 1 - exp(-h / filter)``): the
    drive's own velocity estimate. Returns ``(count, w_est)``."""
    new_count = math.floor(theta / p[_P.COUNT_ANGLE])
    raw = (new_count - count) * p[_P.COUNT_ANGLE] / h
    if p[_P.VELOCITY_LOOP_FILTER] > 0:
        return new_count, omega_est + smoothing * (raw - omega_est)
    return new_count, raw


@njit(cache=True)
def pmsm_advance(
    s: np.ndarray, p: np.ndarray, command: float, h: float, steps: int, velocity_mode: bool, trial: int
) -> None:
    """Advance the PMSM state ``s`` by ``steps`` internal steps of ``h`` seconds with ``command`` held.

    Each internal step: the torque command (velocity loop or direct), the current loop, the electrical plant
    (exact per axis), the mechanics (Heun), then sensing. ``TORQUE_LIMITED`` and ``OVER_SPEED`` say whether a
    limit was hit during these steps. The state lives in locals during the loop (so the compiler keeps it in
    registers) and is written back once.
    """
    theta, omega, t = s[_S.THETA], s[_S.OMEGA], s[_S.TIME]
    currents = (s[_S.ID], s[_S.IQ])
    integrals = (s[_S.INT_D], s[_S.INT_Q])
    int_velocity, omega_est, count = s[_S.INT_VELOCITY], s[_S.OMEGA_ESTIMATE], s[_S.COUNT]
    torque_command = s[_S.TORQUE_COMMAND]
    limited = False
    over_speed = False
    # Constant over the call (h is): computed once, not per internal step.
    decays = (
        math.exp(-p[_P.RESISTANCE] * h / p[_P.INDUCTANCE_D]),
        math.exp(-p[_P.RESISTANCE] * h / p[_P.INDUCTANCE_Q]),
    )
    smoothing = 1.0 - math.exp(-h / p[_P.VELOCITY_LOOP_FILTER]) if p[_P.VELOCITY_LOOP_FILTER] > 0 else 1.0
    for _ in range(steps):
        torque_command, int_velocity, clipped = _torque_command(p, command, omega_est, int_velocity, h, velocity_mode)
        limited = limited or clipped
        vd, vq, int_d, int_q = _current_loop(p, torque_command, omega_est, currents, integrals, h)
        integrals = (int_d, int_q)
        i_d, i_q, torque = _electrical(p, omega, currents, (vd, vq), decays)
        currents = (i_d, i_q)
        theta, omega = _mechanics(p, theta, omega, torque, t, h, trial)
        t += h
        count, omega_est = _sense(p, theta, count, omega_est, h, smoothing)
        over_speed = over_speed or abs(omega) > p[_P.SPEED_LIMIT]
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
    disturbance_value(int(DisturbanceCode.SQUARE), 1.0, 1.0, 0.0, 0.5)
    values = np.zeros(2)
    disturbance_values(int(DisturbanceCode.SQUARE), 1.0, 1.0, 0.0, 0.0, 1e-3, values)
    variation_values(int(VariationCode.RANDOM_WALK), 1.0, 1.0, 0.0, 1e-3, np.zeros(2), 0.0, values)
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
#: per-step call is always this one (about a tenth of a 1 ms step's Python time). Scalars are converted as by
#: ``float()`` / ``int()``; the two vectors must be C-contiguous ``float64`` (the plant's own).
# (numba's CompileResult declares its fields at run time, so mypy does not see entry_point)
pmsm_step_compiled: Callable[..., float] = pmsm_step.overloads[PMSM_STEP_SIGNATURE].entry_point  # type: ignore[attr-defined]
