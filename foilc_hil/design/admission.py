"""One rule for every law: a design not certified as required is rescaled or refused, never handed out as it is.

FOILC and IOILC get the rule from :func:`foilc_hil.design.certificates.certify` (their ``p2`` is rescaled). The laws
whose gain is chosen without the certificates -- P-type (``Gamma``), norm-optimal ILC (its update ``L``) and
gradient ILC (its step) -- get it here, with the same settings:

* ``synthesis.require_monotonic: true`` (the default): the design must be certified MONOTONIC (the worst-case
  induced 2-norm of the trial map, nominal and at the uncertainty vertices, at most
  :data:`~foilc_hil.design.map_norms.CONTRACTION_LIMIT`); ``false``: asymptotic convergence (the worst-case
  spectral radius below one) is enough.
* ``synthesis.on_divergent_filter`` says what happens to a design that is not: ``refuse`` (and ``augment``, not
  implemented) raise :class:`~foilc_hil.errors.ConvergenceCertificateError` (exit 3, one line with the bound);
  ``rescale`` (the default) scales the learning gain by ``s`` in ``(0, 1]``. The worst-case 2-norm of ``I - s K``
  is convex in ``s`` and 1 at ``s = 0``, so the ``s`` minimising it (bounded Brent search on ``log s``) is the
  fastest certified contraction; when even that is not certified, the rule refuses (or, when only asymptotic
  convergence is required, takes the ``s`` minimising the worst-case spectral radius, and refuses if that is not
  below one either).

What is scaled is each law's own: P-type's ``Gamma`` and gradient ILC's step ``beta`` (the scaled value is the
recorded one), norm-optimal ILC's whole update ``s L`` (recorded as ``certificates.noilc.scale``).

Module order: after :mod:`foilc_hil.design.certificates` (whose contraction limit it applies), before
:mod:`foilc_hil.design.noilc`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from foilc_hil.config import DivergentFilterPolicy
from foilc_hil.design.certificate_record import CertificateAction, GrowthBound
from foilc_hil.design.certificates import ScaledVerdict
from foilc_hil.errors import ConvergenceCertificateError

__all__ = ["Admission", "admit"]

#: The smallest gain scale the search considers.
SMALLEST_SCALE = 1e-3
#: Width of the search's final bracket, in ``log s`` (5 % of the scale: the worst-case norm is flat at its minimum).
SCALE_TOLERANCE = 0.05
#: Scales tried, relative to the estimated minimum, when that one is not certified (:func:`_search`).
BACKOFF = (0.9, 0.75, 1.1, 0.5, 1.3, 0.25, 0.1)


@dataclass(frozen=True)
class Admission:
    """What :func:`admit` decided: the verdict that runs, what was done and, for an asymptotic-only rescale, the
    growth bound ``||T||_2^trials``."""

    verdict: ScaledVerdict
    action: CertificateAction
    criterion: str | None
    growth_bound: GrowthBound | None


def _summary(law: str, verdict: ScaledVerdict) -> str:
    methods = sorted({entry.norm_2_method for entry in verdict.plants})
    return (
        f"{law}: worst-case induced 2-norm {verdict.norm_2:.6g}, spectral radius {verdict.spectral_radius:.6g} "
        f"over {len(verdict.plants)} plants ({'; '.join(methods)})"
    )


def _search(
    evaluate: Callable[[float], ScaledVerdict], key: str, estimate: Callable[[float], ScaledVerdict] | None
) -> ScaledVerdict:
    """The scale in ``[SMALLEST_SCALE, 1]`` minimising the worst-case ``key`` (bounded Brent on ``log s``; on the
    cheap ``estimate`` when there is one), certified by ``evaluate``."""
    from scipy.optimize import minimize_scalar

    probe = evaluate if estimate is None else estimate

    def objective(log_scale: float) -> float:
        value = float(getattr(probe(math.exp(log_scale)), key))
        return value if math.isfinite(value) else 1e300

    found = minimize_scalar(
        objective, bounds=(math.log(SMALLEST_SCALE), 0.0), method="bounded", options={"xatol": SCALE_TOLERANCE}
    )
    scale = math.exp(float(found.x))
    best = evaluate(scale)
    if estimate is None or _passes(best, key):
        return best
    # The estimate's minimum missed the certified set (the estimates are biased low by up to about 1e-3, and the
    # worst-case norm can rise steeply past its minimum: gradient ILC's does). The set is an interval of scales
    # (the norm is convex in s), so look on either side, nearest first, certified every time.
    for factor in BACKOFF:
        candidate = evaluate(min(1.0, max(SMALLEST_SCALE, scale * factor)))
        if _passes(candidate, key):
            return candidate
        best = min(best, candidate, key=lambda verdict: float(getattr(verdict, key)))
    return best


def _passes(verdict: ScaledVerdict, key: str) -> bool:
    """Whether ``verdict`` meets what a search on ``key`` looks for (monotonic for the norm, else asymptotic)."""
    return verdict.monotonic if key == "norm_2" else verdict.asymptotic


def admit(
    evaluate: Callable[[float], ScaledVerdict],
    *,
    law: str,
    policy: DivergentFilterPolicy,
    require_monotonic: bool,
    growth_horizon: int,
    estimate: Callable[[float], ScaledVerdict] | None = None,
) -> Admission:
    """Apply the rule (module notes) to the certificates ``evaluate(s)`` of the gain scaled by ``s``.

    ``estimate(s)``: cheaper numbers of the same maps (lower bounds of their norms, say) for the search of the
    scale; the scale it finds is then certified by ``evaluate`` like any other.

    Raises
    ------
    foilc_hil.errors.ConvergenceCertificateError
        When the design is not certified as required and the policy or no scale fixes it (exit 3).
    foilc_hil.errors.ConfigError
        For an unknown policy (``synthesis.on_divergent_filter``).
    """
    policy = DivergentFilterPolicy.parse(policy)
    designed = evaluate(1.0)
    if designed.admissible(require_monotonic):
        return Admission(designed, CertificateAction.NONE, None, None)
    wanted = "monotonically" if require_monotonic else "asymptotically"
    head = f"the law as it runs is not certified to converge {wanted}: {_summary(law, designed)}"
    if policy is DivergentFilterPolicy.REFUSE:
        raise ConvergenceCertificateError(f"{head}; synthesis.on_divergent_filter=refuse")
    if policy is DivergentFilterPolicy.AUGMENT:
        raise ConvergenceCertificateError(
            f"{head}; 'augment' is not implemented, use synthesis.on_divergent_filter=rescale"
        )
    best = _search(evaluate, "norm_2", estimate)
    if best.monotonic:
        return Admission(best, CertificateAction.RESCALE, "monotonic", None)
    if require_monotonic:
        raise ConvergenceCertificateError(
            f"{head}; no scale of the learning gain in [{SMALLEST_SCALE:g}, 1] gives a certified induced 2-norm "
            f"below 1 (best {best.norm_2:.6g} at scale {best.scale:.4g})"
        )
    best = _search(evaluate, "spectral_radius", estimate)
    if not best.asymptotic:
        raise ConvergenceCertificateError(
            f"{head}; no scale of the learning gain in [{SMALLEST_SCALE:g}, 1] gives a certified spectral radius "
            f"below 1 (best {best.spectral_radius:.6g} at scale {best.scale:.4g})"
        )
    growth = GrowthBound(growth_horizon, best.norm_2**growth_horizon)
    return Admission(best, CertificateAction.RESCALE, "asymptotic", growth)
