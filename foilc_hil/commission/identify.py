"""``commission identify``: a safe step-test campaign on the drive, a continuous model fitted to it, and the
norm-bounded uncertainty of its discrete model -- written as a ``plant:`` section ``tune``/``synthesize``/``run``
read directly.

Campaign
--------
The drive is started as the bench starts it (:class:`~drivers.cia402_master.Cia402Drive`: NMT reset communication,
PDO/mode/cycle configuration over SDO, 402 enable) in the chosen mode, then driven over the cyclic path only
(RPDO target, SYNC, TPDO feedback), one command per cycle:

- CSV (default), *pulse* pattern: rest, then for each repetition and amplitude ``A``: ``+A`` (hold), ``0`` (rest),
  ``-A`` (hold), ``0`` (rest). Every edge is a step: up and down, both signs, several sizes.
- CST, *doublet* pattern: ``+A``, ``-A``, ``0`` then ``-A``, ``+A``, ``0``: a torque step integrates into velocity,
  so each pulse is cancelled by its opposite before the rest and the axis comes back near standstill.

Every amplitude must lie inside the drive's limit for the mode (``drive.velocity_limit`` / ``drive.torque_limit``,
plant units). The campaign aborts with a safe stop (quick stop, disable) on any fault the master reports (EMCY,
statusword fault bit, heartbeat loss, missing feedback, the drive leaving OPERATION ENABLED) and when the measured
velocity leaves ``+-output_limit``.

Timing: ``u[k]`` is the target sent before SYNC ``k``; the drive latches it at SYNC ``k`` and reports its first
effect in the TPDO of SYNC ``k + 1``, ``y[k + 1]``. That is the plain zero-order-hold sampling of the plant with
the command's time stamp at the SYNC that latches it. The one cycle a closed loop loses by computing ``u`` from
``y[k]`` and sending it before SYNC ``k + 1`` is the bench's ``input_delay = 1``, added by ``synthesize``/``run``;
the fitted ``delay`` is the plant's own transport delay beyond that (0 for the ``first-order`` model).

Fit
---
Each step ``j`` (a change of the command at cycle ``k_j``) is a window ``k_j .. k_{j+1} - 1``. The model's output
is simulated over the whole record from rest (the record starts with a rest period; its mean level absorbs a
sensor offset), so a step that starts before the previous one has settled is still modelled exactly. The sampled
response is computed without approximation: the model's state space is discretised by matrix exponentials, a
transport delay ``tau = m Ts + delta`` splits each hold interval into the two inputs that act in it (modified
z-transform), and the result is run with ``scipy.signal.lfilter``. The nominal fit uses the residuals of every
window; the fit of step ``j`` alone uses only window ``j`` (the history before it simulated with the same
parameters).

- ``first-order``: ``G(s) = b / (s - a)``; parameters ``a, b``.
- ``first-order-delay``: the same times ``exp(-tau s)``; parameters ``a, b, tau`` (``0 <= tau <= 20 Ts``).
- ``second-order``: ``G(s) = n0 / (s^2 + d1 s + d0)``; parameters ``d1 > 0, d0 > 0, n0``.

``scipy.optimize.least_squares`` fits all steps jointly (the nominal model) and each step alone (the spread).
Reported: R^2 and NRMSE (residual RMS over the step's output range) per step, the residual standard deviation
overall, and the parameters' standard errors and 95 % intervals (*Intervals*).

Intervals
---------
The residuals of a step fit are not white: unmodelled dynamics (a second pole, the measurement's half-cycle
averaging, cogging), a time-varying plant (``plant.variation``) and coloured or quantised sensor noise all leave
slow, correlated residuals, and for a time-varying plant they are deterministic. The white-noise covariance
``s^2 (J'J)^-1`` then understates the error several times (on ``configs/paper_sim.yaml``, whose ``a(t)``, ``b(t)``
vary by 8-9 %, it gave ``a = -1.2518 +- 0.0039`` for a true ``-1.23``: 5.6 standard errors off). The estimate is
kept (least squares, unweighted: re-weighting for coloured noise, GLS, moves it when the error is a model
mismatch rather than noise), and its covariance is the sandwich ``B S B``, ``B = (J'J)^-1``, with ``S`` the
long-run covariance of the scores ``J_k r_k`` estimated by prewhitened HAC (Andrews and Monahan 1992): a VAR(1)
whitens the scores, Newey-West (Bartlett kernel, Andrews' plug-in lag window) estimates the whitened ones' long-run
covariance, and ``(I - Phi)^-1`` recolours it. The interval is ``theta +- 1.96 se`` (``fit.intervals``, with the
white-noise errors for comparison). On paper_sim this gives ``a = -1.2518 +- 0.034`` (the truth 0.64 se away); in
20 seeded campaigns with AR(1) noise (coefficient 0.9) the 95 % intervals hold the true ``a`` and ``b`` together in
20 (the white-noise ones in 8), and the standard errors match the estimates' spread within a factor 2
(``tests/integration/test_commission_identify.py``).

Uncertainty (discrete model, ZOH at ``sample_time``)
----------------------------------------------------
With ``(A0, B0)`` the nominal discrete model and ``(A_i, B_i)`` that of step ``i`` alone (same realisation, delay
excluded), ``rho_A = margin * max(max_i ||A_i - A0||_2, 2 sigma_A)`` and likewise ``rho_B``, where ``sigma`` is the
standard error of the nominal ``A0``/``B0`` propagated from the parameters' covariance (so one step still gives a
non-zero bound). Then

    G1 = sqrt(rho_A) I_n,  H1 = sqrt(rho_A) I_n,  G2 = sqrt(rho_B) I_n,  H2 = sqrt(rho_B) e_1

cover every observed deviation: ``A_i - A0 = G1 Delta H1`` with ``Delta = (A_i - A0) / rho_A``, and
``B_i - B0 = G2 Delta H2`` with ``Delta = [(B_i - B0) / rho_B, 0]``, both of norm <= 1. For a first-order model
these are the scalars ``sqrt(rho_A)``, ``sqrt(rho_B)``. The synthesis treats the two channels as independent blocks,
so the whole box ``|dA| <= rho_A``, ``|dB| <= rho_B`` is covered, not only the observed pairs.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from foilc_hil.errors import DriveError, FoilcHilError, InputError
from foilc_hil.progress import as_step

__all__ = [
    "CampaignSpec",
    "CampaignSummary",
    "ErrorModel",
    "FitResult",
    "ModelKind",
    "StepRecord",
    "StepWindow",
    "UncertaintyBounds",
    "build_campaign",
    "discrete_model",
    "error_model",
    "find_steps",
    "fit_model",
    "fragment_document",
    "plot_fit",
    "run_campaign",
    "simulate_increment",
    "uncertainty_bounds",
]

ModelKind = Literal["first-order", "first-order-delay", "second-order"]
Pattern = Literal["pulse", "doublet"]
MODEL_KINDS: tuple[ModelKind, ...] = ("first-order", "first-order-delay", "second-order")
MAX_DELAY_CYCLES = 20
PRE_STEP_SAMPLES = 10  # samples before a step averaged into its pre-step level
MIN_STEP_SAMPLES = 5  # windows shorter than this are not fitted
STATISTICAL_FLOOR_SIGMAS = 2.0
#: Cap on the prewhitening VAR(1)'s spectral radius: near a unit root the recolouring (I - Phi)^-1 explodes.
MAX_SCORE_AR1 = 0.97
Z_95 = 1.959963984540054  # two-sided 95 % quantile of the normal distribution
COVARIANCE_METHOD = "least squares; prewhitened (VAR(1)) Newey-West HAC sandwich covariance of the scores"


# --- campaign ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CampaignSpec:
    """The step-test campaign.

    Attributes
    ----------
    amplitudes
        Step sizes in plant input units (rpm in CSV, plant torque units in CST), each ``0 < A <= limit``.
    hold, rest
        Seconds each non-zero command is held, and each zero command (rest) lasts.
    repetitions
        How often the whole amplitude sequence is repeated.
    limit
        The drive's limit of the command for the mode (plant units).
    pattern
        ``pulse`` (``+A, 0, -A, 0``) or ``doublet`` (``+A, -A, 0, -A, +A, 0``).
    """

    amplitudes: tuple[float, ...]
    hold: float
    rest: float
    repetitions: int
    limit: float
    pattern: Pattern = "pulse"

    def __post_init__(self) -> None:
        if not self.amplitudes:
            raise InputError("--amplitudes: give at least one step size")
        for amplitude in self.amplitudes:
            if not (math.isfinite(amplitude) and amplitude > 0):
                raise InputError(f"--amplitudes: {amplitude} is not a positive step size")
            if amplitude > self.limit:
                raise InputError(
                    f"--amplitudes: {amplitude} exceeds the drive's limit {self.limit} for the mode "
                    "(drive.velocity_limit / drive.torque_limit)"
                )
        for name, value in (("--hold", self.hold), ("--rest", self.rest)):
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{name}: must be a positive number of seconds, got {value}")
        if self.repetitions < 1:
            raise InputError(f"--repetitions: must be >= 1, got {self.repetitions}")


def build_campaign(spec: CampaignSpec, sample_time: float) -> np.ndarray:
    """The command for every cycle (plant units), starting and ending at rest."""
    hold = max(MIN_STEP_SAMPLES, round(spec.hold / sample_time))
    rest = max(MIN_STEP_SAMPLES, round(spec.rest / sample_time))
    levels: list[tuple[float, int]] = [(0.0, rest)]
    for _ in range(spec.repetitions):
        for amplitude in spec.amplitudes:
            if spec.pattern == "pulse":
                levels += [(amplitude, hold), (0.0, rest), (-amplitude, hold), (0.0, rest)]
            else:
                levels += [(amplitude, hold), (-amplitude, hold), (0.0, rest),
                           (-amplitude, hold), (amplitude, hold), (0.0, rest)]
    return np.concatenate([np.full(count, level) for level, count in levels])


@dataclass(frozen=True)
class StepRecord:
    """What the campaign measured: ``command[k]`` sent before SYNC ``k``, ``output[k]`` answering SYNC ``k``."""

    command: np.ndarray
    output: np.ndarray
    sample_time: float

    def __post_init__(self) -> None:
        if self.command.shape != self.output.shape or self.command.ndim != 1:
            raise InputError("command and output must be 1-D arrays of the same length")


def run_campaign(
    drive: Any,
    command: np.ndarray,
    *,
    sample_time: float,
    output_limit: float,
    feedback_timeout: float,
    progress: Callable[[int, int], None] | None = None,
) -> StepRecord:
    """Run ``command`` on an enabled drive (a :class:`drivers.drive.Drive`), one cycle each; safe stop on abort.

    Raises
    ------
    DriveError (or a subclass)
        On any fault, a lost feedback, the drive leaving OPERATION ENABLED, or ``|y| > output_limit``; the
        drive has been quick-stopped and disabled when it propagates.
    """
    from drivers.cia402 import State402

    applied = np.zeros_like(command, dtype=float)
    output = np.zeros_like(command, dtype=float)
    total = int(command.shape[0])
    try:
        for k in range(total):
            applied[k] = drive.set_target(float(command[k]))
            drive.sync()
            feedback = drive.wait_feedback(feedback_timeout)
            if feedback.state is not State402.OPERATION_ENABLED:
                raise DriveError(f"the drive left OPERATION_ENABLED (now {feedback.state.name}) at cycle {k}")
            output[k] = feedback.velocity
            if not math.isfinite(output[k]) or abs(output[k]) > output_limit:
                raise DriveError(
                    f"measured velocity {output[k]:g} left +-{output_limit:g} (--output-limit) at cycle {k} "
                    f"(t = {k * sample_time:.3f} s)"
                )
            if progress is not None and k % 100 == 0:
                progress(k, total)
    except FoilcHilError:
        drive.safe_stop()
        raise
    return StepRecord(applied, output, sample_time)


# --- model structures -------------------------------------------------------------------------------------------


def transfer_function(kind: ModelKind, theta: Sequence[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``num, den`` (highest power first) and the delay (seconds) of the model with parameters ``theta``."""
    if kind == "first-order":
        a, b = theta
        return np.array([b]), np.array([1.0, -a]), 0.0
    if kind == "first-order-delay":
        a, b, delay = theta
        return np.array([b]), np.array([1.0, -a]), float(delay)
    d1, d0, n0 = theta
    return np.array([n0]), np.array([1.0, d1, d0]), 0.0


