"""The picture of convergence: the trial-to-trial map of the law as it runs, over frequency, against 1.

For long trials a learning law's trial-to-trial map is a Toeplitz operator, and its frequency response (its
symbol) says, frequency by frequency, by how much a component of the input (or error) shrinks from one trial to
the next. ``sup_w |M(e^jw)| < 1`` is the frequency-domain condition for monotone convergence in the long-trial
limit (the textbook ``|Q (1 - L G)| < 1``; IterativeLearningControl2.jl draws it as ``ilc_theorem``), and the
curve shows where an ILC engineer should put a Q-filter's cutoff: below the frequencies where it reaches 1.

The map drawn is the one :mod:`foilc_hil.design.certificates` certifies (the lifted input map
``M = R (Q - P2 S F Gy - P1 Gz)``), with each lifted Toeplitz operator replaced by its transfer function at
``z = e^jw``:

* FOILC, IOILC, P-type (``u_k = Q u_{k-1} + p1 (x_k - x_{k-1}) + p2 E_{k-1}(t + d)``, ``E = F e``):

      M(z) = (I - p1 X)^-1 (Q - p1 X - p2 F(z) G(z)),   X = (zI - A)^-1 B,   G(z) = z^(d+1) C (zI - A)^-1 B,

  ``A, B, C`` the delay-augmented design model (``G`` is then the plant without its delay: the law looks ahead
  over it), ``F(z) = 1 + kp h^-r sum_{j < L} w_j z^-j`` the Grünwald–Letnikov filter truncated at the trial's
  ``L = N - d`` learnable samples, as the law runs it (``kp = 0``: IOILC and P-type, ``F = 1``; P-type has
  ``p1 = 0``, ``p2 = gamma``). Without a Q-filter ``M = 1 - p2 F G_cl`` with ``G_cl = z^(d+1) C (zI - A - B p1)^-1 B``:
  the state feedback ``p1`` changes the plant the learning sees.
* Gradient ILC (``L = beta G0^T``): ``M = Q - beta G0(z)^H G(z)``; on the nominal plant ``Q - beta |G|^2``.
* Norm-optimal ILC (``L = (q G0^T G0 + r I)^-1 q G0^T``): ``M = Q - (q |G0|^2 + r)^-1 q G0^H G``; on the nominal plant
  ``Q - q |G|^2 / (q |G|^2 + r)``. ``G0`` is the nominal plant the law's gain was built on and ``G`` the plant
  it runs on. Their lifted gains are not Toeplitz; the formula is their long-trial limit, away from the trial's
  edges.

``Q(z)`` is the frequency response of the design's Q-filter (:attr:`~foilc_hil.design.record.Design.q_filter`, the
object the certificates were computed with and the law runs; :meth:`~foilc_hil.design.qfilter.QFilter.response`):
the Butterworth ``|H|^2`` for the zero-phase (forward-backward) filter, ``H`` for a causal one; ``1`` without a
filter.
The law stores ``Q u_{k-1}`` and adds the learning term unfiltered, hence ``Q - L G`` rather than ``Q (1 - L G)``;
the two agree without a filter.

Each curve is ``|M|`` (the largest singular value for several channels) at the nominal plant and at each
uncertainty vertex (:func:`~foilc_hil.design.models.uncertainty_vertices`, frozen plants, as the certificates).
What the curve is not: a certificate. Finite trials have edges; the certificate's induced 2-norm of the finite
map is the bound that counts and is marked on the picture beside the curve.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from foilc_hil.config import LawKind
from foilc_hil.design.fractional import gl_weights
from foilc_hil.design.models import uncertainty_vertices
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.record import Design
from foilc_hil.errors import InputError

__all__ = ["ConvergenceCurve", "ConvergencePicture", "convergence_picture", "law_symbol"]

#: frequencies drawn, log-spaced from the lowest a trial resolves (pi / L rad/sample) to Nyquist
POINTS = 600


@dataclass(frozen=True)
class ConvergenceCurve:
    """``|M(e^jw)|`` of one plant (``"nominal"`` or ``"vertex k"``, the certificates' names)."""

    plant: str
    magnitude: np.ndarray

    @property
    def peak(self) -> float:
        """The largest value on the grid (the long-trial contraction factor of the worst frequency)."""
        return float(np.max(self.magnitude))


@dataclass(frozen=True)
class ConvergencePicture:
    """What the picture of convergence draws (:func:`convergence_picture`).

    Attributes
    ----------
    law, formula
        The law and, in words, the map drawn (module notes).
    frequency
        rad/s, log-spaced from ``pi / (L Ts)`` to Nyquist ``pi / Ts``.
    curves
        The nominal plant first, then each uncertainty vertex.
    sample_time, n_samples, learnable
        ``Ts``, the trial's ``N`` and its ``L = N - d`` learnable samples (the fractional filter's length).
    q_filter
        The design's Q-filter, or ``None``.
    certified_norm_2, norm_2_method
        The certificate's worst induced 2-norm of the finite-trial map and how it was obtained (``None`` for a design
        without certificates).
    """

    law: LawKind
    formula: str
    frequency: np.ndarray
    curves: tuple[ConvergenceCurve, ...]
    sample_time: float
    n_samples: int
    learnable: int
    q_filter: QFilter | None
    certified_norm_2: float | None
    norm_2_method: str | None

    @property
    def nominal(self) -> ConvergenceCurve:
        return self.curves[0]

    @property
    def vertices(self) -> tuple[ConvergenceCurve, ...]:
        return self.curves[1:]

    @property
    def worst(self) -> ConvergenceCurve:
        """The curve with the highest peak."""
        return max(self.curves, key=lambda curve: curve.peak)

    def to_json(self) -> dict[str, Any]:
        """The summary a report or ``synthesize --plots`` records (not the curves themselves)."""
        worst = self.worst
        at = float(self.frequency[int(np.argmax(worst.magnitude))])
        return {
            "law": str(self.law),
            "formula": self.formula,
            "n_samples": self.n_samples,
            "nominal_peak": self.nominal.peak,
            "worst_peak": worst.peak,
            "worst_plant": worst.plant,
            "worst_frequency": at,
            "below_one": bool(worst.peak < 1.0),
            "q_filter": None if self.q_filter is None else self.q_filter.to_json(),
            "certified_norm_2": self.certified_norm_2,
            "norm_2_method": self.norm_2_method,
        }


_FORMULAS = {
    LawKind.FOILC: "M = (Q - p1 X - p2 F G) / (1 - p1 X),  F = 1 + kp h^-r sum w_j z^-j",
    LawKind.IOILC: "M = (Q - p1 X - p2 G) / (1 - p1 X)",
    LawKind.P_TYPE: "M = Q - gamma G",
    LawKind.GRADIENT: "M = Q - beta conj(G0) G   (nominal: Q - beta |G|^2)",
    LawKind.NOILC: "M = Q - q conj(G0) G / (q |G0|^2 + r)   (nominal: Q - q|G|^2 / (q|G|^2 + r))",
}


def _plant_responses(A: np.ndarray, B: np.ndarray, C: np.ndarray, z: np.ndarray, lead: int) -> tuple[np.ndarray, ...]:
    """``X = (zI - A)^-1 B`` (``(K, n, m)``) and ``G = z^(lead+1) C X`` (``(K, p, m)``) at each ``z``."""
    n = A.shape[0]
    pencil = z[:, None, None] * np.eye(n) - A
    X = np.linalg.solve(pencil, np.broadcast_to(B.astype(complex), (z.size, *B.shape)))
    G = z[:, None, None] ** (lead + 1) * np.einsum("pn,knm->kpm", C, X)
    return X, G


def _filter_response(design: Design, learnable: int, z: np.ndarray) -> np.ndarray:
    """``F(z)``: the law's Grünwald–Letnikov filter on ``learnable`` samples (Horner in ``z^-1``); 1 for ``kp = 0``."""
    if design.kp == 0.0:
        return np.ones(z.shape, dtype=complex)
    weights = gl_weights(design.r, learnable)
    return 1.0 + design.kp * design.sample_time**-design.r * np.polyval(weights[::-1], 1.0 / z)


def _lifted_law_symbol(
    design: Design, A: np.ndarray, B: np.ndarray, z: np.ndarray, q: np.ndarray, learnable: int
) -> np.ndarray:
    """``M(z)`` (``(K, m, m)``) of the gradient or norm-optimal law on the plant ``(A, B)`` (module notes)."""
    assert design.certificates is not None
    lead, C = design.input_delay, design.measured_output
    m = B.shape[1]
    _, G = _plant_responses(A, B, C, z, lead)
    _, G0 = _plant_responses(design.A, design.B, C, z, lead)
    G0h = np.conj(np.swapaxes(G0, 1, 2))
    identity = np.eye(m)
    if design.law is LawKind.GRADIENT:
        step = design.certificates.gradient
        if step is None:
            raise InputError("design.certificates.gradient: a gradient design records its step beta")
        scale = float(getattr(step, "scale", 1.0))  # a shrunk update, where the certificate step records one
        learning = scale * step.beta * G0h @ G
    else:
        weights = design.certificates.noilc
        if weights is None:
            raise InputError("design.certificates.noilc: a norm-optimal design records its weights q, r")
        scale = float(getattr(weights, "scale", 1.0))
        normal = weights.q * G0h @ G0 + weights.r * identity
        learning = scale * np.linalg.solve(normal, weights.q * G0h @ G)
    return q[:, None, None] * identity - learning


def law_symbol(
    design: Design,
    w: np.ndarray,
    *,
    plant: tuple[np.ndarray, np.ndarray] | None = None,
    n_samples: int | None = None,
) -> np.ndarray:
    """``M(e^jw)`` of ``design``'s law, ``(K, m, m)`` complex, at ``w`` rad/sample (module notes).

    Parameters
    ----------
    design
        The design (its law, gain, model, Q-filter and, for gradient and NOILC, the step or weights in its
        certificates).
    w
        Frequencies in rad/sample, in ``(0, pi]``.
    plant
        ``(A, B)`` of the plant the law runs on (e.g. an uncertainty vertex); ``None``: the design's nominal model.
    n_samples
        The trial length ``N`` (the fractional filter's truncation at ``N - d``); ``None``: the certificates'.
    """
    frequencies = np.asarray(w, dtype=float)
    if frequencies.ndim != 1 or not np.all((frequencies > 0) & (frequencies <= math.pi)):
        raise InputError("w: must be a 1-D array of frequencies in (0, pi] rad/sample")
    learnable = _learnable(design, n_samples)
    A, B = plant if plant is not None else (design.A, design.B)
    z = np.exp(1j * frequencies)
    q = np.ones(z.shape, dtype=complex) if design.q_filter is None else design.q_filter.response(frequencies)
    if design.law in (LawKind.GRADIENT, LawKind.NOILC):
        return _lifted_law_symbol(design, A, B, z, q, learnable)
    m = B.shape[1]
    X, G = _plant_responses(A, B, design.measured_output, z, design.input_delay)
    p1X = np.einsum("mn,knj->kmj", design.p1, X)
    F = _filter_response(design, learnable, z)
    learning = np.einsum("mp,kpj->kmj", design.p2, G) * F[:, None, None]
    feedback = np.eye(m) - p1X
    return np.linalg.solve(feedback, q[:, None, None] * np.eye(m) - p1X - learning)


def _learnable(design: Design, n_samples: int | None) -> int:
    """``L = N - d``: the trial's samples an input can move (the certificates' length)."""
    if n_samples is None:
        if design.certificates is None:
            raise InputError("n_samples: a design without certificates needs the trial length")
        n_samples = design.certificates.n_samples
    learnable = int(n_samples) - design.input_delay
    if learnable < 1:
        raise InputError(f"n_samples: {n_samples} leaves no learnable sample after {design.input_delay} of delay")
    return learnable


def _magnitude(M: np.ndarray) -> np.ndarray:
    """``|M|`` per frequency: the modulus, or the largest singular value for several channels."""
    if M.shape[1:] == (1, 1):
        return np.asarray(np.abs(M[:, 0, 0]))
    return np.asarray(np.linalg.svd(M, compute_uv=False)[:, 0])


def convergence_picture(design: Design, *, n_samples: int | None = None, points: int = POINTS) -> ConvergencePicture:
    """``|M(e^jw)|`` of the law at the nominal plant and at every uncertainty vertex, for the picture.

    The law's Q-filter is the design's (:attr:`~foilc_hil.design.record.Design.q_filter`); ``n_samples`` the
    trial length (default: the certificates'). The frequency grid is ``points`` log-spaced values from
    ``pi / L`` to ``pi`` rad/sample, given in rad/s.
    """
    learnable = _learnable(design, n_samples)
    w = np.unique(np.concatenate([np.geomspace(math.pi / max(learnable, 2), math.pi, points), [math.pi]]))
    plants = [("nominal", design.A, design.B)]
    plants += [
        (f"vertex {k}", design.A + dA, design.B + dB)
        for k, (dA, dB) in enumerate(uncertainty_vertices(design.uncertainty), start=1)
    ]
    n_samples = learnable + design.input_delay
    curves = tuple(
        ConvergenceCurve(name, _magnitude(law_symbol(design, w, plant=(A, B), n_samples=n_samples)))
        for name, A, B in plants
    )
    certificates = design.certificates
    norm_2 = method = None
    if certificates is not None:
        norm_2 = certificates.norm_2
        worst = max(certificates.plants, key=lambda plant: plant.norm_2, default=None)
        method = None if worst is None else worst.norm_2_method
    return ConvergencePicture(
        law=design.law,
        formula=_FORMULAS[design.law],
        frequency=w / design.sample_time,
        curves=curves,
        sample_time=design.sample_time,
        n_samples=n_samples,
        learnable=learnable,
        q_filter=design.q_filter,
        certified_norm_2=norm_2,
        norm_2_method=method,
    )
