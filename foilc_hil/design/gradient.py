"""Gradient (steepest-descent) ILC, lifted: the simplest model-based baseline beside norm-optimal ILC.

Each trial takes one step down the gradient of ``||e||^2 / 2`` with respect to the input,

    u_k = u_{k-1} + beta G^T e_{k-1},

with ``G`` the lifted nominal plant of :func:`foilc_hil.design.noilc.lifted_plant` (inputs ``u[0..N-d-1]`` to the
errors they move, ``e[d..N-1]``). ``G^T e`` runs the plant's impulse response backwards in time over the trial: the
law is feedforward only, computed between trials (like NOILC's).

The step
--------
On the nominal plant the error map is ``T = I - beta G G^T``: symmetric, eigenvalues ``1 - beta sigma_i^2`` for
the singular values ``sigma_i`` of ``G``. It contracts monotonically (``||T||_2 < 1``) exactly when
``0 < beta < 2 / ||G||_2^2``. The design takes ``beta = STEP_RELATIVE / ||G||_2^2`` with :data:`STEP_RELATIVE`
``= 1``: the middle of that interval. The direction of the largest plant gain is then removed in one trial
(eigenvalue 0), every other contracts by ``1 - sigma_i^2 / ||G||^2 in [0, 1)`` (no overshoot on the nominal plant),
and a plant whose gain is up to twice the nominal one in that direction still contracts. The slowest direction is
the one of the smallest plant gain: gradient ILC is slow where the plant is small, which is NOILC's advantage.

Certificates
------------
The dense trial map (error map, or the input map with a Q-filter) at the nominal plant and every uncertainty
vertex, spectral radius and induced 2-norm, by :func:`foilc_hil.design.noilc.certify_lifted`, the code NOILC's
certificates use.

Module order: after :mod:`foilc_hil.design.noilc`, before :mod:`foilc_hil.design.lmi`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from foilc_hil.config import LawKind
from foilc_hil.design.certificates import LawStructure
from foilc_hil.design.models import DiscreteModel, Uncertainty
from foilc_hil.design.noilc import certify_lifted, lifted_plant, noilc_gain
from foilc_hil.design.record import Design, GradientStep, NoilcWeights
from foilc_hil.errors import InputError

__all__ = ["STEP_RELATIVE", "certify_gradient", "gradient_gain", "gradient_step", "lifted_gain"]

#: ``beta ||G||_2^2``: 1 is the middle of the monotonic range ``(0, 2)`` (module notes).
STEP_RELATIVE = 1.0


def gradient_step(model: DiscreteModel, n_samples: int) -> GradientStep:
    """``beta = STEP_RELATIVE / ||G||_2^2`` for trials of ``n_samples`` on ``model`` (module notes)."""
    G = lifted_plant(model.A, model.B, model.measured_output, n_samples, model.input_delay)
    norm = float(np.linalg.norm(G, 2))
    if not norm > 0:
        raise InputError("plant: no input moves the measured output within a trial; gradient ILC cannot learn")
    return GradientStep(beta=STEP_RELATIVE / norm**2, plant_norm=norm, step_relative=STEP_RELATIVE)


def gradient_gain(model: DiscreteModel, step: GradientStep, n_samples: int) -> np.ndarray:
    """``L = beta G^T``, ``(L m) x (L p)``: the lifted learning gain."""
    G = lifted_plant(model.A, model.B, model.measured_output, n_samples, model.input_delay)
    return np.asarray(step.beta * G.T, dtype=float)


def certify_gradient(
    model: DiscreteModel, uncertainty: Uncertainty, law: LawStructure, *, require_monotonic: bool
) -> Design:
    """The gradient ILC design for ``model``: its step and the certificates of the law as it runs."""
    step = gradient_step(model, law.n_samples)
    return certify_lifted(
        model,
        uncertainty,
        gradient_gain(model, step, law.n_samples),
        law,
        require_monotonic=require_monotonic,
        kind=LawKind.GRADIENT,
        addition={"gradient": step},
    )


def lifted_gain(design: Design, n_samples: int) -> np.ndarray | None:
    """The lifted gain ``L`` of a NOILC or gradient design for trials of ``n_samples``; ``None`` for the laws that
    run per sample (FOILC, IOILC, P-type). Rebuilt from the weights or step its certificates record.

    The array is read-only and shared: a process keeps the last few gains (a robustness run builds a law per drawn
    plant from one design, and NOILC's gain costs an ``O(L^3)`` solve, about a second at 2000 samples)."""
    certificates = design.certificates
    if design.law is LawKind.NOILC and certificates is not None and certificates.noilc is not None:
        return _shared_gain(_SameModel(design.model), certificates.noilc, n_samples)
    if design.law is LawKind.GRADIENT and certificates is not None and certificates.gradient is not None:
        return _shared_gain(_SameModel(design.model), certificates.gradient, n_samples)
    if design.law in (LawKind.NOILC, LawKind.GRADIENT):
        raise InputError(f"design.certificates: a {design.law} design records its lifted gain's parameters")
    return None


@dataclass(frozen=True, eq=False)
class _SameModel:
    """A model as a cache key: equal when the lifted plant ``G`` is (its ``A``, ``B``, measured output, delay)."""

    model: DiscreteModel

    def _key(self) -> tuple[object, ...]:
        m = self.model
        arrays = (m.A, m.B, m.measured_output)
        return (m.input_delay, *((a.shape, a.tobytes()) for a in arrays))

    def __hash__(self) -> int:
        return hash(self._key())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _SameModel) and self._key() == other._key()


@functools.lru_cache(maxsize=4)
def _shared_gain(model: _SameModel, parameters: NoilcWeights | GradientStep, n_samples: int) -> np.ndarray:
    if isinstance(parameters, NoilcWeights):
        gain = noilc_gain(model.model, parameters, n_samples)
    else:
        gain = gradient_gain(model.model, parameters, n_samples)
    gain.flags.writeable = False
    return gain