def state_space(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The realisation ``a, b, c`` the fragment is written in: ``x' = a x + b u`` with ``y = x`` for a first-order
    model, the controllable canonical form (``scipy.signal.tf2ss``) otherwise."""
    from scipy import signal

    if den.size == 2:
        return np.array([[-den[1] / den[0]]]), np.array([[num[-1] / den[0]]]), np.array([[1.0]])
    a, b, c, _ = signal.tf2ss(num, den)
    return np.asarray(a, float), np.asarray(b, float), np.asarray(c, float)


def _hold_matrices(a: np.ndarray, b: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """``Phi(h) = exp(a h)`` and ``Gamma(h) = int_0^h exp(a s) ds b`` from one matrix exponential."""
    from scipy.linalg import expm

    n, m = a.shape[0], b.shape[1]
    block = np.zeros((n + m, n + m))
    block[:n, :n] = a * h
    block[:n, n:] = b * h
    exponential = expm(block)
    return exponential[:n, :n], exponential[:n, n:]


def discrete_model(num: np.ndarray, den: np.ndarray, sample_time: float) -> tuple[np.ndarray, np.ndarray]:
    """ZOH ``A, B`` of the realisation :func:`state_space` (no delay), as the synthesis discretises it."""
    a, b, _ = state_space(num, den)
    return _hold_matrices(a, b, sample_time)


def simulate_increment(
    num: np.ndarray, den: np.ndarray, delay: float, increments: np.ndarray, sample_time: float
) -> np.ndarray:
    """Exact sampled response, from rest, to a held input: ``y[k]`` after ``increments[0..k-1]`` acted.

    The input ``increments[i]`` is held over ``[i Ts, (i + 1) Ts)`` and reaches the plant ``delay`` seconds later;
    with ``delay = m Ts + delta`` the hold interval ``k`` sees ``increments[k - m - 1]`` for ``delta`` seconds then
    ``increments[k - m]``: ``x[k+1] = Phi x[k] + Phi(Ts - delta) Gamma(delta) u[k-m-1] + Gamma(Ts - delta) u[k-m]``.
    """
    from scipy import signal

    a, b, c = state_space(num, den)
    m_cycles = math.floor(delay / sample_time + 1e-12)
    delta = delay - m_cycles * sample_time
    phi, _ = _hold_matrices(a, b, sample_time)
    phi_rest, gamma_rest = _hold_matrices(a, b, sample_time - delta)
    _, gamma_delta = _hold_matrices(a, b, delta)
    gamma_new = gamma_rest
    gamma_old = phi_rest @ gamma_delta
    den_z = np.poly(phi)
    response = np.zeros(increments.shape[0])
    for gamma, shift in ((gamma_new, m_cycles), (gamma_old, m_cycles + 1)):
        if not np.any(gamma):
            continue
        num_z, _ = signal.ss2tf(phi, gamma, c, np.zeros((1, 1)))
        shifted = np.concatenate([np.zeros(shift), increments])[: increments.shape[0]]
        response += signal.lfilter(np.real(num_z[0]), np.real(den_z), shifted)
    return response


# --- steps ------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StepWindow:
    """One step: cycles ``start .. stop - 1``, the command before it, and the measured level before it."""

    start: int
    stop: int
    command_before: float
    command_after: float
    level_before: float

    @property
    def size(self) -> float:
        return self.command_after - self.command_before

    def to_json(self) -> dict[str, Any]:
        return {
            "start": self.start,
            "stop": self.stop,
            "from": self.command_before,
            "to": self.command_after,
        }


def find_steps(record: StepRecord) -> list[StepWindow]:
    """Every change of the command, with its window up to the next change."""
    command, output = record.command, record.output
    changes = [k for k in range(1, command.shape[0]) if command[k] != command[k - 1]]
    bounds = [*changes, command.shape[0]]
    windows: list[StepWindow] = []
    previous_start = 0
    for start, stop in itertools.pairwise(bounds):
        if stop - start >= MIN_STEP_SAMPLES:
            # y[start] still answers the old command (it depends on u[..start-1]): it closes the pre-step average
            first = max(previous_start + 1, start + 1 - PRE_STEP_SAMPLES)
            level = float(np.mean(output[first : start + 1]))
            windows.append(StepWindow(start, stop, float(command[start - 1]), float(command[start]), level))
        previous_start = start
    return windows


def _predict(kind: ModelKind, theta: np.ndarray, record: StepRecord, level: float) -> np.ndarray:
    """The model's output over the whole record, from rest at ``level`` with the record's first command."""
    num, den, delay = transfer_function(kind, theta)
    increments = record.command - record.command[0]
    return level + simulate_increment(num, den, delay, increments, record.sample_time)


def _rest_level(record: StepRecord, windows: list[StepWindow]) -> float:
    """The output before the first step (the axis at rest: its mean absorbs a sensor offset)."""
    first = windows[0].start if windows else record.output.shape[0]
    return float(np.mean(record.output[: first + 1]))


# --- fit --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StepFit:
    """One step fitted alone, and the nominal model's quality on it."""

    window: StepWindow
    theta: np.ndarray
    r2: float
    nrmse: float
    converged: bool = True  # False: least_squares stopped at its evaluation limit (the parameters are not a fit)

    def to_json(self, kind: ModelKind) -> dict[str, Any]:
        return {**self.window.to_json(), "parameters": _named(kind, self.theta), "r2": self.r2, "nrmse": self.nrmse,
                "converged": self.converged}


@dataclass(frozen=True)
class FitResult:
    """The nominal model (all steps jointly), each step alone, and the quality figures."""

    kind: ModelKind
    theta: np.ndarray
    covariance: np.ndarray
    steps: tuple[StepFit, ...]
    residual_std: float
    r2: float
    sample_time: float
    predictions: tuple[np.ndarray, ...] = field(repr=False)
    errors: ErrorModel = field(repr=False)
    converged: bool = True  # the joint fit; each step's is in ``steps``

    @property
    def num(self) -> np.ndarray:
        return transfer_function(self.kind, self.theta)[0]

    @property
    def den(self) -> np.ndarray:
        return transfer_function(self.kind, self.theta)[1]

    @property
    def delay(self) -> float:
        return transfer_function(self.kind, self.theta)[2]

    @property
    def standard_errors(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))


