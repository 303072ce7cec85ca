"""LMI synthesis of the learning gain ``P = (p1 p2)`` (paper section 4.2, Theorem 1, LMI (31); Remark 1).

The 2D Roesser model, derived
-----------------------------
For the discrete plant ``x(t+1) = (A + dA) x(t) + (B + dB) u(t) + d(t)``, ``y = C x`` run trial after trial with
``u_k(t) = u_{k-1}(t) + r_k(t)``, the state difference ``dx_k(t) = x_k(t) - x_{k-1}(t)`` obeys (paper (11))::

    dx_k(t+1) = (A + dA) dx_k(t) + (B + dB) r_k(t) + phi_k(t)

(``phi`` collects the trial-to-trial change of ``dA``, ``dB`` and ``d``). The tracking error
``e = y_r - y`` satisfies ``e_k(t+1) = e_{k-1}(t+1) - C dx_k(t+1)`` because ``y_r`` repeats and ``y = C x``, so

    e_k(t+1) = e_{k-1}(t+1) - C (A + dA) dx_k(t) - C (B + dB) r_k(t) - C phi_k(t).

The paper's (14) prints ``+ C (B + dB) r`` and ``+ C phi``; the signs above follow from (10)-(13). With the
state ``(dx_k(t), E_{k-1}(t+1))`` of the Roesser model (18) and ``E`` in place of ``e`` (the fractional filter's
residual ``v`` joins the disturbance),

    Abar = [[A, 0], [-C A, I]],  Bbar = [[B], [-C B]],
    dAbar = [[G1], [-C G1]] Delta1 [H1 0],  dBbar = [[G2], [-C G2]] Delta2 H2.

The paper prints the lower-left block of ``Abar`` as ``-A``; that only agrees with the derivation when ``C = I``.
The disturbance ``w = (phi, v)`` (``n + p`` entries) enters through ``Dbar = [[I, 0], [-C, I]]``; the printed
``D = diag(C, I)`` has ``2p`` rows for an ``(n + p)``-dimensional state, which does not fit. The performance
output is the error state, ``z = Cz (dx, E) = E`` with ``Cz = [0 I]`` (the print's ``C Q`` cannot multiply
an ``(n + p)``-square ``Q`` either).

The LMI
-------
With ``Q = diag(Qb, Qt) > 0``, ``Q(tau, theta) = diag(tau Qb, theta Qt)``, ``J = P Q`` and Lemma 2 applied to
each uncertainty channel (``sigma1, sigma2 > 0``)::

    [ -Q(tau,theta)  *                                   *        *        *     *   ]
    [ Abar Q+Bbar J  -Q + s1 G1b G1b' + s2 G2b G2b'      *        *        *     *   ]
    [ H1b Q          0                                  -s1 I     *        *     *   ]  < 0
    [ H2 J           0                                   0       -s2 I     *     *   ]
    [ Cz Q           0                                   0        0      -g I    *   ]
    [ 0              Dbar'                               0        0        0   -g I  ]

(``G1b = [G1; -C G1]``, ``H1b = [H1 0]``, ``G2b = [G2; -C G2]``), minimising ``gamma`` (Remark 1);
``P = J Q^-1``.

Numerics: scaling, bounded multipliers, a relative margin
--------------------------------------------------------
On the shipped plants the blocks of (31) differ by orders of magnitude (paper_sim: ``B = 0.0167``,
``G1 = 0.001`` against ``H1 = 1``), so the solver ran with multipliers ``sigma ~ 1e5`` and an LMI that held by an
absolute margin of 1e-6 -- 1e-11 of the matrix's norm, below the solver's own tolerance: feasibility and ``gamma``
were noise. The LMI is therefore solved on a scaled Roesser model (:class:`Scaling`):

* ``x = T xs``, ``u = S us`` and each channel's ``Gbar Delta H`` split as ``(Gbar c) Delta (H / c)`` (``T``, ``S``
  diagonal, ``c`` one scalar per channel, so a full ``Delta`` commutes with it), chosen by Osborne balancing of the
  interconnection ``[[Abar, Bbar, Gbar], [1/Bbar', 0, 0], [H, 0, 0]]`` (the ``1/Bbar'`` row, entry by entry, zero
  where ``Bbar`` is, stands for the size of the gain the LMI will find: a gain that cancels each state's input
  entry), then one common factor that balances ``T^-1 Dbar`` against ``Cz T``. Every factor is a power of two:
  scaling and unscaling are exact in floating point.
* The scaled LMI is a congruence of the original one, ``M = Dg Ms Dg`` with ``Dg = diag(T, T, c, I, I)``, at
  ``Q = T Qs T``, ``J = S Js T``, ``sigma = c^2 sigma_s`` and the same ``gamma`` (``w`` and ``z`` are not scaled),
  so it has the same inertia and ``P = J Q^-1 = S Ps T^-1``.
* The margin is relative, in the constraints themselves: with ``s`` a variable bounding the norm,
  ``-s I <= Ms <= -margin s I``, ``Qs >= margin s I``, ``sigma_s >= margin s``; and the multipliers are bounded,
  ``sigma_s <= SIGMA_BOUND`` (:data:`SIGMA_BOUND`).

Independent checks (numpy, after the solve)
-------------------------------------------
* the LMI matrix rebuilt in numpy from the solved (unscaled) values has largest eigenvalue ``< 0``, and the scaled
  matrix ``Dg^-1 M Dg^-1`` a margin relative to its norm of at least
  :data:`~foilc_hil.design.certificate_record.LMI_RELATIVE_MARGIN_MIN` (else LMI (31) holds only within rounding:
  the solution and its ``gamma`` are refused, never returned);
* ``Qb, Qt`` have smallest eigenvalue ``> 0``;
* at every uncertainty vertex (``Delta = +-1`` for scalars; for matrices the sign-diagonal partial isometries and
  seeded random ones, all extreme points of the unit spectral-norm ball), the closed loop
  ``Acl = Abar + Bbar P + dAbar + dBbar P`` satisfies the Lyapunov decrease
  ``Acl' Q^-1 Acl - diag(tau Qb^-1, theta Qt^-1) < 0`` and its 1D conditions: spectral radius of the time
  block ``A + dA + (B + dB) p1`` and of the trial block ``I - C (B + dB) p2`` below one.

A failing check raises :class:`~foilc_hil.errors.LmiInfeasibleError` naming the condition (CLI exit 3).

Module order: after :mod:`foilc_hil.design.certificates` (the solved gain is certified as the law runs), before
:mod:`foilc_hil.design.pipeline` (which takes everything from the configuration).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

import numpy as np

from foilc_hil.config import DivergentFilterPolicy, LawKind
from foilc_hil.design.certificate_record import LMI_RELATIVE_MARGIN_MIN, LmiChecks, LmiScaling, Timing
from foilc_hil.design.certificates import certify
from foilc_hil.design.lifted import LawStructure
from foilc_hil.design.models import DiscreteModel, Uncertainty, uncertainty_vertices
from foilc_hil.design.record import Design
from foilc_hil.errors import ConfigError, InputError, LmiInfeasibleError
from foilc_hil.progress import as_step

__all__ = [
    "SIGMA_BOUND",
    "LmiSolution",
    "LmiVerification",
    "RoesserModel",
    "Scaling",
    "SpectralChecks",
    "VertexChecks",
    "balance",
    "lmi_matrix",
    "roesser_model",
    "solve_lmi",
    "synthesize",
    "verify_lmi_solution",
]

Solver = Literal["CLARABEL", "SCS"]
_SOLVERS: tuple[Solver, ...] = ("CLARABEL", "SCS")
INFEASIBLE = "infeasible"  # cvxpy.INFEASIBLE, spelled here: cvxpy is imported only to solve

#: Upper bound of every multiplier ``sigma_s`` of the scaled LMI (module notes). The scaled blocks are O(1), so a
#: multiplier beyond this means one channel's Lemma-2 term outweighs the rest of the matrix by 1e4 and the LMI's
#: margin relative to it would be rounding; the bound makes the solver find another solution or report none.
SIGMA_BOUND = 1e4
#: Osborne sweeps of :func:`balance` at most (it converges in a handful on these small matrices).
_BALANCE_SWEEPS = 50

@dataclass(frozen=True)
class Channel:
    """One independent uncertainty channel of the Roesser model: ``Gbar Delta Hbar`` adds to ``Abar``
    (``kind="state"``, ``Hbar = [H 0]`` multiplies ``Q``) or ``Gbar Delta H P`` (``kind="input"``, ``H``
    multiplies ``J``)."""

    kind: str
    Gbar: np.ndarray
    H: np.ndarray


@dataclass(frozen=True)
class RoesserModel:
    """The 2D Roesser model (18) as derived in the module notes; all blocks for state ``(dx, E)``."""

    Abar: np.ndarray
    Bbar: np.ndarray
    channels: tuple[Channel, ...]
    Dbar: np.ndarray
    Cz: np.ndarray
    n_states: int
    n_outputs: int


def roesser_model(model: DiscreteModel, uncertainty: Uncertainty) -> RoesserModel:
    """Build ``Abar, Bbar``, the uncertainty channels ``[G; -C G] Delta [H 0]`` / ``[G; -C G] Delta H P``,
    ``Dbar`` and ``Cz`` (module notes)."""
    uncertainty.check_against(model)
    A, B, C = model.A, model.B, model.C
    n, p = model.n_states, model.n_outputs
    Abar = np.block([[A, np.zeros((n, p))], [-C @ A, np.eye(p)]])
    Bbar = np.vstack([B, -C @ B])
    channels = []
    for kind, G, H in uncertainty.channels():
        Gbar = np.vstack([G, -C @ G])
        Hbar = np.hstack([H, np.zeros((H.shape[0], p))]) if kind == "state" else H
        channels.append(Channel(kind, Gbar, Hbar))
    Dbar = np.block([[np.eye(n), np.zeros((n, p))], [-C, np.eye(p)]])
    Cz = np.hstack([np.zeros((p, n)), np.eye(p)])
    return RoesserModel(Abar, Bbar, tuple(channels), Dbar, Cz, n, p)


def _power_of_two(value: float) -> float:
    return float(2.0 ** round(math.log2(value)))


@dataclass(frozen=True)
class Scaling:
    """The diagonal similarity LMI (31) is solved in (module notes): ``x = T xs``, ``u = S us``, channel ``i``
    split as ``(Gbar c_i) Delta (H / c_i)``; every factor a power of two."""

    state: np.ndarray  # diag(T), n + p
    inputs: np.ndarray  # diag(S), m
    channels: tuple[float, ...]  # c_i

    def apply(self, roesser: RoesserModel) -> RoesserModel:
        """The scaled Roesser model: ``T^-1 Abar T``, ``T^-1 Bbar S``, ``T^-1 Gbar c``, ``H T / c`` (``H S / c``),
        ``T^-1 Dbar``, ``Cz T``."""
        T, S = self.state, self.inputs
        channels = tuple(
            Channel(ch.kind, ch.Gbar * c / T[:, None], ch.H * (T if ch.kind == "state" else S)[None, :] / c)
            for ch, c in zip(roesser.channels, self.channels, strict=True)
        )
        return replace(
            roesser,
            Abar=roesser.Abar * T[None, :] / T[:, None],
            Bbar=roesser.Bbar * S[None, :] / T[:, None],
            channels=channels,
            Dbar=roesser.Dbar / T[:, None],
            Cz=roesser.Cz * T[None, :],
        )

    def congruence(self, roesser: RoesserModel) -> np.ndarray:
        """``diag(Dg)``: the original LMI matrix is ``Dg Ms Dg`` (module notes)."""
        parts = [self.state, self.state]
        parts += [np.full(ch.H.shape[0], c) for ch, c in zip(roesser.channels, self.channels, strict=True)]
        parts += [np.ones(roesser.n_outputs), np.ones(roesser.Dbar.shape[1])]
        return np.concatenate(parts)

    def unscale(self, values: dict[str, Any]) -> dict[str, Any]:
        """The scaled problem's solution in the original coordinates: ``Q = T Qs T``, ``J = S Js T``,
        ``sigma = c^2 sigma_s``, the same ``gamma`` (exact: powers of two)."""
        T, S = self.state, self.inputs
        n = values["Qb"].shape[0]
        return {
            "Qb": values["Qb"] * np.outer(T[:n], T[:n]),
            "Qt": values["Qt"] * np.outer(T[n:], T[n:]),
            "J": values["J"] * np.outer(S, T),
            "sigmas": tuple(sigma * c**2 for sigma, c in zip(values["sigmas"], self.channels, strict=True)),
            "gamma": values["gamma"],
        }


def _interconnection(roesser: RoesserModel) -> tuple[np.ndarray, list[list[int]]]:
    """The square matrix Osborne balances, over the signals ``x``, ``u`` and one block per channel, and its
    groups (one per state, one per input, one per channel: a channel shares one factor)."""
    nb, m = roesser.Bbar.shape
    sizes = [channel.H.shape[0] for channel in roesser.channels]
    Z = np.zeros((nb + m + sum(sizes),) * 2)
    Z[:nb, :nb] = roesser.Abar
    Z[:nb, nb : nb + m] = roesser.Bbar
    B = roesser.Bbar.T
    # the size of a gain that cancels each state's input entry (module notes)
    Z[nb : nb + m, :nb] = np.divide(1.0, B, out=np.zeros_like(B), where=B != 0)
    groups = [[i] for i in range(nb + m)]
    start = nb + m
    for channel, q in zip(roesser.channels, sizes, strict=True):
        Z[:nb, start : start + q] = channel.Gbar
        columns = slice(0, nb) if channel.kind == "state" else slice(nb, nb + m)
        Z[start : start + q, columns] = channel.H
        groups.append(list(range(start, start + q)))
        start += q
    return Z, groups


def balance(roesser: RoesserModel) -> Scaling:
    """Osborne balancing (2-norms of each group's off-diagonal rows and columns made equal, factors rounded to
    powers of two) of the model's interconnection, then one common factor balancing ``T^-1 Dbar`` against
    ``Cz T`` (module notes)."""
    Z, groups = _interconnection(roesser)
    d = np.ones(Z.shape[0])
    for _ in range(_BALANCE_SWEEPS):
        changed = False
        for group in groups:
            scaled = Z * d[None, :] / d[:, None]
            others = np.ones(Z.shape[0], dtype=bool)
            others[group] = False
            row = float(np.linalg.norm(scaled[np.ix_(np.array(group), others)]))
            column = float(np.linalg.norm(scaled[np.ix_(others, np.array(group))]))
            if row == 0 or column == 0:
                continue
            factor = _power_of_two(math.sqrt(row / column))
            if factor != 1.0:
                d[group] *= factor
                changed = True
        if not changed:
            break
    nb, m = roesser.Bbar.shape
    T = d[:nb]
    common = _power_of_two(
        math.sqrt(float(np.linalg.norm(roesser.Dbar / T[:, None])) / float(np.linalg.norm(roesser.Cz * T[None, :])))
    )
    channels = tuple(float(d[group[0]]) * common for group in groups[nb + m :])
    return Scaling(state=T * common, inputs=d[nb : nb + m] * common, channels=channels)


@dataclass(frozen=True)
class LmiSolution:
    """Solved values of LMI (31) and how they were obtained."""

    P: np.ndarray
    Qb: np.ndarray
    Qt: np.ndarray
    J: np.ndarray
    sigmas: tuple[float, ...]
    gamma: float
    solver: str
    status: str
    checks: LmiChecks
    seconds: float = 0.0  # wall-clock time of the solve and its checks (informational)


@dataclass(frozen=True)
class SpectralChecks:
    """The eigenvalue checks of the solved LMI matrix and of ``Q``, with the margin relative to the norm of the scaled
    matrix ``Dg^-1 M Dg^-1`` (the one solved) and of ``M`` itself (:func:`verify_lmi_solution`)."""

    lmi_max_eigenvalue: float
    Qb_min_eigenvalue: float
    Qt_min_eigenvalue: float
    relative_margin: float
    relative_margin_unscaled: float
    Q_condition: float


@dataclass(frozen=True)
class VertexChecks:
    """Theorem 1's Lyapunov decrease and 1D radii: the worst over the nominal model and the ``vertices_checked``
    uncertainty vertices."""

    lyapunov_max_eigenvalue: float
    time_radius: float
    trial_radius: float
    vertices_checked: int


@dataclass(frozen=True)
class LmiVerification:
    """What :func:`verify_lmi_solution` measured on a solution it confirmed, and its gain ``P = J Q^-1``."""

    spectral: SpectralChecks
    vertices: VertexChecks
    P: np.ndarray


def lmi_matrix(
    roesser: RoesserModel,
    *,
    Qb: Any,
    Qt: Any,
    J: Any,
    sigmas: Sequence[Any],
    gamma: Any,
    tau: float,
    theta: float,
    bmat: Any,
) -> Any:
    """The LMI (31) matrix from values (``bmat=np.block``) or cvxpy expressions (``bmat=cp.bmat``).

    One row/column block per uncertainty channel (``sigmas[i]`` its multiplier); laid out as in the module
    notes. The one function builds both, so the numpy check evaluates exactly the matrix handed to the solver.
    """
    n, p = roesser.n_states, roesser.n_outputs
    nb = n + p
    nw = roesser.Dbar.shape[1]
    Z = np.zeros
    Q = bmat([[Qb, Z((n, p))], [Z((p, n)), Qt]])
    Qw = bmat([[tau * Qb, Z((n, p))], [Z((p, n)), theta * Qt]])
    AQ = roesser.Abar @ Q + roesser.Bbar @ J
    CzQ = roesser.Cz @ Q
    sizes = [channel.H.shape[0] for channel in roesser.channels]
    HQ = [channel.H @ (Q if channel.kind == "state" else J) for channel in roesser.channels]
    second = -Q
    for sigma, channel in zip(sigmas, roesser.channels, strict=True):
        second = second + sigma * (channel.Gbar @ channel.Gbar.T)
    rows: list[list[Any]] = [
        [-Qw, AQ.T, *[h.T for h in HQ], CzQ.T, Z((nb, nw))],
        [AQ, second, *[Z((nb, q)) for q in sizes], Z((nb, p)), roesser.Dbar],
    ]
    for i, (sigma, q) in enumerate(zip(sigmas, sizes, strict=True)):
        row = [HQ[i], Z((q, nb))]
        row += [-sigma * np.eye(q) if j == i else Z((q, sizes[j])) for j in range(len(sizes))]
        row += [Z((q, p)), Z((q, nw))]
        rows.append(row)
    rows.append([CzQ, Z((p, nb)), *[Z((p, q)) for q in sizes], -gamma * np.eye(p), Z((p, nw))])
    rows.append([Z((nw, nb)), roesser.Dbar.T, *[Z((nw, q)) for q in sizes], Z((nw, p)), -gamma * np.eye(nw)])
    return bmat(rows)


def _check_rates(tau: float, theta: float, margin: float) -> None:
    for name, value in (("tau", tau), ("theta", theta)):
        if not (isinstance(value, (int, float)) and 0.0 < value < 1.0):
            raise ConfigError(f"must satisfy 0 < {name} < 1, got {value!r}", key=f"synthesis.{name}")
    if not (isinstance(margin, (int, float)) and math.isfinite(margin) and margin > 0):
        raise ConfigError(f"must be positive, got {margin!r}", key="synthesis.margin")


@dataclass(frozen=True)
class StandardForm:
    """LMI (31) as ``M(x) = F0 + sum_i x_i F_i`` over the decision vector ``x`` (the upper triangles of ``Qb`` and
    ``Qt``, ``J`` row by row, the multipliers ``sigma``, then ``gamma``), and ``Qb``, ``Qt`` as linear maps of ``x``.

    The coefficients are :func:`lmi_matrix` evaluated with numpy at ``x = 0`` and at each unit vector (the matrix is
    affine in the decision variables), so cvxpy gets one linear map instead of an expression tree of blocks, whose
    compilation would be most of a solve's time (the solver itself is a small part).
    ``tests/design/test_lmi_numerics.py``

    checks ``M(x)`` against :func:`lmi_matrix` at random ``x``.
    """

    F0: np.ndarray
    F: np.ndarray  # (size * size, k): column i is F_i, row-major
    Qb_map: np.ndarray  # (n * n, k)
    Qt_map: np.ndarray  # (p * p, k)
    n_states: int
    n_outputs: int
    n_inputs: int
    n_channels: int

    @property
    def size(self) -> int:
        """Rows (and columns) of ``M``."""
        return self.F0.shape[0]

    def unpack(self, x: np.ndarray) -> dict[str, Any]:
        """The decision variables of ``x``: ``Qb``, ``Qt`` (symmetric), ``J``, ``sigmas``, ``gamma``."""
        return _unpack(x, self.Qb_map, self.Qt_map, self.n_states, self.n_outputs, self.n_inputs, self.n_channels)

    def matrix(self, x: np.ndarray) -> np.ndarray:
        """``M(x)``."""
        return self.F0 + (self.F @ np.asarray(x, dtype=float)).reshape(self.F0.shape)


def _unpack(
    x: np.ndarray, Qb_map: np.ndarray, Qt_map: np.ndarray, n: int, p: int, m: int, c: int
) -> dict[str, Any]:
    """:meth:`StandardForm.unpack` (``n`` states, ``p`` outputs, ``m`` inputs, ``c`` channels)."""
    start = n * (n + 1) // 2 + p * (p + 1) // 2  # J's first entry, after the two upper triangles
    x = np.asarray(x, dtype=float)
    sigma_slots, gamma_slot = _multiplier_slots(x.size, c)
    return {
        "Qb": (Qb_map @ x).reshape(n, n),
        "Qt": (Qt_map @ x).reshape(p, p),
        "J": x[start:start + m * (n + p)].reshape(m, n + p),
        "sigmas": tuple(float(x[slot]) for slot in sigma_slots),
        "gamma": float(x[gamma_slot]),
    }


def _multiplier_slots(k: int, c: int) -> tuple[range, int]:
    """Where the ``c`` multipliers ``sigma`` and ``gamma`` sit in a decision vector of ``k`` entries: its last
    ``c + 1``, in that order (:class:`StandardForm`)."""
    return range(k - 1 - c, k - 1), k - 1


def _symmetric_map(size: int, offset: int, k: int) -> np.ndarray:
    """The ``(size * size, k)`` map from ``x`` to a symmetric matrix whose upper triangle is ``x[offset:]``."""
    rows, columns = np.triu_indices(size)
    mapping = np.zeros((size * size, k))
    slots = offset + np.arange(rows.size)
    mapping[rows * size + columns, slots] = 1.0
    mapping[columns * size + rows, slots] = 1.0
    return mapping


def standard_form(scaled: RoesserModel, tau: float, theta: float) -> StandardForm:
    """The coefficients of LMI (31) on ``scaled`` (see :class:`StandardForm`)."""
    n, p = scaled.n_states, scaled.n_outputs
    m, c = scaled.Bbar.shape[1], len(scaled.channels)
    upper_n, upper_p = n * (n + 1) // 2, p * (p + 1) // 2
    k = upper_n + upper_p + m * (n + p) + c + 1
    Qb_map, Qt_map = _symmetric_map(n, 0, k), _symmetric_map(p, upper_n, k)

    def evaluate(x: np.ndarray) -> np.ndarray:
        values = _unpack(x, Qb_map, Qt_map, n, p, m, c)
        return np.asarray(lmi_matrix(scaled, tau=tau, theta=theta, bmat=np.block, **values), dtype=float)

    F0 = evaluate(np.zeros(k))
    F = np.empty((F0.size, k))
    for i, unit in enumerate(np.eye(k)):
        F[:, i] = (evaluate(unit) - F0).ravel()
    return StandardForm(F0, F, Qb_map, Qt_map, n, p, m, c)


def _solve_once(
    scaled: RoesserModel, tau: float, theta: float, solver: Solver, margin: float
) -> tuple[str, dict[str, Any] | None]:
    """Solve the scaled LMI (module notes: relative margin, bounded multipliers); the values are the scaled ones."""
    import cvxpy as cp

    form = standard_form(scaled, tau, theta)
    n, p, c, size = form.n_states, form.n_outputs, form.n_channels, form.size
    x = cp.Variable(form.F.shape[1], name="x")
    bound = cp.Variable(name="norm_bound")  # s >= ||Ms||: the margin is relative to it
    M = cp.reshape(form.F0.ravel() + form.F @ x, (size, size), order="C")
    Qb = cp.reshape(form.Qb_map @ x, (n, n), order="C")
    Qt = cp.reshape(form.Qt_map @ x, (p, p), order="C")
    sigma_slots, gamma_slot = _multiplier_slots(form.F.shape[1], c)
    sigmas = [x[slot] for slot in sigma_slots]
    gamma = x[gamma_slot]
    eye = np.eye(size)
    # M, Qb and Qt are symmetric by construction; cvxpy's PSD constraint still wants a symmetric expression, so
    # symmetrise explicitly (a no-op on the exact value).
    M_sym = (M + M.T) / 2
    constraints = [
        M_sym << -margin * bound * eye,
        M_sym >> -bound * eye,
        (Qb + Qb.T) / 2 >> margin * bound * np.eye(n),
        (Qt + Qt.T) / 2 >> margin * bound * np.eye(p),
        *[sigma >= margin * bound for sigma in sigmas],
        *[sigma <= SIGMA_BOUND for sigma in sigmas],
    ]
    problem = cp.Problem(cp.Minimize(gamma), constraints)
    try:
        with warnings.catch_warnings():
            # cvxpy warns "Solution may be inaccurate" on stderr; the status says it (recorded in the design) and
            # the numpy re-check of the solution decides, so the warning only cluttered make demo's output
            warnings.filterwarnings("ignore", message="Solution may be inaccurate", category=UserWarning)
            problem.solve(solver=solver)
    except cp.error.SolverError as exc:
        return f"solver error: {exc}".splitlines()[0], None
    status = str(problem.status)
    if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or x.value is None:
        return status, None
    return status, form.unpack(np.asarray(x.value, dtype=float))


def _spectral_radius(matrix: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(matrix)))) if matrix.size else 0.0


def _relative_margin(M: np.ndarray) -> float:
    """``-lambda_max(M) / ||M||_2`` of a symmetric matrix: near machine epsilon means "holds within rounding"."""
    spectrum = np.linalg.eigvalsh((M + M.T) / 2)
    return float(-np.max(spectrum) / np.max(np.abs(spectrum)))


def _condition(Qb: np.ndarray, Qt: np.ndarray) -> float:
    """``cond(diag(Qb, Qt))`` from the eigenvalues of its symmetric blocks."""
    values = np.concatenate([np.linalg.eigvalsh((Qb + Qb.T) / 2), np.linalg.eigvalsh((Qt + Qt.T) / 2)])
    return float(np.max(values) / np.min(values)) if np.min(values) > 0 else math.inf


def _spectral_checks(M: np.ndarray, congruence: np.ndarray, Qb: np.ndarray, Qt: np.ndarray) -> SpectralChecks:
    """The eigenvalue checks of the solved LMI matrix and ``Q`` (:class:`SpectralChecks`)."""
    return SpectralChecks(
        lmi_max_eigenvalue=float(np.max(np.linalg.eigvalsh((M + M.T) / 2))),
        Qb_min_eigenvalue=float(np.min(np.linalg.eigvalsh(Qb))),
        Qt_min_eigenvalue=float(np.min(np.linalg.eigvalsh(Qt))),
        relative_margin=_relative_margin(M / np.outer(congruence, congruence)),
        relative_margin_unscaled=_relative_margin(M),
        Q_condition=_condition(Qb, Qt),
    )


def verify_lmi_solution(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    values: dict[str, Any],
    *,
    tau: float,
    theta: float,
    scaling: Scaling | None = None,
) -> LmiVerification:
    """The independent numpy checks of the module notes on ``values`` in the original coordinates (``scaling``: the
    coordinates they were solved in, for the relative margin). Returns the measured numbers and the gain.

    Raises
    ------
    foilc_hil.errors.LmiInfeasibleError
        Naming the first condition that fails; a margin within rounding refuses the solution and its ``gamma``.
    """
    roesser = roesser_model(model, uncertainty)
    n = model.n_states
    Qb, Qt, J = values["Qb"], values["Qt"], values["J"]
    Qb = (Qb + Qb.T) / 2
    Qt = (Qt + Qt.T) / 2
    M = lmi_matrix(
        roesser,
        Qb=Qb,
        Qt=Qt,
        J=J,
        sigmas=values["sigmas"],
        gamma=values["gamma"],
        tau=tau,
        theta=theta,
        bmat=np.block,
    )
    if not np.allclose(M, M.T, rtol=0, atol=1e-12 * max(1.0, float(np.max(np.abs(M))))):
        raise LmiInfeasibleError("LMI (31): the assembled matrix is not symmetric (internal error)")
    congruence = np.ones(M.shape[0]) if scaling is None else scaling.congruence(roesser)
    spectral = _spectral_checks(M, congruence, Qb, Qt)
    lmi_max, qb_min, qt_min = spectral.lmi_max_eigenvalue, spectral.Qb_min_eigenvalue, spectral.Qt_min_eigenvalue
    if not lmi_max < 0:
        raise LmiInfeasibleError(f"LMI (31): largest eigenvalue of the solved matrix is {lmi_max:.3g}, not < 0")
    if not spectral.relative_margin >= LMI_RELATIVE_MARGIN_MIN:
        raise LmiInfeasibleError(
            f"LMI (31) holds only within rounding (margin {spectral.relative_margin:.3g} of its norm, below "
            f"{LMI_RELATIVE_MARGIN_MIN:g}): gamma = {values['gamma']:.6g} is not confirmed"
        )
    if not (qb_min > 0 and qt_min > 0):
        raise LmiInfeasibleError(f"LMI (31): Q is not positive definite (min eigenvalues {qb_min:.3g}, {qt_min:.3g})")
    Q = np.block([[Qb, np.zeros((n, Qt.shape[0]))], [np.zeros((Qt.shape[0], n)), Qt]])
    P = np.linalg.solve(Q.T, J.T).T  # J Q^-1
    rates = np.block(
        [[tau * np.linalg.inv(Qb), np.zeros((n, Qt.shape[0]))], [np.zeros((Qt.shape[0], n)), theta * np.linalg.inv(Qt)]]
    )
    return LmiVerification(spectral, _vertex_checks(model, uncertainty, P, np.linalg.inv(Q), rates), P)


def _vertex_checks(
    model: DiscreteModel, uncertainty: Uncertainty, P: np.ndarray, Qinv: np.ndarray, rates: np.ndarray
) -> VertexChecks:
    """Theorem 1's Lyapunov decrease and 1D radii at the nominal model and every vertex; the worst of each."""
    n = model.n_states
    p1, p2 = P[:, :n], P[:, n:]
    worst_lyapunov, worst_time, worst_trial = -math.inf, 0.0, 0.0
    cases: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros_like(model.A), np.zeros_like(model.B))]
    cases.extend(uncertainty_vertices(uncertainty))
    for index, (dA, dB) in enumerate(cases):
        A_v, B_v = model.A + dA, model.B + dB
        Abar_v = np.block([[A_v, np.zeros((n, model.n_outputs))], [-model.C @ A_v, np.eye(model.n_outputs)]])
        Bbar_v = np.vstack([B_v, -model.C @ B_v])
        Acl = Abar_v + Bbar_v @ P
        lyapunov = float(np.max(np.linalg.eigvalsh(Acl.T @ Qinv @ Acl - rates)))
        time_radius = _spectral_radius(A_v + B_v @ p1)
        trial_radius = _spectral_radius(np.eye(model.n_outputs) - model.C @ B_v @ p2)
        where = "the nominal model" if index == 0 else f"uncertainty vertex {index}"
        if not lyapunov < 0:
            raise LmiInfeasibleError(f"Theorem 1: Lyapunov decrease fails at {where} (max eigenvalue {lyapunov:.3g})")
        if not time_radius < 1:
            raise LmiInfeasibleError(f"Theorem 1: time-direction block unstable at {where} (radius {time_radius:.4g})")
        if not trial_radius < 1:
            raise LmiInfeasibleError(
                f"Theorem 1: trial-direction block unstable at {where} (radius {trial_radius:.4g})"
            )
        worst_lyapunov = max(worst_lyapunov, lyapunov)
        worst_time = max(worst_time, time_radius)
        worst_trial = max(worst_trial, trial_radius)
    return VertexChecks(worst_lyapunov, worst_time, worst_trial, vertices_checked=len(cases) - 1)


