"""The typed certificates of a design: what :mod:`foilc_hil.design.certificates` (and the LMI, the co-design,
NOILC, gradient ILC and P-type) prove about the law as it runs, as frozen records with their JSON.

:class:`Certificates` is the ``certificates`` document of a :class:`~foilc_hil.design.record.Design`, one
:class:`PlantCertificate` per plant (nominal and each uncertainty vertex), with :class:`Proof` saying what each
number is; :class:`LmiChecks`, :class:`CodesignRecord`, :class:`NoilcWeights`, :class:`GradientStep` and
:class:`PTypeGain` are what each way of designing adds. Their ``to_json()`` writes exactly the keys (and key order)
of the documents earlier versions wrote, and ``from_json`` reads those documents back, so logs written before the
records were typed still ``replay --verify``.

Module order: after :mod:`foilc_hil.design.json_fields`, before :mod:`foilc_hil.design.record`.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np

from foilc_hil.config import FractionalMemory
from foilc_hil.design.json_fields import (
    jsonable,
    read_mapping,
    read_matrix,
    read_number,
    read_optional,
    read_typed,
)
from foilc_hil.errors import InputError

__all__ = [
    "LMI_RELATIVE_MARGIN_MIN",
    "BoundClaim",
    "Bounds",
    "CertificateAction",
    "CertificateMethod",
    "Certificates",
    "CodesignRecord",
    "GradientStep",
    "GrowthBound",
    "LmiChecks",
    "LmiScaling",
    "MonotoneVerdict",
    "NoilcWeights",
    "PTypeGain",
    "PlantCertificate",
    "Proof",
    "Timing",
]


#: Below this margin relative to the LMI matrix's norm (about 1e6 x machine epsilon), LMI (31) is reported to hold
#: only within rounding (:attr:`LmiChecks.within_rounding`).
LMI_RELATIVE_MARGIN_MIN = 1e-10


@enum.unique
class CertificateAction(StrEnum):
    """What the certificate step did to the LMI gain."""

    NONE = "none"
    RESCALE = "rescale"
    CODESIGN = "codesign"


@dataclass(frozen=True)
class Bounds:
    """Worst case over the plants of the spectral radius and induced 2-norm of the lifted trial map."""

    spectral_radius: float
    norm_2: float

    def to_json(self) -> dict[str, Any]:
        """``{"spectral_radius", "norm_2"}``."""
        return {"spectral_radius": self.spectral_radius, "norm_2": self.norm_2}

    @classmethod
    def from_json(cls, value: Any, where: str) -> Bounds:
        """Read :meth:`to_json` output."""
        document = read_mapping(value, where)
        return cls(read_number(document, "spectral_radius", where), read_number(document, "norm_2", where))


@enum.unique
class BoundClaim(StrEnum):
    """What a certificate's number is: a rigorous bound from above or below, or the exact value (to a stated
    tolerance)."""

    UPPER = "upper bound"
    LOWER = "lower bound"
    EXACT = "exact"


@enum.unique
class CertificateMethod(StrEnum):
    """How a certificate was computed (:mod:`foilc_hil.design.qmap`)."""

    SYMBOL = "symbol + finite-length correction"
    STRUCTURED = "structured exact"
    DENSE = "dense"


@enum.unique
class MonotoneVerdict(StrEnum):
    """Whether the map is certified monotone (``norm_2`` at most the contraction limit), certified not monotone
    (a lower bound or the exact value at or above it), or neither within the time allowed."""

    MONOTONE = "monotone"
    NOT_MONOTONE = "not monotone"
    INCONCLUSIVE = "inconclusive"


@dataclass(frozen=True)
class Proof:
    """What one plant's certificate proves and how (an addition: absent from earlier documents)."""

    norm_2: BoundClaim
    spectral_radius: BoundClaim
    monotone: MonotoneVerdict
    method: CertificateMethod

    def to_json(self) -> dict[str, Any]:
        """``{"norm_2", "spectral_radius", "monotone", "method"}``."""
        return {
            "norm_2": str(self.norm_2),
            "spectral_radius": str(self.spectral_radius),
            "monotone": str(self.monotone),
            "method": str(self.method),
        }

    @classmethod
    def from_json(cls, value: Any) -> Proof:
        """Read :meth:`to_json` output."""
        where = "design.certificates.plants[].proof"
        document = read_mapping(value, where)
        try:
            return cls(
                BoundClaim(read_typed(document, "norm_2", str, where)),
                BoundClaim(read_typed(document, "spectral_radius", str, where)),
                MonotoneVerdict(read_typed(document, "monotone", str, where)),
                CertificateMethod(read_typed(document, "method", str, where)),
            )
        except ValueError as exc:
            raise InputError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class PlantCertificate:
    """The lifted trial map of one plant (nominal or an uncertainty vertex): see
    :func:`foilc_hil.design.certificates.map_certificate`.

    ``map`` is ``"error"`` (no Q-filter) or ``"input (Q-filter)"``; ``spectral_radius_method`` is given for the
    input map only, ``norm_2_symbol`` for the error map's Toeplitz path only. ``proof`` (the Q-filtered input map
    of :mod:`foilc_hil.design.qmap`) says what ``norm_2`` and ``spectral_radius`` are (upper or lower bounds, or
    exact), whether the map is certified monotone, not monotone or neither, and by which method.
    """

    plant: str
    map: str
    spectral_radius: float
    norm_2: float
    norm_2_method: str
    spectral_radius_method: str | None = None
    norm_2_symbol: float | None = None
    proof: Proof | None = None

    def named(self, plant: str) -> PlantCertificate:
        """The same certificate for the plant called ``plant``."""
        return PlantCertificate(
            plant,
            self.map,
            self.spectral_radius,
            self.norm_2,
            self.norm_2_method,
            self.spectral_radius_method,
            self.norm_2_symbol,
            self.proof,
        )

    def to_json(self) -> dict[str, Any]:
        """The entry of ``certificates["plants"]`` (keys in the order earlier versions wrote them)."""
        document: dict[str, Any] = {"plant": self.plant, "map": self.map}
        if self.spectral_radius_method is not None:
            document["spectral_radius_method"] = self.spectral_radius_method
        document.update(
            {"spectral_radius": self.spectral_radius, "norm_2": self.norm_2, "norm_2_method": self.norm_2_method}
        )
        if self.norm_2_symbol is not None:
            document["norm_2_symbol"] = self.norm_2_symbol
        if self.proof is not None:  # an addition (docs/interface-additions.md)
            document["proof"] = self.proof.to_json()
        return document

    @classmethod
    def from_json(cls, value: Any, where: str) -> PlantCertificate:
        """Read :meth:`to_json` output."""
        document = read_mapping(value, where)
        return cls(
            plant=read_typed(document, "plant", str, where),
            map=read_typed(document, "map", str, where),
            spectral_radius=read_number(document, "spectral_radius", where),
            norm_2=read_number(document, "norm_2", where),
            norm_2_method=read_typed(document, "norm_2_method", str, where),
            spectral_radius_method=read_optional(document, "spectral_radius_method", str),
            norm_2_symbol=read_number(document, "norm_2_symbol", where) if "norm_2_symbol" in document else None,
            proof=read_optional(document, "proof", Proof.from_json),
        )