_PARAMETER_NAMES: dict[str, tuple[str, ...]] = {
    "first-order": ("a", "b"),
    "first-order-delay": ("a", "b", "delay"),
    "second-order": ("d1", "d0", "n0"),
}


def _named(kind: ModelKind, theta: np.ndarray) -> dict[str, float]:
    return {name: float(value) for name, value in zip(_PARAMETER_NAMES[kind], theta, strict=True)}


def _initial_guess(kind: ModelKind, windows: list[StepWindow], record: StepRecord) -> np.ndarray:
    """From the largest step: DC gain from its end level, time constant from its 63 % crossing."""
    window = max(windows, key=lambda w: abs(w.size))
    y = record.output[window.start : window.stop] - window.level_before
    tail = y[-max(1, y.shape[0] // 5) :]
    final = float(np.mean(tail))
    gain = final / window.size if window.size else 1.0
    if gain == 0 or not math.isfinite(gain):
        gain = 1.0
    crossing = np.nonzero(np.abs(y) >= 0.632 * abs(final))[0]
    tau = max(record.sample_time, (float(crossing[0]) - 0.5) * record.sample_time if crossing.size else 1.0)
    if kind == "first-order":
        return np.array([-1.0 / tau, gain / tau])
    if kind == "first-order-delay":
        return np.array([-1.0 / tau, gain / tau, 0.5 * record.sample_time])
    fast = 10.0 / tau
    return np.array([1.0 / tau + fast, fast / tau, gain * fast / tau])


def _bounds(kind: ModelKind, sample_time: float) -> tuple[list[float], list[float]]:
    if kind == "first-order":
        return [-np.inf, -np.inf], [np.inf, np.inf]
    if kind == "first-order-delay":
        return [-np.inf, -np.inf, 0.0], [np.inf, np.inf, MAX_DELAY_CYCLES * sample_time]
    return [1e-9, 1e-9, -np.inf], [np.inf, np.inf, np.inf]


def _least_squares(
    kind: ModelKind, windows: list[StepWindow], record: StepRecord, start: np.ndarray, level: float,
    fixed_delay: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Fit the residuals inside ``windows``; returns ``theta``, the residuals, the Jacobian and whether the solver
    converged (``False``: it stopped at its evaluation limit)."""
    from scipy.optimize import least_squares

    mask = np.zeros(record.output.shape[0], dtype=bool)
    for window in windows:
        mask[window.start : window.stop] = True
    measured = record.output[mask]
    low, high = _bounds(kind, record.sample_time)
    free = np.ones(start.shape[0], dtype=bool)
    if fixed_delay is not None and kind == "first-order-delay":
        free[2] = False

    def full(x: np.ndarray) -> np.ndarray:
        theta = start.copy()
        theta[free] = x
        if fixed_delay is not None and kind == "first-order-delay":
            theta[2] = fixed_delay
        return theta

    def residuals(x: np.ndarray) -> np.ndarray:
        return np.asarray(_predict(kind, full(x), record, level)[mask] - measured)

    x0 = np.clip(start[free], np.array(low)[free] + 1e-12, np.array(high)[free] - 1e-12)
    solution = least_squares(residuals, x0, bounds=(np.array(low)[free], np.array(high)[free]),
                             x_scale="jac", method="trf")
    jacobian = np.zeros((solution.fun.shape[0], start.shape[0]))
    jacobian[:, free] = solution.jac
    return full(solution.x), solution.fun, jacobian, bool(solution.status > 0)


def _quality(predicted: np.ndarray, measured: np.ndarray) -> tuple[float, float]:
    residual = measured - predicted
    spread = float(np.sum((measured - np.mean(measured)) ** 2))
    r2 = 1.0 - float(np.sum(residual**2)) / spread if spread > 0 else float("nan")
    span = float(np.max(measured) - np.min(measured))
    nrmse = float(np.sqrt(np.mean(residual**2))) / span if span > 0 else float("nan")
    return r2, nrmse


@dataclass(frozen=True)
class ErrorModel:
    """How the parameters' covariance was estimated (module docstring, *Intervals*).

    ``score_ar1`` is the spectral radius of the VAR(1) the scores were prewhitened with, ``bandwidth`` the
    Newey-West lag window on the whitened scores, ``white_covariance`` the covariance a white-noise model
    (``s^2 (J'J)^-1``) claims, for comparison.
    """

    covariance: np.ndarray
    white_covariance: np.ndarray
    score_ar1: float
    bandwidth: int

    def to_json(self, kind: ModelKind, theta: np.ndarray) -> dict[str, Any]:
        """``{"method", "score_ar1", "bandwidth", "confidence_95", "standard_errors_white_noise"}``."""
        errors = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        white = np.sqrt(np.clip(np.diag(self.white_covariance), 0.0, None))
        return {
            "method": COVARIANCE_METHOD,
            "score_ar1": self.score_ar1,
            "bandwidth": self.bandwidth,
            "confidence_95": {
                name: [float(value - Z_95 * error), float(value + Z_95 * error)]
                for name, value, error in zip(_PARAMETER_NAMES[kind], theta, errors, strict=True)
            },
            "standard_errors_white_noise": _named(kind, white),
        }


def _andrews_bandwidth(series: np.ndarray) -> int:
    """Andrews' (1991) AR(1) plug-in lag window for the Bartlett kernel, from ``series``' lag-one correlation."""
    n = series.shape[0]
    energy = float(np.dot(series[:-1], series[:-1]))
    rho = float(np.dot(series[1:], series[:-1])) / energy if energy > 0 else 0.0
    rho = min(MAX_SCORE_AR1, max(-MAX_SCORE_AR1, rho))
    alpha = 4.0 * rho**2 / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)
    return int(min(n - 2, math.ceil(1.1447 * (alpha * n) ** (1.0 / 3.0))))


def _newey_west(scores: np.ndarray, bandwidth: int) -> np.ndarray:
    """Bartlett-weighted sum of the scores' autocovariances up to ``bandwidth`` (Newey and West 1987)."""
    meat = scores.T @ scores
    for lag in range(1, bandwidth + 1):
        cross = scores[lag:].T @ scores[:-lag]
        meat += (1.0 - lag / (bandwidth + 1.0)) * (cross + cross.T)
    return np.asarray(meat)


def error_model(jacobian: np.ndarray, residual: np.ndarray) -> ErrorModel:
    """The least-squares estimate's covariance, robust to coloured and uneven residuals (module docstring).

    Prewhitened HAC (Andrews and Monahan 1992): the scores ``s_k = J_k r_k`` are whitened by a VAR(1)
    ``s_k = Phi s_{k-1} + v_k`` (spectral radius capped at :data:`MAX_SCORE_AR1`), the long-run covariance of
    ``v`` is estimated by Newey-West, and recoloured: ``S = (I - Phi)^-1 S_v (I - Phi)^-T``. The covariance is
    ``B S B`` with ``B = (J'J)^-1``, degrees-of-freedom corrected.
    """
    n, p = jacobian.shape
    bread = np.linalg.pinv(jacobian.T @ jacobian)
    white = float(np.sum(residual**2)) / max(1, n - p) * bread
    scores = jacobian * residual[:, None]
    phi = np.linalg.lstsq(scores[:-1], scores[1:], rcond=None)[0].T
    radius = float(np.max(np.abs(np.linalg.eigvals(phi))))
    if radius > MAX_SCORE_AR1:
        phi *= MAX_SCORE_AR1 / radius
    innovations = scores[1:] - scores[:-1] @ phi.T
    bandwidth = _andrews_bandwidth(innovations.sum(axis=1))
    recolour = np.linalg.inv(np.eye(p) - phi)
    long_run = recolour @ _newey_west(innovations, bandwidth) @ recolour.T
    covariance = bread @ long_run @ bread * n / max(1, n - p)
    return ErrorModel(covariance, white, min(radius, MAX_SCORE_AR1), bandwidth)


@as_step("identification: model fit")
def fit_model(record: StepRecord, kind: ModelKind = "first-order") -> FitResult:
    """Fit ``kind`` to every step of ``record`` jointly and to each alone (see the module docstring).

    Raises
    ------
    DriveError
        When the record holds no usable step or the fit fails (the measured output did not respond).
    """
    if kind not in MODEL_KINDS:
        raise InputError(f"--model: {kind!r} is not one of {', '.join(MODEL_KINDS)}")
    windows = find_steps(record)
    if not windows:
        raise DriveError("the campaign produced no step of at least five samples to fit")
    start = _initial_guess(kind, windows, record)
    level = _rest_level(record, windows)
    theta, residual, jacobian, converged = _least_squares(kind, windows, record, start, level)
    errors = error_model(jacobian, residual)
    fixed_delay = float(theta[2]) if kind == "first-order-delay" else None
    steps: list[StepFit] = []
    predictions: list[np.ndarray] = []
    measured_all: list[np.ndarray] = []
    nominal = _predict(kind, theta, record, level)
    for window in windows:
        measured = record.output[window.start : window.stop]
        predicted = nominal[window.start : window.stop]
        predictions.append(predicted)
        measured_all.append(measured)
        r2, nrmse = _quality(predicted, measured)
        alone, _, _, settled = _least_squares(kind, [window], record, theta.copy(), level, fixed_delay=fixed_delay)
        steps.append(StepFit(window, alone, r2, nrmse, settled))
    all_measured = np.concatenate(measured_all)
    r2_total, _ = _quality(np.concatenate(predictions), all_measured)
    if not np.all(np.isfinite(theta)):
        raise DriveError("the fit diverged (non-finite parameters): did the axis respond to the steps?")
    return FitResult(kind, theta, errors.covariance, tuple(steps), float(np.std(residual)), r2_total,
                     record.sample_time, tuple(predictions), errors, converged)


# --- uncertainty ------------------------------------------------------------------------------------------------


_UNCERTAINTY_CONSTRUCTION = (
    "rho = margin * max(max_i ||X_i - X0||_2, 2 sigma_X0); G = sqrt(rho) I, H = sqrt(rho) I "
    "(H2 = sqrt(rho_B) e1); X_i the ZOH model of step i fitted alone"
)


@dataclass(frozen=True)
class UncertaintyBounds:
    """``G1, H1, G2, H2`` of the ``plant.uncertainty`` section and how they were built (module docstring)."""

    g1: np.ndarray
    h1: np.ndarray
    g2: np.ndarray
    h2: np.ndarray
    rho_a: float
    rho_b: float
    observed_max_da: float  # max over the steps of ||A_i - A0||_2
    observed_max_db: float
    sigma_a: float  # propagated standard error of A0 / B0
    sigma_b: float
    margin: float
    per_step: tuple[tuple[float, float], ...]  # (||A_i - A0||, ||B_i - B0||) per step

    def to_json(self) -> dict[str, Any]:
        return {
            "G1": self.g1.tolist(),
            "H1": self.h1.tolist(),
            "G2": self.g2.tolist(),
            "H2": self.h2.tolist(),
            "rho_A": self.rho_a,
            "rho_B": self.rho_b,
            "observed_max_dA": self.observed_max_da,
            "observed_max_dB": self.observed_max_db,
            "sigma_A": self.sigma_a,
            "sigma_B": self.sigma_b,
            "margin": self.margin,
            "per_step": [{"dA": da, "dB": db} for da, db in self.per_step],
            "construction": _UNCERTAINTY_CONSTRUCTION,
        }


def uncertainty_bounds(fit: FitResult, *, margin: float = 1.25) -> UncertaintyBounds:
    """``G1, H1, G2, H2`` covering the per-step spread of the discrete model (module docstring)."""
    if not (math.isfinite(margin) and margin >= 1):
        raise InputError(f"--uncertainty-margin: must be >= 1, got {margin}")
    ts = fit.sample_time
    a0, b0 = discrete_model(fit.num, fit.den, ts)
    n = a0.shape[0]
    per_step: list[tuple[float, float]] = []
    for step in fit.steps:
        num, den, _ = transfer_function(fit.kind, step.theta)
        a_i, b_i = discrete_model(num, den, ts)
        per_step.append((float(np.linalg.norm(a_i - a0, 2)), float(np.linalg.norm(b_i - b0, 2))))
    spread_a = max((da for da, _ in per_step), default=0.0)
    spread_b = max((db for _, db in per_step), default=0.0)
    sigma_a, sigma_b = _propagated_sigma(fit)
    rho_a = margin * max(spread_a, STATISTICAL_FLOOR_SIGMAS * sigma_a)
    rho_b = margin * max(spread_b, STATISTICAL_FLOOR_SIGMAS * sigma_b)
    root_a, root_b = math.sqrt(rho_a), math.sqrt(rho_b)
    e1 = np.zeros((n, 1))
    e1[0, 0] = 1.0
    return UncertaintyBounds(
        g1=root_a * np.eye(n),
        h1=root_a * np.eye(n),
        g2=root_b * np.eye(n),
        h2=root_b * e1,
        rho_a=rho_a,
        rho_b=rho_b,
        observed_max_da=spread_a,
        observed_max_db=spread_b,
        sigma_a=sigma_a,
        sigma_b=sigma_b,
        margin=margin,
        per_step=tuple(per_step),
    )


def _propagated_sigma(fit: FitResult) -> tuple[float, float]:
    """Standard error of ``||A0||``/``||B0||`` directions: ``sqrt(trace(J C J'))`` by finite differences."""
    ts = fit.sample_time
    a0, b0 = discrete_model(fit.num, fit.den, ts)
    base = np.concatenate([a0.ravel(), b0.ravel()])
    jac = np.zeros((base.shape[0], fit.theta.shape[0]))
    for i in range(fit.theta.shape[0]):
        h = 1e-6 * max(1.0, abs(float(fit.theta[i])))
        theta = fit.theta.copy()
        theta[i] += h
        num, den, _ = transfer_function(fit.kind, theta)
        a1, b1 = discrete_model(num, den, ts)
        jac[:, i] = (np.concatenate([a1.ravel(), b1.ravel()]) - base) / h
    covariance = jac @ fit.covariance @ jac.T
    if not np.all(np.isfinite(covariance)):
        return 0.0, 0.0
    n_a = a0.size
    return (math.sqrt(max(0.0, float(np.trace(covariance[:n_a, :n_a])))),
            math.sqrt(max(0.0, float(np.trace(covariance[n_a:, n_a:])))))


# --- documents --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CampaignSummary:
    """What the identification campaign was: its spec, mode and size, and what it measured."""

    mode: str  # "csv" or "cst"
    spec: CampaignSpec
    cycles: int
    sample_time: float
    output_quantum: float  # one count of the feedback, in plant units
    max_abs_output: float

    def to_json(self) -> dict[str, Any]:
        return {
            "mode": self.mode,
            "pattern": self.spec.pattern,
            "amplitudes": list(self.spec.amplitudes),
            "hold": self.spec.hold,
            "rest": self.spec.rest,
            "repetitions": self.spec.repetitions,
            "cycles": self.cycles,
            "sample_time": self.sample_time,
            "output_quantum": self.output_quantum,
            "max_abs_output": self.max_abs_output,
        }


def identification_document(
    fit: FitResult, uncertainty: UncertaintyBounds, campaign: CampaignSummary
) -> dict[str, Any]:
    """The ``--json`` document: ``{"plant", "uncertainty", "fit", "campaign"}`` (interface.md)."""
    a, b, c = state_space(fit.num, fit.den)
    scalar = a.shape == (1, 1)
    plant = {
        "a": float(a[0, 0]) if scalar else a.tolist(),
        "b": float(b[0, 0]) if scalar else b.tolist(),
        "c": float(c[0, 0]) if scalar else c.tolist(),
        "num": [float(x) for x in fit.num],
        "den": [float(x) for x in fit.den],
        "delay": fit.delay,
    }
    a_d, b_d = discrete_model(fit.num, fit.den, fit.sample_time)
    fit_doc = {
        "model": fit.kind,
        "parameters": _named(fit.kind, fit.theta),
        "standard_errors": _named(fit.kind, fit.standard_errors),
        "intervals": fit.errors.to_json(fit.kind, fit.theta),
        "r2": fit.r2,
        "residual_std": fit.residual_std,
        "steps": [step.to_json(fit.kind) for step in fit.steps],
        "converged": fit.converged,
        "discrete": {"A": a_d.tolist(), "B": b_d.tolist(), "sample_time": fit.sample_time},
    }
    return {"plant": plant, "uncertainty": uncertainty.to_json(), "fit": fit_doc, "campaign": campaign.to_json()}


def fragment_document(document: dict[str, Any], sample_time: float, base: dict[str, Any] | None) -> dict[str, Any]:
    """The YAML that ``tune``/``synthesize``/``run`` read: ``sample_time`` and ``plant: {a, b, c, num, den, delay,
    uncertainty: {G1, H1, G2, H2}}``, on top of ``base`` (the ``--config`` document, other sections kept; its
    ``plant.model`` and ``plant.pmsm`` stay so the embedded emulator keeps emulating the same axis)."""
    result: dict[str, Any] = {key: value for key, value in (base or {}).items()}
    plant: dict[str, Any] = dict(result.get("plant") or {})
    identified = document["plant"]
    for key in ("a", "b", "c", "num", "den", "delay"):
        plant[key] = identified[key]
    unc = document["uncertainty"]
    plant["uncertainty"] = {key: unc[key] for key in ("G1", "H1", "G2", "H2")}
    result["plant"] = plant
    result["sample_time"] = sample_time
    return result


def plot_fit(record: StepRecord, fit: FitResult, path: str | Path) -> None:
    """PNG of the measured steps against the fitted model, and the residuals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ts = record.sample_time
    t = np.arange(record.output.shape[0]) * ts
    fig, (ax_y, ax_r) = plt.subplots(2, 1, figsize=(10, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    ax_y.plot(t, record.command, color="0.6", lw=1, label="command")
    ax_y.plot(t, record.output, color="tab:blue", lw=1, label="measured")
    for index, (step, predicted) in enumerate(zip(fit.steps, fit.predictions, strict=True)):
        window = step.window
        tw = t[window.start : window.stop]
        ax_y.plot(tw, predicted, color="tab:red", lw=1, ls="--", label="fitted model" if index == 0 else None)
        ax_r.plot(tw, record.output[window.start : window.stop] - predicted, color="tab:red", lw=0.8)
    ax_y.set_ylabel("velocity (plant units)")
    ax_y.set_title(f"{fit.kind}: " + ", ".join(f"{k} = {v:.5g}" for k, v in _named(fit.kind, fit.theta).items())
                   + f"   R^2 = {fit.r2:.4f}")
    ax_y.legend(loc="upper right")
    ax_r.set_ylabel("residual")
    ax_r.set_xlabel("t (s)")
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=110)
    except OSError as exc:
        raise InputError(f"--plot: cannot write {path}: {exc}") from exc
    finally:
        plt.close(fig)