@as_step("LMI (31)")
def solve_lmi(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    *,
    tau: float,
    theta: float,
    solver: Solver = "CLARABEL",
    margin: float = 1e-6,
) -> LmiSolution:
    """Solve LMI (31) minimising ``gamma`` on the scaled model with a margin relative to the matrix's norm
    (``margin``), and verify the solution independently in the original coordinates (module notes).

    The requested solver is tried first, then the other one if it fails to solve or its solution fails a
    check; the solution records which solver produced it. A solver that proves the problem infeasible (a
    certificate, cvxpy's ``infeasible``) ends the search: the other one cannot find what does not exist, and SCS
    spent its whole iteration budget (4-9 s) trying.

    Raises
    ------
    foilc_hil.errors.LmiInfeasibleError
        When no solver yields a solution that passes every check; the message names the failing condition.
    """
    started = time.perf_counter()
    _check_rates(tau, theta, margin)
    if solver not in _SOLVERS:
        raise ConfigError(f"must be one of {', '.join(_SOLVERS)}, got {solver!r}", key="synthesis.solver")
    roesser = roesser_model(model, uncertainty)
    scaling = balance(roesser)
    scaled = scaling.apply(roesser)
    order = [solver, *[s for s in _SOLVERS if s != solver]]
    failures: list[str] = []
    for name in order:
        status, solved = _solve_once(scaled, tau, theta, name, margin)
        if solved is None:
            failures.append(f"{name}: {status}")
            if status == INFEASIBLE:
                break
            continue
        values = scaling.unscale(solved)
        try:
            verified = verify_lmi_solution(model, uncertainty, values, tau=tau, theta=theta, scaling=scaling)
        except LmiInfeasibleError as exc:
            failures.append(f"{name}: {exc}")
            continue
        P = verified.P
        record = LmiChecks(
            solver=name,
            status=status,
            sigmas=tuple(values["sigmas"]),
            solver_failures=tuple(failures),
            P_lmi=P,
            scaling=LmiScaling(
                state=tuple(float(x) for x in scaling.state),
                inputs=tuple(float(x) for x in scaling.inputs),
                channels=scaling.channels,
                sigmas=tuple(solved["sigmas"]),
                sigma_bound=SIGMA_BOUND,
                Q_condition=_condition(solved["Qb"], solved["Qt"]),
            ),
            **asdict(verified.spectral),
            **asdict(verified.vertices),
        )
        return LmiSolution(
            P=P,
            Qb=(values["Qb"] + values["Qb"].T) / 2,
            Qt=(values["Qt"] + values["Qt"].T) / 2,
            J=values["J"],
            sigmas=tuple(values["sigmas"]),
            gamma=float(values["gamma"]),
            solver=name,
            status=status,
            checks=record,
            seconds=time.perf_counter() - started,
        )
    raise LmiInfeasibleError(f"LMI (31) infeasible for tau={tau:g}, theta={theta:g} ({'; '.join(failures)})")