@dataclass(frozen=True)
class GrowthBound:
    """``||T||_2^trials``: how much the error's l2 norm can grow when only asymptotic convergence is certified."""

    trials: int
    bound: float

    def to_json(self) -> dict[str, Any]:
        """``{"trials", "bound"}``."""
        return {"trials": self.trials, "bound": self.bound}


@dataclass(frozen=True)
class LmiScaling:
    """The scaled coordinates LMI (31) was solved in (:class:`foilc_hil.design.lmi.Scaling`): the diagonal factors
    (powers of two), the multipliers as solved and their upper bound, and the condition number of the scaled
    ``Qs = T^-1 Q T^-1`` (``LmiChecks.Q_condition`` is the original ``Q``'s)."""

    state: tuple[float, ...]
    inputs: tuple[float, ...]
    channels: tuple[float, ...]
    sigmas: tuple[float, ...]
    sigma_bound: float
    Q_condition: float

    def to_json(self) -> dict[str, Any]:
        """``certificates["lmi"]["scaling"]``."""
        return {
            "state": list(self.state),
            "inputs": list(self.inputs),
            "channels": list(self.channels),
            "sigmas": list(self.sigmas),
            "sigma_bound": self.sigma_bound,
            "Q_condition": self.Q_condition,
        }

    @classmethod
    def from_json(cls, value: Any) -> LmiScaling:
        """Read :meth:`to_json` output."""
        where = "design.certificates.lmi.scaling"
        document = read_mapping(value, where)
        state, inputs, channels, sigmas = (
            tuple(float(x) for x in read_typed(document, key, list, where))
            for key in ("state", "inputs", "channels", "sigmas")
        )
        return cls(
            state,
            inputs,
            channels,
            sigmas,
            sigma_bound=read_number(document, "sigma_bound", where),
            Q_condition=read_number(document, "Q_condition", where),
        )


