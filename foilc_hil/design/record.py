"""The learning gain and everything it was designed on: one frozen, JSON-round-trippable record.

A :class:`Design` is what ``foilc-hil synthesize`` prints, what the learning laws (:mod:`foilc_hil.laws.learning`) run
with, and what an MCAP log stores in its ``foilc_hil.design`` metadata record (``replay --verify`` rebuilds the
law from it, so :meth:`Design.from_json` must reproduce :meth:`Design.to_json` exactly).

The law applies, per sample ``t`` of trial ``k`` (paper eq. 21, with ``P = (p1 p2)``)::

    u_k(t) = u_{k-1}(t) + p1 @ (x_k(t) - x_{k-1}(t)) + p2 @ E_{k-1}(t + 1)
    E      = (I + kp D^r) e            (fractional PD function of the tracking error)

Sample alignment is that of :mod:`foilc_hil.references`: ``error[i] = e((i+1) Ts)`` is the first error sample
``u(i)`` can move, so with no input delay the paper's ``E_{k-1}(t+1)`` is ``E_{k-1}[i]``. With ``input_delay = d``
cycles the design model is augmented (:func:`foilc_hil.design.models.augment_input_delay`): the state is
``z = [x; u(t-d); ...; u(t-1)]``, ``C`` is the ``d``-step-ahead output map and ``C_measured = [C_plant 0]``; the law
then uses ``E_{k-1}[i + d]`` (:attr:`Design.error_lead`, zero past the end of the trial), the first error
sample ``u(i)`` can move through the delay.

``gain_scale`` is informational: when the certificate step had to shrink ``p2`` (see
:mod:`foilc_hil.design.certificates`), the stored ``P`` already contains the shrunk ``p2``; ``gain_scale`` records by
how much, so a reader can tell the LMI gain from the gain that runs.

A P-type design (law ``p-type``) is the same record with ``P = (0 Gamma)`` (no state term, ``kp = 0``: the law
learns from ``e`` itself) and no LMI: ``Qb``, ``Qt``, ``gamma``, ``tau`` and ``theta`` are ``None`` (``null`` in
JSON).

The certificates are typed (:class:`Certificates`, :class:`PlantCertificate`, ...); their ``to_json()`` writes
exactly the keys (and key order) of the documents earlier versions wrote, and ``from_json`` reads those documents
back, so logs written before the records were typed still ``replay --verify``.

Module order inside :mod:`foilc_hil.design`: ``models`` < ``fractional``, ``qfilter``, ``ptype`` < ``record`` <
``certificates`` < ``lmi`` < ``tuning`` < ``pipeline`` (each imports only modules to its left).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, TypeVar, cast

import numpy as np

from foilc_hil.config import FractionalMemory, LawKind
from foilc_hil.design.models import DiscreteModel, Uncertainty, ssmatrix
from foilc_hil.errors import InputError

__all__ = [
    "BoundClaim",
    "Bounds",
    "CertificateAction",
    "CertificateMethod",
    "Certificates",
    "CodesignRecord",
    "Design",
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
    "jsonable",
]

_T = TypeVar("_T")

#: Below this margin relative to the LMI matrix's norm (about 1e6 x machine epsilon), LMI (31) is reported to hold
#: only within rounding (:attr:`LmiChecks.within_rounding`).
LMI_RELATIVE_MARGIN_MIN = 1e-10


def _matrix(value: Any, name: str) -> np.ndarray:
    """``value`` as a finite 2-D float array (a copy, read-only); the error names ``design.<name>``."""
    return ssmatrix(value, f"design.{name}", allow_scalar=False)


def _rows(array: np.ndarray) -> list[list[float]]:
    """A matrix as JSON lists of rows (Python floats round-trip exactly through ``json``)."""
    return [[float(x) for x in row] for row in np.asarray(array, dtype=float)]


def jsonable(value: Any) -> Any:
    """Plain JSON values (numpy scalars/arrays converted, non-finite floats as strings, records via ``to_json``)."""
    if hasattr(value, "to_json"):
        return jsonable(value.to_json())
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return number if math.isfinite(number) else str(number)
    return value


# --- reading JSON back --------------------------------------------------------------------------------------------


def _number(document: Mapping[str, Any], key: str, where: str) -> float:
    """A float written by :func:`jsonable` (non-finite values were written as strings such as ``"inf"``)."""
    if key not in document:
        raise InputError(f"{where}.{key}: is required")
    raw = document[key]
    if isinstance(raw, str) and raw in ("inf", "-inf", "nan"):
        return float(raw)
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise InputError(f"{where}.{key}: must be a number")
    return float(raw)


def _optional(document: Mapping[str, Any], key: str, read: Callable[[Any], _T]) -> _T | None:
    return read(document[key]) if key in document and document[key] is not None else None


def _typed(document: Mapping[str, Any], key: str, kind: type[_T], where: str) -> _T:
    if key not in document:
        raise InputError(f"{where}.{key}: is required")
    value = document[key]
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise InputError(f"{where}.{key}: must be a {kind.__name__}")
    return value


def _mapping(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise InputError(f"{where}: must be an object")
    return value


# --- certificates -------------------------------------------------------------------------------------------------


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
        document = _mapping(value, where)
        return cls(_number(document, "spectral_radius", where), _number(document, "norm_2", where))


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
        document = _mapping(value, where)
        try:
            return cls(
                BoundClaim(_typed(document, "norm_2", str, where)),
                BoundClaim(_typed(document, "spectral_radius", str, where)),
                MonotoneVerdict(_typed(document, "monotone", str, where)),
                CertificateMethod(_typed(document, "method", str, where)),
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
        document = _mapping(value, where)
        return cls(
            plant=_typed(document, "plant", str, where),
            map=_typed(document, "map", str, where),
            spectral_radius=_number(document, "spectral_radius", where),
            norm_2=_number(document, "norm_2", where),
            norm_2_method=_typed(document, "norm_2_method", str, where),
            spectral_radius_method=_optional(document, "spectral_radius_method", str),
            norm_2_symbol=_number(document, "norm_2_symbol", where) if "norm_2_symbol" in document else None,
            proof=_optional(document, "proof", Proof.from_json),
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
        document = _mapping(value, where)
        state, inputs, channels, sigmas = (
            tuple(float(x) for x in _typed(document, key, list, where))
            for key in ("state", "inputs", "channels", "sigmas")
        )
        return cls(
            state,
            inputs,
            channels,
            sigmas,
            sigma_bound=_number(document, "sigma_bound", where),
            Q_condition=_number(document, "Q_condition", where),
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
        document = _mapping(value, where)
        numbers = {
            key: _number(document, key, where)
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
            solver=_typed(document, "solver", str, where),
            status=_typed(document, "status", str, where),
            sigmas=tuple(float(s) for s in _typed(document, "sigmas", list, where)),
            vertices_checked=_typed(document, "vertices_checked", int, where),
            solver_failures=tuple(str(f) for f in _typed(document, "solver_failures", list, where)),
            P_lmi=_matrix(document.get("P_lmi"), "certificates.lmi.P_lmi"),
            # additions: absent from documents written before them
            relative_margin=_number(document, "relative_margin", where) if "relative_margin" in document else math.nan,
            Q_condition=_number(document, "Q_condition", where) if "Q_condition" in document else math.nan,
            relative_margin_unscaled=(
                _number(document, "relative_margin_unscaled", where)
                if "relative_margin_unscaled" in document
                else math.nan
            ),
            scaling=_optional(document, "scaling", LmiScaling.from_json),
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
        document = _mapping(value, where)
        q, r, relative = (_number(document, key, where) for key in ("q", "r", "r_relative"))
        return cls(q, r, relative, _number(document, "scale", where) if "scale" in document else 1.0)


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
        document = _mapping(value, where)
        return cls(*(_number(document, key, where) for key in ("beta", "plant_norm", "step_relative")))


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
        document = _mapping(value, where)
        numbers = {key: _number(document, key, where) for key in _CODESIGN_NUMBERS}
        guess = document.get("initial_guess")
        return cls(
            noise_gain=_number(document, "noise_gain", where) if document.get("noise_gain") is not None else None,
            time_varying_norm_2=_number(document, "time_varying_norm_2", where),
            time_varying_samples=_typed(document, "time_varying_samples", int, where),
            time_varying_horizon=_typed(document, "time_varying_horizon", int, where),
            candidates=_typed(document, "candidates", int, where),
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
        document = _mapping(value, where)
        try:
            memory = FractionalMemory(_typed(document, "fractional_memory", str, where))
            action = CertificateAction(_typed(document, "action", str, where))
        except ValueError as exc:
            raise InputError(f"{where}: {exc}") from None
        growth = _optional(document, "growth_bound", lambda v: _mapping(v, f"{where}.growth_bound"))
        seconds = _optional(document, "seconds", lambda v: _mapping(v, f"{where}.seconds"))
        return cls(
            spectral_radius=_number(document, "spectral_radius", where),
            norm_2=_number(document, "norm_2", where),
            monotonic_required=_typed(document, "monotonic_required", bool, where),
            n_samples=_typed(document, "n_samples", int, where),
            lead=_typed(document, "lead", int, where),
            fractional_memory=memory,
            filter_first_weight=_number(document, "filter_first_weight", where),
            naive_without_filter=Bounds.from_json(
                document.get("naive_without_filter"), f"{where}.naive_without_filter"
            ),
            designed=Bounds.from_json(document.get("designed"), f"{where}.designed"),
            vertices=_typed(document, "vertices", int, where),
            q_filter=_typed(document, "q_filter", bool, where),
            action=action,
            gain_scale=_number(document, "gain_scale", where),
            asymptotic=_typed(document, "asymptotic", bool, where),
            monotonic=_typed(document, "monotonic", bool, where),
            plants=tuple(
                PlantCertificate.from_json(entry, f"{where}.plants[{i}]")
                for i, entry in enumerate(_typed(document, "plants", list, where))
            ),
            growth_bound=None
            if growth is None
            else GrowthBound(_typed(growth, "trials", int, where), _number(growth, "bound", where)),
            rescale_criterion=_optional(document, "rescale_criterion", str),
            largest_admissible_scale=(
                _number(document, "largest_admissible_scale", where) if "largest_admissible_scale" in document else None
            ),
            lmi=_optional(document, "lmi", LmiChecks.from_json),
            seconds=None
            if seconds is None
            else Timing(_number(seconds, "lmi", where), _number(seconds, "total", where)),
            p_type=(
                PTypeGain(_matrix(document["gain"], "certificates.gain"), _number(document, "frequency_bound", where))
                if "gain" in document
                else None
            ),
            noilc=_optional(document, "noilc", NoilcWeights.from_json),
            codesign=_optional(document, "codesign", CodesignRecord.from_json),
            gradient=_optional(document, "gradient", GradientStep.from_json),
        )


# --- the design ---------------------------------------------------------------------------------------------------

_LMI_KEYS = ("Qb", "Qt", "gamma", "tau", "theta")


@dataclass(frozen=True)
class Design:
    """A learning gain, the model it was designed on, and its convergence certificates.

    Attributes
    ----------
    law
        :class:`~foilc_hil.config.LawKind`: ``foilc``, ``ioilc`` (``kp = 0``: integer-order law, same 2D
        structure) or ``p-type`` (``P = (0 Gamma)``, no LMI).
    model
        The discrete model ``z(t+1) = A z(t) + B u(t)``, design output ``C``, measured output ``C_measured``,
        including ``input_delay`` augmentation states (:class:`~foilc_hil.design.models.DiscreteModel`).
    uncertainty
        Its norm-bounded uncertainty ``dA = G1 Delta H1``, ``dB = G2 Delta H2``, ``||Delta|| <= 1``.
    P
        The learning gain ``(p1 p2)``, ``m x (n + p)``: the gain that runs (after any certificate rescale).
    kp, r
        The fractional PD function ``E = (I + kp D^r) e``; ``kp = 0`` for IOILC and P-type.
    Qb, Qt, gamma, tau, theta
        The LMI solution of Theorem 1 (Lyapunov blocks, minimised ``gamma``, the weights of
        ``Q(tau, theta) = diag(tau Qb, theta Qt)``); ``None`` for a P-type design.
    gain_scale
        ``1.0`` unless the certificate step rescaled ``p2`` (``P`` holds the rescaled gain).
    certificates
        Convergence certificates of the law as it runs; ``None`` for a design given by hand (tests).
    """

    law: LawKind
    model: DiscreteModel
    uncertainty: Uncertainty
    P: np.ndarray
    kp: float
    r: float
    Qb: np.ndarray | None = None
    Qt: np.ndarray | None = None
    gamma: float | None = None
    tau: float | None = None
    theta: float | None = None
    gain_scale: float = 1.0
    certificates: Certificates | None = None

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "law", LawKind(self.law))
        except ValueError:
            raise InputError(f"design.law: must be one of {', '.join(LawKind)}, got {self.law!r}") from None
        try:
            self.uncertainty.check_against(self.model)
        except InputError as exc:
            raise InputError(f"design: the uncertainty does not fit the model: {exc}") from None
        n, m, p = self.n_states, self.n_inputs, self.n_outputs
        object.__setattr__(self, "P", _matrix(self.P, "P"))
        self._check_shape("P", self.P, (m, n + p))
        lmi = [getattr(self, key) is None for key in _LMI_KEYS]
        if any(lmi) and not all(lmi):
            raise InputError(f"design: {', '.join(_LMI_KEYS)} are given together (an LMI solution) or not at all")
        if not any(lmi):
            assert self.Qb is not None and self.Qt is not None
            object.__setattr__(self, "Qb", _matrix(self.Qb, "Qb"))
            object.__setattr__(self, "Qt", _matrix(self.Qt, "Qt"))
            self._check_shape("Qb", self.Qb, (n, n))
            self._check_shape("Qt", self.Qt, (p, p))
        for name in ("kp", "r", "gain_scale", "gamma", "tau", "theta"):
            value = getattr(self, name)
            if value is None:
                continue
            if not math.isfinite(float(value)):
                raise InputError(f"design.{name}: must be finite")
            object.__setattr__(self, name, float(value))

    @staticmethod
    def _check_shape(name: str, matrix: np.ndarray, shape: tuple[int, int]) -> None:
        if matrix.shape != shape:
            raise InputError(f"design.{name}: must be {shape[0]}x{shape[1]}, got {matrix.shape[0]}x{matrix.shape[1]}")

    # --- the model, delegated -------------------------------------------------------------------------------

    @property
    def A(self) -> np.ndarray:
        """The (augmented) state matrix, ``n x n``."""
        return self.model.A

    @property
    def B(self) -> np.ndarray:
        """The input matrix, ``n x m``."""
        return self.model.B

    @property
    def C(self) -> np.ndarray:
        """The design output map, ``p x n`` (the ``d``-step-ahead output with input delay)."""
        return self.model.C

    @property
    def measured_output(self) -> np.ndarray:
        """``C_measured``, the measured output ``y = C_measured z``."""
        return self.model.measured_output

    @property
    def C_measured(self) -> np.ndarray:
        """Alias of :attr:`measured_output` (the JSON key)."""
        return self.model.measured_output

    @property
    def G1(self) -> np.ndarray:
        """``dA = G1 Delta H1``."""
        return self.uncertainty.G1

    @property
    def H1(self) -> np.ndarray:
        """``dA = G1 Delta H1``."""
        return self.uncertainty.H1

    @property
    def G2(self) -> np.ndarray:
        """``dB = G2 Delta H2``."""
        return self.uncertainty.G2

    @property
    def H2(self) -> np.ndarray:
        """``dB = G2 Delta H2``."""
        return self.uncertainty.H2

    @property
    def sample_time(self) -> float:
        """Seconds per sample."""
        return self.model.sample_time

    @property
    def input_delay(self) -> int:
        """Cycles of input transport delay folded into the model (0 offline, 1 over CAN)."""
        return self.model.input_delay

    @property
    def n_states(self) -> int:
        """``n``, the states of the (augmented) design model."""
        return self.model.n_states

    @property
    def n_inputs(self) -> int:
        """``m``, the plant inputs."""
        return self.model.n_inputs

    @property
    def n_outputs(self) -> int:
        """``p``, the plant outputs."""
        return self.model.n_outputs

    # --- gain blocks ----------------------------------------------------------------------------------------

    @property
    def p1(self) -> np.ndarray:
        """The state-difference gain, ``m x n`` (zero for P-type)."""
        return self.P[:, : self.n_states]

    @property
    def p2(self) -> np.ndarray:
        """The error gain (acting on ``E_{k-1}(t+1)``), ``m x p`` (``Gamma`` for P-type)."""
        return self.P[:, self.n_states :]

    @property
    def error_lead(self) -> int:
        """Extra samples of lead on the error: the law uses ``E_{k-1}[i + error_lead]`` (``= input_delay``)."""
        return self.input_delay

    # --- JSON -----------------------------------------------------------------------------------------------

    def to_json(self) -> dict[str, Any]:
        """The interface document of ``synthesize --json`` (matrices as lists of rows), plus ``law``,
        ``input_delay``, ``gain_scale``, ``p1``, ``p2`` and ``C_measured``; no LMI values (``null``) for P-type."""
        document: dict[str, Any] = {name: _rows(getattr(self, name)) for name in ("A", "B", "C")}
        document.update({name: _rows(getattr(self, name)) for name in ("G1", "H1", "G2", "H2", "P")})
        document.update(
            {name: None if getattr(self, name) is None else _rows(getattr(self, name)) for name in ("Qb", "Qt")}
        )
        document.update(
            {
                "gamma": self.gamma,
                "tau": self.tau,
                "theta": self.theta,
                "kp": self.kp,
                "r": self.r,
                "sample_time": self.sample_time,
                "certificates": {} if self.certificates is None else self.certificates.to_json(),
                "law": str(self.law),
                "input_delay": self.input_delay,
                "gain_scale": self.gain_scale,
                "p1": _rows(self.p1),
                "p2": _rows(self.p2),
                "C_measured": _rows(self.measured_output),
            }
        )
        return document

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> Design:
        """Rebuild a design from :meth:`to_json` output (exact round trip; also documents of earlier versions).

        Raises
        ------
        foilc_hil.errors.InputError
            Naming the missing or malformed key.
        """
        if not isinstance(document, Mapping):
            raise InputError("design: must be a JSON object")
        for key in ("A", "B", "C", "G1", "H1", "G2", "H2", "P", *_LMI_KEYS, "kp", "r", "sample_time"):
            if key not in document:
                raise InputError(f"design.{key}: is required")
        delay = document.get("input_delay", 0)
        if isinstance(delay, bool) or not isinstance(delay, int):
            raise InputError("design.input_delay: must be an integer")
        if delay and "C_measured" not in document:
            raise InputError("design.C_measured: is required when input_delay > 0")
        model = DiscreteModel(
            _matrix(document["A"], "A"),
            _matrix(document["B"], "B"),
            _matrix(document["C"], "C"),
            _number(document, "sample_time", "design"),
            input_delay=delay,
            C_measured=_matrix(document["C_measured"], "C_measured") if "C_measured" in document else None,
        )
        G1, H1, G2, H2 = (_matrix(document[key], key) for key in ("G1", "H1", "G2", "H2"))
        uncertainty = Uncertainty(G1, H1, G2, H2)
        certificates = _mapping(document.get("certificates", {}), "design.certificates")
        lmi_absent = document["Qb"] is None
        return cls(
            law=cast(LawKind, document.get("law", "foilc")),  # validated by __post_init__
            model=model,
            uncertainty=uncertainty,
            P=_matrix(document["P"], "P"),
            kp=_number(document, "kp", "design"),
            r=_number(document, "r", "design"),
            Qb=None if lmi_absent else _matrix(document["Qb"], "Qb"),
            Qt=None if lmi_absent else _matrix(document["Qt"], "Qt"),
            gamma=None if lmi_absent else _number(document, "gamma", "design"),
            tau=None if lmi_absent else _number(document, "tau", "design"),
            theta=None if lmi_absent else _number(document, "theta", "design"),
            gain_scale=_number(document, "gain_scale", "design") if "gain_scale" in document else 1.0,
            certificates=Certificates.from_json(certificates) if certificates else None,
        )
