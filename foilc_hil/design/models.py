"""Discrete design models: zero-order hold or forward Euler, input-delay augmentation, discrete uncertainty.

Errata item 1: the paper's eq. (6) ``A = a - I`` is a forward-Euler step with unit sample time. The product
discretises with a zero-order hold and the configured sample time (``A = exp(a Ts)``,
``B = int_0^Ts exp(a s) ds b``, both read off one matrix exponential of the block matrix
``[[a, b], [0, 0]] Ts``); ``method="euler"`` gives ``A = I + a Ts``, ``B = b Ts`` to compare with the print.

Uncertainty: the config's ``plant.uncertainty`` matrices ``G1, H1, G2, H2`` describe the DISCRETE model the gain
is designed on, ``dA = G1 Delta H1``, ``dB = G2 Delta H2`` with ``||Delta|| <= 1`` (paper eq. 7 is written for
the discrete model too). They are not rescaled with ``Ts``; omitted ones mean no uncertainty in that channel
(zero matrices of compatible size).

Input delay: a SYNC-driven CAN loop applies the input one cycle late. :func:`augment_input_delay` folds ``d``
cycles of delay into the state, ``z(t) = [x(t); u(t-d); ...; u(t-1)]``, so ``x(t+1) = A x(t) + B u(t-d)`` is the
first block row of ``z(t+1) = Az z(t) + Bz u(t)``. The measured output is ``y(t) = [C 0] z(t)``; the design
output is the ``d``-step-ahead output ``y(t+d) = Cz z(t)`` (computable from ``z(t)`` because the inputs of the
next ``d`` steps are already in the delay line), which restores relative degree one for the Roesser model of
Theorem 1. A law designed on the augmented model therefore uses the measured error ``d`` samples further ahead
(see :attr:`foilc_hil.design.record.Design.error_lead`).

Module order: first in :mod:`foilc_hil.design` (imports no other design module).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np

from foilc_hil.errors import ConfigError, InputError
from foilc_hil.schema import as_array
from plant_emulator.config import UncertaintyConfig
from plant_emulator.linear import ContinuousModel

__all__ = [
    "DiscreteModel",
    "Uncertainty",
    "augment_input_delay",
    "discretize",
    "uncertainty_from_config",
    "uncertainty_vertices",
]

Method = Literal["zoh", "euler"]

#: Cap on sampled vertices per uncertainty channel (matrix Delta), and on vertex combinations overall.
MAX_VERTICES_PER_CHANNEL = 8
MAX_VERTEX_COMBINATIONS = 32


def ssmatrix(value: object, name: str, *, allow_scalar: bool = True) -> np.ndarray:
    """``value`` as a finite, read-only 2-D float array (a copy); errors name the matrix (python-control's
    ``_ssmatrix`` style). A scalar becomes ``1 x 1`` unless ``allow_scalar`` is false."""
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name}: must be a real matrix (list of rows of numbers)") from None
    if array.ndim == 0 and allow_scalar:
        array = array.reshape(1, 1)
    if array.ndim != 2:
        raise InputError(f"{name}: must be a 2-D matrix, got {array.ndim} dimension(s)")
    if not np.all(np.isfinite(array)):
        raise InputError(f"{name}: must be finite")
    array.setflags(write=False)
    return array


@dataclass(frozen=True)
class DiscreteModel:
    """``x(t+1) = A x(t) + B u(t)``, ``y(t) = C x(t)`` sampled every ``sample_time`` seconds.

    Attributes
    ----------
    A, B, C
        ``n x n``, ``n x m``, ``p x n``. ``C`` is the design output (see the module notes on input delay).
    sample_time
        Seconds per sample.
    input_delay
        Cycles of input delay folded into the state (0: none).
    C_measured
        The measured output ``y(t) = C_measured z(t)``; equal to ``C`` without input delay.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    sample_time: float
    input_delay: int = 0
    C_measured: np.ndarray | None = None

    def __post_init__(self) -> None:
        A = ssmatrix(self.A, "A")
        B = ssmatrix(self.B, "B")
        C = ssmatrix(self.C, "C")
        n = A.shape[0]
        if A.shape != (n, n):
            raise InputError(f"A: must be square, got {A.shape[0]}x{A.shape[1]}")
        if B.shape[0] != n:
            raise InputError(f"B: must have {n} rows (the states of A), got {B.shape[0]}")
        if C.shape[1] != n:
            raise InputError(f"C: must have {n} columns (the states of A), got {C.shape[1]}")
        if not (isinstance(self.sample_time, (int, float)) and math.isfinite(self.sample_time)):
            raise InputError("sample_time: must be a finite number")
        if self.sample_time <= 0:
            raise InputError(f"sample_time: must be positive, got {self.sample_time}")
        if int(self.input_delay) != self.input_delay or self.input_delay < 0:
            raise InputError(f"input_delay: must be a non-negative integer, got {self.input_delay}")
        measured = C if self.C_measured is None else ssmatrix(self.C_measured, "C_measured")
        if measured.shape != C.shape:
            raise InputError(f"C_measured: must be {C.shape[0]}x{C.shape[1]} like C, got {measured.shape}")
        if self.input_delay == 0 and not np.array_equal(measured, C):
            raise InputError("C_measured: must equal C when there is no input delay")
        for name, value in (("A", A), ("B", B), ("C", C), ("C_measured", measured)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "sample_time", float(self.sample_time))
        object.__setattr__(self, "input_delay", int(self.input_delay))

    @property
    def n_states(self) -> int:
        """``n``."""
        return int(self.A.shape[0])

    @property
    def n_inputs(self) -> int:
        """``m``."""
        return int(self.B.shape[1])

    @property
    def n_outputs(self) -> int:
        """``p``."""
        return int(self.C.shape[0])

    @property
    def measured_output(self) -> np.ndarray:
        """``C_measured`` (never ``None`` after construction)."""
        assert self.C_measured is not None
        return self.C_measured