@dataclass(frozen=True)
class LmiChecks:
    """How LMI (31) was solved and the independent numpy checks of its solution (:mod:`foilc_hil.design.lmi`)."""

    solver: str
    status: str
    sigmas: tuple[float, ...]
    lmi_max_eigenvalue: float
    Qb_min_eigenvalue: float
    Qt_min_eigenvalue: float
    lyapunov_max_eigenvalue: float
    time_radius: float
    trial_radius: float
    vertices_checked: int
    solver_failures: tuple[str, ...]
    P_lmi: np.ndarray
    relative_margin: float = math.nan
    Q_condition: float = math.nan
    relative_margin_unscaled: float = math.nan
    scaling: LmiScaling | None = None

    @property
    def within_rounding(self) -> bool:
        """Whether the LMI holds only by a margin comparable to rounding (:data:`LMI_RELATIVE_MARGIN_MIN`): its
        feasibility and ``gamma`` are then solver noise, and the Lyapunov and vertex checks are what certify."""
        return not self.relative_margin >= LMI_RELATIVE_MARGIN_MIN

    def to_json(self) -> dict[str, Any]:
        """``certificates["lmi"]``."""
        return {
            "solver": self.solver,
            "status": self.status,
            "sigmas": list(self.sigmas),
            "lmi_max_eigenvalue": self.lmi_max_eigenvalue,
            "Qb_min_eigenvalue": self.Qb_min_eigenvalue,
            "Qt_min_eigenvalue": self.Qt_min_eigenvalue,
            "lyapunov_max_eigenvalue": self.lyapunov_max_eigenvalue,
            "time_radius": self.time_radius,
            "trial_radius": self.trial_radius,
            "vertices_checked": self.vertices_checked,
            "solver_failures": list(self.solver_failures),
            "P_lmi": self.P_lmi,
            "relative_margin": self.relative_margin,
            "Q_condition": self.Q_condition,
            # additions (docs/interface-additions.md): the scaled problem
            "relative_margin_unscaled": self.relative_margin_unscaled,
            "scaling": None if self.scaling is None else self.scaling.to_json(),
        }

    @classmethod
    def from_json(cls, value: Any) -> LmiChecks:
        """Read :meth:`to_json` output."""
        where = "design.certificates.lmi"
        document = read_mapping(value, where)
        numbers = {
            key: read_number(document, key, where)
            for key in (
                "lmi_max_eigenvalue",
                "Qb_min_eigenvalue",
                "Qt_min_eigenvalue",
                "lyapunov_max_eigenvalue",
                "time_radius",
                "trial_radius",
            )
        }
        return cls(
            solver=read_typed(document, "solver", str, where),
            status=read_typed(document, "status", str, where),
            sigmas=tuple(float(s) for s in read_typed(document, "sigmas", list, where)),
            vertices_checked=read_typed(document, "vertices_checked", int, where),
            solver_failures=tuple(str(f) for f in read_typed(document, "solver_failures", list, where)),
            P_lmi=read_matrix(document.get("P_lmi"), "certificates.lmi.P_lmi"),
            # additions: absent from documents written before them
            relative_margin=(
                read_number(document, "relative_margin", where) if "relative_margin" in document else math.nan
            ),
            Q_condition=read_number(document, "Q_condition", where) if "Q_condition" in document else math.nan,
            relative_margin_unscaled=(
                read_number(document, "relative_margin_unscaled", where)
                if "relative_margin_unscaled" in document
                else math.nan
            ),
            scaling=read_optional(document, "scaling", LmiScaling.from_json),
            **numbers,
        )


