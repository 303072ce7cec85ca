"""Gradient (steepest-descent) ILC: the simplest model-based baseline beside norm-optimal ILC.

Each trial takes one step down the gradient of ``||e||^2 / 2`` with respect to the input,

    u_k = u_{k-1} + beta G^T e_{k-1},

with ``G`` the lifted nominal plant of :func:`foilc_hil.design.noilc.lifted_plant` (inputs ``u[0..N-d-1]`` to the
errors they move, ``e[d..N-1]``). ``G^T e`` runs the plant's impulse response backwards in time over the trial: one
backward pass of the adjoint state-space system (:func:`foilc_hil.design.noilc.plant_operator`, transposed),
``O(N n)``, no lifted matrix. The law is feedforward only, computed between trials (like NOILC's).

The step
--------
On the nominal plant the error map is ``T = I - beta G G^T``: symmetric, eigenvalues ``1 - beta sigma_i^2`` for
the singular values ``sigma_i`` of ``G``. It contracts monotonically (``||T||_2 < 1``) exactly when
``0 < beta < 2 / ||G||_2^2``. The design takes ``beta = STEP_RELATIVE / ||G||_2^2`` with :data:`STEP_RELATIVE`
``= 1``: the middle of that interval. The direction of the largest plant gain is then removed in one trial
(eigenvalue 0), every other contracts by ``1 - sigma_i^2 / ||G||^2 in [0, 1)`` (no overshoot on the nominal plant),
and a plant whose gain is up to twice the nominal one in that direction still contracts. The slowest direction is
the one of the smallest plant gain: gradient ILC is slow where the plant is small, which is NOILC's advantage.
``||G||_2`` is :func:`foilc_hil.design.noilc.plant_norm` (structured, no SVD).

Certificates
------------
Those of NOILC (:func:`foilc_hil.design.noilc.certify_lifted`: dense for short trials, the structured test of the
trial map ``I - beta G_v G^T`` for long ones; its spectral radius also through the similar map
``I - beta G^T G_v``), under the one rule of :mod:`foilc_hil.design.admission`: a step that is not certified
monotonic is rescaled (the recorded ``beta`` and ``step_relative`` are the scaled ones) or refused.

Module order: after :mod:`foilc_hil.design.noilc`, before :mod:`foilc_hil.design.lmi`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from foilc_hil.config import DivergentFilterPolicy, LawKind
from foilc_hil.design.certificate_record import GradientStep, NoilcWeights
from foilc_hil.design.lifted import LawStructure
from foilc_hil.design.models import DiscreteModel, Uncertainty
from foilc_hil.design.noilc import LiftedDesign, LiftedUpdate, certify_lifted, noilc_update, plant_norm, plant_operator
from foilc_hil.design.record import Design
from foilc_hil.design.trial_operator import TrialOperator
from foilc_hil.errors import InputError

__all__ = [
    "STEP_RELATIVE",
    "certify_gradient",
    "gradient_gain",
    "gradient_step",
    "gradient_update",
    "lifted_gain",
    "lifted_update",
]

#: ``beta ||G||_2^2``: 1 is the middle of the monotonic range ``(0, 2)`` (module notes).
STEP_RELATIVE = 1.0


def gradient_step(model: DiscreteModel, n_samples: int, step_relative: float = STEP_RELATIVE) -> GradientStep:
    """``beta = step_relative / ||G||_2^2`` for trials of ``n_samples`` on ``model`` (module notes)."""
    norm = plant_norm(model, n_samples)
    if not norm > 0:
        raise InputError("plant: no input moves the measured output within a trial; gradient ILC cannot learn")
    return GradientStep(beta=step_relative / norm**2, plant_norm=norm, step_relative=step_relative)


def gradient_update(model: DiscreteModel, step: GradientStep, n_samples: int) -> LiftedUpdate:
    """``du = beta G^T e``: the adjoint pass of the plant, scaled (no right factor)."""
    G = plant_operator(model.A, model.B, model.measured_output, n_samples, model.input_delay)
    return LiftedUpdate(G.transpose().scaled(step.beta), TrialOperator.identity(G.length, G.shape[1]))


def gradient_gain(model: DiscreteModel, step: GradientStep, n_samples: int) -> np.ndarray:
    """``L = beta G^T``, ``(L m) x (L p)``: the lifted learning gain, dense."""
    return gradient_update(model, step, n_samples).dense()


def certify_gradient(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    law: LawStructure,
    *,
    require_monotonic: bool,
    policy: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE,
    growth_horizon: int = 10,
) -> Design:
    """The gradient ILC design for ``model``: its step and the certificates of the law as it runs, rescaled or
    refused by the rule of :mod:`foilc_hil.design.admission`."""
    step = gradient_step(model, law.n_samples)
    base = gradient_update(model, step, law.n_samples)

    def scaled(scale: float) -> GradientStep:
        return GradientStep(scale * step.beta, step.plant_norm, scale * step.step_relative)

    lifted = LiftedDesign(
        LawKind.GRADIENT,
        base,
        lambda scale: {"gradient": scaled(scale)},
        policy,
        require_monotonic,
        growth_horizon,
    )
    return certify_lifted(model, uncertainty, lifted, law)


def lifted_update(design: Design, n_samples: int) -> LiftedUpdate | None:
    """The update ``du = L e`` of a NOILC or gradient design for trials of ``n_samples``, rebuilt from the weights
    (and scale) or the step its certificates record; ``None`` for the laws that run per sample (FOILC, IOILC,
    P-type). Shared: a process keeps the last few (a robustness run builds a law per drawn plant from one design)."""
    certificates = design.certificates
    if design.law is LawKind.NOILC and certificates is not None and certificates.noilc is not None:
        return _shared_update(_SameModel(design.model), certificates.noilc, n_samples)
    if design.law is LawKind.GRADIENT and certificates is not None and certificates.gradient is not None:
        return _shared_update(_SameModel(design.model), certificates.gradient, n_samples)
    if design.law in (LawKind.NOILC, LawKind.GRADIENT):
        raise InputError(f"design.certificates: a {design.law} design records its lifted gain's parameters")
    return None


def lifted_gain(design: Design, n_samples: int) -> np.ndarray | None:
    """:func:`lifted_update` as a dense, read-only, shared ``(L m) x (L p)`` matrix (the robustness draws' dense
    maps); ``None`` for the laws that run per sample."""
    update = lifted_update(design, n_samples)
    if update is None:
        return None
    return _shared_gain(update)


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
def _shared_update(model: _SameModel, parameters: NoilcWeights | GradientStep, n_samples: int) -> LiftedUpdate:
    if isinstance(parameters, NoilcWeights):
        return noilc_update(model.model, parameters, n_samples)
    return gradient_update(model.model, parameters, n_samples)


@functools.lru_cache(maxsize=4)
def _shared_gain(update: LiftedUpdate) -> np.ndarray:
    gain = update.dense()
    gain.flags.writeable = False
    return gain