@dataclass(frozen=True)
class Uncertainty:
    """Norm-bounded uncertainty ``dA = G1 Delta1 H1``, ``dB = G2 Delta2 H2``, ``||Delta_i|| <= 1``.

    ``state_blocks`` splits ``Delta1`` into independent diagonal blocks (their sizes, summing to the columns of
    ``G1``); empty means one block. Delay augmentation uses it to keep the plant's ``dA`` and the delayed ``dB``
    as separate channels, each with its own multiplier in the LMI (a shared one would be needlessly conservative).
    """

    G1: np.ndarray
    H1: np.ndarray
    G2: np.ndarray
    H2: np.ndarray
    state_blocks: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        for name in ("G1", "H1", "G2", "H2"):
            object.__setattr__(self, name, ssmatrix(getattr(self, name), name))
        blocks = tuple(int(b) for b in self.state_blocks)
        if blocks and (any(b < 1 for b in blocks) or sum(blocks) != self.G1.shape[1]):
            raise InputError(f"state_blocks: must be positive sizes summing to {self.G1.shape[1]}, got {blocks}")
        object.__setattr__(self, "state_blocks", blocks)
        if self.G1.shape[1] != self.H1.shape[0]:
            raise InputError(
                f"G1/H1: Delta must fit between them: G1 has {self.G1.shape[1]} columns, H1 {self.H1.shape[0]} rows"
            )
        if self.G2.shape[1] != self.H2.shape[0]:
            raise InputError(
                f"G2/H2: Delta must fit between them: G2 has {self.G2.shape[1]} columns, H2 {self.H2.shape[0]} rows"
            )

    @classmethod
    def none(cls, n_states: int, n_inputs: int) -> Uncertainty:
        """No uncertainty: zero matrices of compatible size (``Delta`` 1 x 1)."""
        return cls(np.zeros((n_states, 1)), np.zeros((1, n_states)), np.zeros((n_states, 1)), np.zeros((1, n_inputs)))

    def check_against(self, model: DiscreteModel) -> None:
        """Raise :class:`ConfigError` naming the matrix whose size does not fit ``model``."""
        n, m = model.n_states, model.n_inputs
        checks = (
            ("G1", self.G1.shape[0], n, "rows"),
            ("H1", self.H1.shape[1], n, "columns"),
            ("G2", self.G2.shape[0], n, "rows"),
            ("H2", self.H2.shape[1], m, "columns"),
        )
        for name, actual, expected, what in checks:
            if actual != expected:
                raise ConfigError(f"must have {expected} {what}, got {actual}", key=f"plant.uncertainty.{name}")

    def channels(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """The independent non-zero channels ``(kind, G, H)``: kind ``"state"`` (``G Delta H`` adds to ``A``)
        or ``"input"`` (adds to ``B``). Channels with ``G = 0`` or ``H = 0`` are left out."""
        result: list[tuple[str, np.ndarray, np.ndarray]] = []
        sizes = self.state_blocks or (self.G1.shape[1],)
        start = 0
        for size in sizes:
            G, H = self.G1[:, start : start + size], self.H1[start : start + size, :]
            start += size
            if np.any(G) and np.any(H):
                result.append(("state", G, H))
        if np.any(self.G2) and np.any(self.H2):
            result.append(("input", self.G2, self.H2))
        return result

    @property
    def is_zero(self) -> bool:
        """True when both channels vanish (``G Delta H = 0`` for every ``Delta``)."""
        return not ((np.any(self.G1) and np.any(self.H1)) or (np.any(self.G2) and np.any(self.H2)))


def _orthonormal_extreme(rows: int, cols: int, rng: np.random.Generator) -> np.ndarray:
    """A random extreme point of the unit spectral-norm ball: all singular values one."""
    k = max(rows, cols)
    q, r = np.linalg.qr(rng.standard_normal((k, k)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return np.asarray(q[:rows, :cols])


def _channel_vertices(rows: int, cols: int, seed: int) -> list[np.ndarray]:
    """Extreme points of ``{Delta : ||Delta||_2 <= 1}`` (``rows x cols``) to check at.

    ``1 x 1``: exactly ``{-1, +1}``. Otherwise the ball has a continuum of extreme points (the partial
    isometries); we take the sign-diagonal ones ``diag(+-1)`` (all of them when there are at most
    ``MAX_VERTICES_PER_CHANNEL``) plus seeded random orthonormal ones, up to the cap. This samples, it does not
    enumerate: the LMI itself covers the whole ball, the vertex checks are an independent spot check.
    """
    if rows == 1 and cols == 1:
        return [np.array([[-1.0]]), np.array([[1.0]])]
    k = min(rows, cols)
    vertices: list[np.ndarray] = []
    for signs in itertools.product((-1.0, 1.0), repeat=k):
        if len(vertices) >= MAX_VERTICES_PER_CHANNEL // 2:
            break
        delta = np.zeros((rows, cols))
        delta[np.arange(k), np.arange(k)] = signs
        vertices.append(delta)
    rng = np.random.default_rng(seed)
    while len(vertices) < MAX_VERTICES_PER_CHANNEL:
        vertices.append(_orthonormal_extreme(rows, cols, rng))
    return vertices


def uncertainty_vertices(uncertainty: Uncertainty, *, seed: int = 0) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``(dA, dB)`` at the uncertainty vertices (see :func:`_channel_vertices`); nothing when uncertainty is zero.

    Each independent channel (:meth:`Uncertainty.channels`) takes its extreme points; the combinations are
    produced sign-diagonal ones first, at most :data:`MAX_VERTEX_COMBINATIONS` of them.
    """
    n, m = uncertainty.G1.shape[0], uncertainty.H2.shape[1]
    per_channel: list[list[tuple[np.ndarray, np.ndarray]]] = []
    for index, (kind, G, H) in enumerate(uncertainty.channels()):
        options = []
        for delta in _channel_vertices(G.shape[1], H.shape[0], seed + index):
            term = G @ delta @ H
            options.append((term, np.zeros((n, m))) if kind == "state" else (np.zeros((n, n)), term))
        per_channel.append(options)
    if not per_channel:
        return
    for count, combination in enumerate(itertools.product(*per_channel)):
        if count >= MAX_VERTEX_COMBINATIONS:
            return
        dA = sum((term[0] for term in combination), np.zeros((n, n)))
        dB = sum((term[1] for term in combination), np.zeros((n, m)))
        yield dA, dB


def uncertainty_from_config(config: UncertaintyConfig, n_states: int, n_inputs: int) -> Uncertainty:
    """The discrete-model uncertainty of ``plant.uncertainty``; omitted pairs become zeros.

    Raises
    ------
    foilc_hil.errors.ConfigError
        When only one matrix of a pair is given or a size does not fit the model (naming the key).
    """
    pairs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for g_name, h_name, cols in (("G1", "H1", n_states), ("G2", "H2", n_inputs)):
        g_raw = getattr(config, g_name)
        h_raw = getattr(config, h_name)
        if (g_raw is None) != (h_raw is None):
            missing = h_name if h_raw is None else g_name
            partner = g_name if missing == h_name else h_name
            raise ConfigError(f"is required together with {partner}", key=f"plant.uncertainty.{missing}")
        if g_raw is None:
            pairs[g_name] = (np.zeros((n_states, 1)), np.zeros((1, cols)))
            continue
        g = as_array(g_raw, f"plant.uncertainty.{g_name}")
        h = as_array(h_raw, f"plant.uncertainty.{h_name}")
        if g.shape[0] != n_states:
            raise ConfigError(
                f"must have {n_states} rows (the states), got {g.shape[0]}", key=f"plant.uncertainty.{g_name}"
            )
        if h.shape[1] != cols:
            what = "states" if h_name == "H1" else "inputs"
            raise ConfigError(
                f"must have {cols} columns (the {what}), got {h.shape[1]}", key=f"plant.uncertainty.{h_name}"
            )
        if g.shape[1] != h.shape[0]:
            raise ConfigError(
                f"Delta must fit between {g_name} ({g.shape[1]} columns) and {h_name} ({h.shape[0]} rows)",
                key=f"plant.uncertainty.{h_name}",
            )
        pairs[g_name] = (g, h)
    return Uncertainty(pairs["G1"][0], pairs["G1"][1], pairs["G2"][0], pairs["G2"][1])


def discretize(model: ContinuousModel, sample_time: float, method: Method = "zoh") -> DiscreteModel:
    """Sample ``x' = a x + b u``, ``y = c x`` every ``sample_time`` seconds.

    Parameters
    ----------
    model
        The continuous model (its ``delay`` is not folded in here; see :func:`augment_input_delay`).
    sample_time
        ``Ts > 0`` in seconds.
    method
        ``"zoh"``: ``A = exp(a Ts)``, ``B = int_0^Ts exp(a s) ds b`` from ``expm([[a, b], [0, 0]] Ts)``;
        ``"euler"``: ``A = I + a Ts``, ``B = b Ts`` (the paper's eq. (6) is this with ``Ts = 1``).

    Raises
    ------
    foilc_hil.errors.InputError
        For a non-positive sample time or an unknown method.
    """
    from scipy.linalg import expm

    if not (isinstance(sample_time, (int, float)) and math.isfinite(sample_time) and sample_time > 0):
        raise InputError(f"sample_time: must be positive and finite, got {sample_time!r}")
    a = ssmatrix(model.a, "a")
    b = ssmatrix(model.b, "b")
    c = ssmatrix(model.c, "c")
    n, m = a.shape[0], b.shape[1]
    if method == "zoh":
        block = np.zeros((n + m, n + m))
        block[:n, :n] = a * sample_time
        block[:n, n:] = b * sample_time
        exponential = expm(block)
        A, B = exponential[:n, :n], exponential[:n, n:]
    elif method == "euler":
        A, B = np.eye(n) + a * sample_time, b * sample_time
    else:
        raise InputError(f"method: must be 'zoh' or 'euler', got {method!r}")
    return DiscreteModel(A, B, c, float(sample_time))


def augment_input_delay(
    model: DiscreteModel, cycles: int, uncertainty: Uncertainty | None = None
) -> tuple[DiscreteModel, Uncertainty]:
    """Fold ``cycles`` samples of input delay into the state (module notes), padding the uncertainty.

    The augmented state is ``z = [x; u(t-d); ...; u(t-1)]`` (oldest input first), so
    ``x(t+1) = A x(t) + B u(t-d)``, each delay slot shifts one place, and ``u(t)`` enters the last slot.
    The returned model's ``C`` is the ``d``-step-ahead output map ``Cz`` with ``y(t+d) = Cz z(t)``;
    ``C_measured = [C 0]``. The uncertainty is padded with zeros: ``dA`` acts on ``x`` only (``G1 -> [G1; 0]``,
    ``H1 -> [H1 0]``), and ``dB`` multiplies the delayed input, so it moves into the state matrix as
    ``dAz = [G2; 0] Delta2 [0 ... H2]`` (the input matrix of the augmented model is exact). Because
    Theorem 1's uncertainty channels are independent, ``dB`` then becomes a second ``dA`` channel: the returned
    ``G1/H1`` stack both (``Delta = diag(Delta1, Delta2)``, still ``||Delta|| <= 1``) and ``G2/H2`` are zero.

    Raises
    ------
    foilc_hil.errors.InputError
        For a negative or non-integer ``cycles``, or a model that is already augmented.
    """
    if int(cycles) != cycles or cycles < 0:
        raise InputError(f"input_delay: must be a non-negative integer, got {cycles!r}")
    if model.input_delay:
        raise InputError("input_delay: the model is already augmented")
    n, m = model.n_states, model.n_inputs
    base_uncertainty = uncertainty if uncertainty is not None else Uncertainty.none(n, m)
    base_uncertainty.check_against(model)
    d = int(cycles)
    if d == 0:
        return model, base_uncertainty
    nz = n + d * m
    Az = np.zeros((nz, nz))
    Az[:n, :n] = model.A
    Az[:n, n : n + m] = model.B  # the oldest slot u(t-d) drives the plant
    for slot in range(d - 1):  # slot i+1 moves to slot i
        Az[n + slot * m : n + (slot + 1) * m, n + (slot + 1) * m : n + (slot + 2) * m] = np.eye(m)
    Bz = np.zeros((nz, m))
    Bz[n + (d - 1) * m :, :] = np.eye(m)
    C_measured = np.hstack([model.C, np.zeros((model.n_outputs, d * m))])
    C_ahead = C_measured @ np.linalg.matrix_power(Az, d)
    G1 = np.vstack([base_uncertainty.G1, np.zeros((d * m, base_uncertainty.G1.shape[1]))])
    H1 = np.hstack([base_uncertainty.H1, np.zeros((base_uncertainty.H1.shape[0], d * m))])
    G2_as_state = np.vstack([base_uncertainty.G2, np.zeros((d * m, base_uncertainty.G2.shape[1]))])
    H2_as_state = np.zeros((base_uncertainty.H2.shape[0], nz))
    H2_as_state[:, n : n + m] = base_uncertainty.H2
    G1z = np.hstack([G1, G2_as_state])
    H1z = np.zeros((H1.shape[0] + H2_as_state.shape[0], nz))
    H1z[: H1.shape[0]] = H1
    H1z[H1.shape[0] :] = H2_as_state
    augmented = DiscreteModel(Az, Bz, C_ahead, model.sample_time, input_delay=d, C_measured=C_measured)
    blocks = (H1.shape[0], H2_as_state.shape[0])
    return augmented, Uncertainty(G1z, H1z, np.zeros((nz, 1)), np.zeros((1, m)), state_blocks=blocks)