@dataclass(frozen=True)
class Timing:
    """Wall-clock seconds of the LMI solve and of the whole synthesis (informational)."""

    lmi: float
    total: float

    def to_json(self) -> dict[str, Any]:
        """``{"lmi", "total"}``."""
        return {"lmi": self.lmi, "total": self.total}


@dataclass(frozen=True)
class PTypeGain:
    """What a P-type design adds to its certificates: the Arimoto gain and its frequency-domain bound."""

    gain: np.ndarray
    frequency_bound: float

    def to_json(self) -> dict[str, Any]:
        """``{"gain", "frequency_bound"}`` (the keys ``simulate --law p-type`` always reported)."""
        return {"gain": self.gain, "frequency_bound": self.frequency_bound}


@dataclass(frozen=True)
class NoilcWeights:
    """What a norm-optimal ILC design adds to its certificates: its weights ``Q = q I``, ``R = r I`` (absolute;
    ``r = r_relative ||G||_2^2 q``), from which the law rebuilds its lifted gain exactly, and the ``scale`` its
    update runs at (``u_k = u_(k-1) + scale L e_(k-1)``: below 1 only when the certificate step had to shrink it,
    :func:`foilc_hil.design.noilc.certify_noilc`; written only then, so earlier documents read back unchanged)."""

    q: float
    r: float
    r_relative: float
    scale: float = 1.0

    def to_json(self) -> dict[str, Any]:
        """``certificates["noilc"]``: ``{"q", "r", "r_relative"}``, and ``"scale"`` when it is not 1."""
        document = {"q": self.q, "r": self.r, "r_relative": self.r_relative}
        if self.scale != 1.0:
            document["scale"] = self.scale
        return document

    @classmethod
    def from_json(cls, value: Any) -> NoilcWeights:
        """Read :meth:`to_json` output."""
        where = "design.certificates.noilc"
        document = read_mapping(value, where)
        q, r, relative = (read_number(document, key, where) for key in ("q", "r", "r_relative"))
        return cls(q, r, relative, read_number(document, "scale", where) if "scale" in document else 1.0)


@dataclass(frozen=True)
class GradientStep:
    """What a gradient ILC design adds to its certificates: the step ``beta`` of ``u_k = u_{k-1} + beta G^T e``
    and the plant norm ``||G||_2`` it was chosen from (``beta = step_relative / ||G||_2^2``), from which the law
    rebuilds its lifted gain exactly."""

    beta: float
    plant_norm: float
    step_relative: float

    def to_json(self) -> dict[str, Any]:
        """``certificates["gradient"]``: ``{"beta", "plant_norm", "step_relative"}``."""
        return {"beta": self.beta, "plant_norm": self.plant_norm, "step_relative": self.step_relative}

    @classmethod
    def from_json(cls, value: Any) -> GradientStep:
        """Read :meth:`to_json` output."""
        where = "design.certificates.gradient"
        document = read_mapping(value, where)
        return cls(*(read_number(document, key, where) for key in ("beta", "plant_norm", "step_relative")))


_CODESIGN_NUMBERS = (
    "objective",
    "noise_weight",
    "gain",
    "state_gain",
    "symbol_norm",
    "ioilc_objective",
    "ioilc_norm_2",
)