def synthesize(
    model: DiscreteModel,
    uncertainty: Uncertainty | None,
    law: LawStructure,
    *,
    kind: LawKind = LawKind.FOILC,
    tau: float = 0.868,
    theta: float = 0.868,
    solver: Solver = "CLARABEL",
    margin: float = 1e-6,
    policy: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE,
    require_monotonic: bool = True,
    growth_horizon: int = 10,
) -> Design:
    """Solve Theorem 1 for ``P`` on ``model`` and certify the law as it runs (fractional filter included).

    Parameters
    ----------
    model
        The discrete design model (already delay-augmented if the loop has input delay).
    uncertainty
        Its norm-bounded uncertainty; ``None``: none.
    law
        How the law runs (:class:`~foilc_hil.design.lifted.LawStructure`: ``kp``, ``r``, trial length,
        lead = the model's input delay, fractional memory, Q-filter); the certificates are of exactly this law.
    kind
        ``foilc`` or ``ioilc`` (IOILC certifies ``kp = 0``).
    tau, theta
        Convergence indices along time and trials, in ``(0, 1)``.
    solver, margin
        cvxpy solver tried first and the LMI strictness margin.
    policy
        ``synthesis.on_divergent_filter`` (see :func:`foilc_hil.design.certificates.certify`).
    require_monotonic
        Demand a monotonic (induced 2-norm) certificate, not only an asymptotic (spectral radius) one.
    growth_horizon
        Trials over which the error-growth bound is reported when only asymptotic convergence is certified.

    Raises
    ------
    foilc_hil.errors.LmiInfeasibleError
        The LMI has no solution passing the checks (exit 3).
    foilc_hil.errors.ConvergenceCertificateError
        The law as it runs is not certified and could not be fixed (exit 3).
    """
    started = time.perf_counter()
    if kind not in (LawKind.FOILC, LawKind.IOILC):
        raise InputError(f"law: synthesize designs 'foilc' or 'ioilc', got {kind!r}")
    if law.lead != model.input_delay:
        raise InputError(f"law: its lead {law.lead} must be the model's input delay {model.input_delay}")
    if kind is LawKind.IOILC:
        law = replace(law, kp=0.0)
    unc = uncertainty if uncertainty is not None else Uncertainty.none(model.n_states, model.n_inputs)
    solution = solve_lmi(model, unc, tau=tau, theta=theta, solver=solver, margin=margin)
    lmi_seconds = time.perf_counter() - started
    outcome = certify(
        model, unc, solution.P, law, policy=policy, require_monotonic=require_monotonic, growth_horizon=growth_horizon
    )
    timing = Timing(lmi_seconds, time.perf_counter() - started)
    return Design(
        law=LawKind(kind),
        model=model,
        uncertainty=unc,
        P=outcome.P,
        kp=law.kp,
        r=law.r,
        Qb=solution.Qb,
        Qt=solution.Qt,
        gamma=solution.gamma,
        tau=float(tau),
        theta=float(theta),
        gain_scale=outcome.gain_scale,
        certificates=replace(outcome.certificates, lmi=solution.checks, seconds=timing),
    )