@dataclass(frozen=True)
class CodesignRecord:
    """How the co-design chose ``kp``, ``r`` and the scale of ``p2`` (:mod:`foilc_hil.design.codesign`).

    Attributes
    ----------
    objective
        The chosen point's objective: ``max(certified worst-case 2-norm, sampled time-varying 2-norm) +
        noise_weight * noise_gain``.
    noise_weight, noise_gain
        The weight and the chosen point's noise gain (``None`` when not computed: several outputs).
    gain, state_gain
        The scales applied to the LMI's ``p2`` (before any certificate rescale) and ``p1``.
    symbol_norm
        The search's surrogate at the chosen point: worst over the frozen plants of the long-trial symbol norm.
    time_varying_norm_2, time_varying_samples, time_varying_horizon
        Worst induced 2-norm over seeded draws of a time-varying ``Delta(t)`` on a trial shortened to the horizon
        (a sampled check, not a proof); ``nan`` without draws.
    ioilc_objective, ioilc_norm_2
        The same objective and certified 2-norm at ``kp = 0`` with the LMI gain: IOILC's design, always a
        candidate, so ``objective <= ioilc_objective``.
    candidates
        Points the search covered: every grid point (evaluated, or ruled out by a lower bound), the Nelder–Mead
        evaluations and the finalists (certified, or ruled out by a lower bound).
    initial_guess
        ``(kp, r)`` from ``tuning`` (the tuner or the given values) the search started from, if any.
    """

    objective: float
    noise_weight: float
    noise_gain: float | None
    gain: float
    state_gain: float
    symbol_norm: float
    time_varying_norm_2: float
    time_varying_samples: int
    time_varying_horizon: int
    ioilc_objective: float
    ioilc_norm_2: float
    candidates: int
    initial_guess: tuple[float, float] | None

    def to_json(self) -> dict[str, Any]:
        """``certificates["codesign"]``."""
        document: dict[str, Any] = {key: getattr(self, key) for key in _CODESIGN_NUMBERS}
        document.update(
            {
                "noise_gain": self.noise_gain,
                "time_varying_norm_2": self.time_varying_norm_2,
                "time_varying_samples": self.time_varying_samples,
                "time_varying_horizon": self.time_varying_horizon,
                "candidates": self.candidates,
                "initial_guess": None if self.initial_guess is None else list(self.initial_guess),
            }
        )
        return dict(jsonable(document))

    @classmethod
    def from_json(cls, value: Any) -> CodesignRecord:
        """Read :meth:`to_json` output."""
        where = "design.certificates.codesign"
        document = read_mapping(value, where)
        numbers = {key: read_number(document, key, where) for key in _CODESIGN_NUMBERS}
        guess = document.get("initial_guess")
        return cls(
            noise_gain=read_number(document, "noise_gain", where) if document.get("noise_gain") is not None else None,
            time_varying_norm_2=read_number(document, "time_varying_norm_2", where),
            time_varying_samples=read_typed(document, "time_varying_samples", int, where),
            time_varying_horizon=read_typed(document, "time_varying_horizon", int, where),
            candidates=read_typed(document, "candidates", int, where),
            initial_guess=None if guess is None else (float(guess[0]), float(guess[1])),
            **numbers,
        )


@dataclass(frozen=True)
class Certificates:
    """Convergence certificates of the law as it runs (:func:`foilc_hil.design.certificates.certify`), plus the
    LMI record and timing of a synthesis, or the gain of a P-type design.

    The worst case over the plants of the accepted gain is ``spectral_radius``/``norm_2``; ``designed`` is the
    LMI gain before any rescale, ``naive_without_filter`` that gain with the fractional filter and Q-filter off.
    """

    spectral_radius: float
    norm_2: float
    monotonic_required: bool
    n_samples: int
    lead: int
    fractional_memory: FractionalMemory
    filter_first_weight: float
    naive_without_filter: Bounds
    designed: Bounds
    vertices: int
    q_filter: bool
    action: CertificateAction
    gain_scale: float
    asymptotic: bool
    monotonic: bool
    plants: tuple[PlantCertificate, ...]
    growth_bound: GrowthBound | None = None
    rescale_criterion: str | None = None
    largest_admissible_scale: float | None = None
    lmi: LmiChecks | None = None
    seconds: Timing | None = None
    p_type: PTypeGain | None = None
    noilc: NoilcWeights | None = None
    codesign: CodesignRecord | None = None
    gradient: GradientStep | None = None

    def to_json(self) -> dict[str, Any]:
        """The ``certificates`` document: exactly the keys, in the order, of the documents earlier versions wrote
        (the P-type ``gain``/``frequency_bound`` last). Non-finite numbers are written as strings."""
        document: dict[str, Any] = {
            "spectral_radius": self.spectral_radius,
            "norm_2": self.norm_2,
            "monotonic_required": self.monotonic_required,
            "n_samples": self.n_samples,
            "lead": self.lead,
            "fractional_memory": str(self.fractional_memory),
            "filter_first_weight": self.filter_first_weight,
            "naive_without_filter": self.naive_without_filter.to_json(),
            "designed": self.designed.to_json(),
            "vertices": self.vertices,
            "q_filter": self.q_filter,
        }
        if self.growth_bound is not None:
            document["growth_bound"] = self.growth_bound.to_json()
        document["action"] = str(self.action)
        if self.rescale_criterion is not None:
            document["rescale_criterion"] = self.rescale_criterion
        document["gain_scale"] = self.gain_scale
        if self.largest_admissible_scale is not None:
            document["largest_admissible_scale"] = self.largest_admissible_scale
        document.update(
            {"asymptotic": self.asymptotic, "monotonic": self.monotonic, "plants": [p.to_json() for p in self.plants]}
        )
        for key, record in (("lmi", self.lmi), ("seconds", self.seconds)):
            if record is not None:
                document[key] = record.to_json()
        if self.p_type is not None:
            document.update(self.p_type.to_json())
        for key, addition in (("noilc", self.noilc), ("codesign", self.codesign), ("gradient", self.gradient)):
            if addition is not None:  # additions (docs/interface-additions.md): absent from earlier documents
                document[key] = addition.to_json()
        return dict(jsonable(document))

    @classmethod
    def from_json(cls, value: Any) -> Certificates:
        """Read :meth:`to_json` output (also the untyped documents earlier versions wrote: same keys)."""
        where = "design.certificates"
        document = read_mapping(value, where)
        try:
            memory = FractionalMemory(read_typed(document, "fractional_memory", str, where))
            action = CertificateAction(read_typed(document, "action", str, where))
        except ValueError as exc:
            raise InputError(f"{where}: {exc}") from None
        growth = read_optional(document, "growth_bound", lambda v: read_mapping(v, f"{where}.growth_bound"))
        seconds = read_optional(document, "seconds", lambda v: read_mapping(v, f"{where}.seconds"))
        return cls(
            spectral_radius=read_number(document, "spectral_radius", where),
            norm_2=read_number(document, "norm_2", where),
            monotonic_required=read_typed(document, "monotonic_required", bool, where),
            n_samples=read_typed(document, "n_samples", int, where),
            lead=read_typed(document, "lead", int, where),
            fractional_memory=memory,
            filter_first_weight=read_number(document, "filter_first_weight", where),
            naive_without_filter=Bounds.from_json(
                document.get("naive_without_filter"), f"{where}.naive_without_filter"
            ),
            designed=Bounds.from_json(document.get("designed"), f"{where}.designed"),
            vertices=read_typed(document, "vertices", int, where),
            q_filter=read_typed(document, "q_filter", bool, where),
            action=action,
            gain_scale=read_number(document, "gain_scale", where),
            asymptotic=read_typed(document, "asymptotic", bool, where),
            monotonic=read_typed(document, "monotonic", bool, where),
            plants=tuple(
                PlantCertificate.from_json(entry, f"{where}.plants[{i}]")
                for i, entry in enumerate(read_typed(document, "plants", list, where))
            ),
            growth_bound=None
            if growth is None
            else GrowthBound(read_typed(growth, "trials", int, where), read_number(growth, "bound", where)),
            rescale_criterion=read_optional(document, "rescale_criterion", str),
            largest_admissible_scale=(
                read_number(document, "largest_admissible_scale", where)
                if "largest_admissible_scale" in document
                else None
            ),
            lmi=read_optional(document, "lmi", LmiChecks.from_json),
            seconds=None
            if seconds is None
            else Timing(read_number(seconds, "lmi", where), read_number(seconds, "total", where)),
            p_type=(
                PTypeGain(
                    read_matrix(document["gain"], "certificates.gain"), read_number(document, "frequency_bound", where)
                )
                if "gain" in document
                else None
            ),
            noilc=read_optional(document, "noilc", NoilcWeights.from_json),
            codesign=read_optional(document, "codesign", CodesignRecord.from_json),
            gradient=read_optional(document, "gradient", GradientStep.from_json),
        )
