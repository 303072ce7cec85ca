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

The certificates are typed (:class:`~foilc_hil.design.certificate_record.Certificates`, one
:class:`~foilc_hil.design.certificate_record.PlantCertificate` per plant, ...:
:mod:`foilc_hil.design.certificate_record`); the JSON fields are read by :mod:`foilc_hil.design.json_fields`.

Module order inside :mod:`foilc_hil.design`: ``models`` < ``fractional``, ``qfilter``, ``ptype`` < ``json_fields`` <
``certificate_record`` < ``record`` < ``certificates`` < ``lmi`` < ``tuning`` < ``pipeline`` (each imports only
modules to its left; the whole order: ``docs/architecture.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np

from foilc_hil.config import LawKind, QFilterConfig, QFilterPhase
from foilc_hil.design.certificate_record import Certificates
from foilc_hil.design.json_fields import (
    matrix_rows,
    read_mapping,
    read_matrix,
    read_number,
    read_optional,
    read_typed,
)
from foilc_hil.design.models import DiscreteModel, Uncertainty
from foilc_hil.design.qfilter import QFilter
from foilc_hil.errors import InputError

__all__ = ["Design", "with_logged_q_filter"]


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
    q_filter
        The Q-filter the certificates were computed with and the law runs (:mod:`foilc_hil.design.qfilter`): the
        object the design pipeline built once from ``law.q_filter``, at this design's sample time; ``None``
        without one.
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
    q_filter: QFilter | None = None

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
        object.__setattr__(self, "P", read_matrix(self.P, "P"))
        self._check_shape("P", self.P, (m, n + p))
        lmi = [getattr(self, key) is None for key in _LMI_KEYS]
        if any(lmi) and not all(lmi):
            raise InputError(f"design: {', '.join(_LMI_KEYS)} are given together (an LMI solution) or not at all")
        if not any(lmi):
            assert self.Qb is not None and self.Qt is not None
            object.__setattr__(self, "Qb", read_matrix(self.Qb, "Qb"))
            object.__setattr__(self, "Qt", read_matrix(self.Qt, "Qt"))
            self._check_shape("Qb", self.Qb, (n, n))
            self._check_shape("Qt", self.Qt, (p, p))
        for name in ("kp", "r", "gain_scale", "gamma", "tau", "theta"):
            value = getattr(self, name)
            if value is None:
                continue
            if not math.isfinite(float(value)):
                raise InputError(f"design.{name}: must be finite")
            object.__setattr__(self, name, float(value))
        if self.q_filter is not None and not (
            isinstance(self.q_filter, QFilter) and self.q_filter.sample_time == self.sample_time
        ):
            raise InputError(f"design.q_filter: must be a QFilter at the design's sample time, got {self.q_filter!r}")

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
        document: dict[str, Any] = {name: matrix_rows(getattr(self, name)) for name in ("A", "B", "C")}
        document.update({name: matrix_rows(getattr(self, name)) for name in ("G1", "H1", "G2", "H2", "P")})
        document.update(
            {name: None if getattr(self, name) is None else matrix_rows(getattr(self, name)) for name in ("Qb", "Qt")}
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
                "p1": matrix_rows(self.p1),
                "p2": matrix_rows(self.p2),
                "C_measured": matrix_rows(self.measured_output),
            }
        )
        if self.q_filter is not None:  # an addition (docs/interface.md): absent from earlier documents
            document["q_filter"] = self.q_filter.to_json()
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
            read_matrix(document["A"], "A"),
            read_matrix(document["B"], "B"),
            read_matrix(document["C"], "C"),
            read_number(document, "sample_time", "design"),
            input_delay=delay,
            C_measured=read_matrix(document["C_measured"], "C_measured") if "C_measured" in document else None,
        )
        G1, H1, G2, H2 = (read_matrix(document[key], key) for key in ("G1", "H1", "G2", "H2"))
        uncertainty = Uncertainty(G1, H1, G2, H2)
        certificates = read_mapping(document.get("certificates", {}), "design.certificates")
        lmi_absent = document["Qb"] is None
        return cls(
            law=cast(LawKind, document.get("law", "foilc")),  # validated by __post_init__
            model=model,
            uncertainty=uncertainty,
            P=read_matrix(document["P"], "P"),
            kp=read_number(document, "kp", "design"),
            r=read_number(document, "r", "design"),
            Qb=None if lmi_absent else read_matrix(document["Qb"], "Qb"),
            Qt=None if lmi_absent else read_matrix(document["Qt"], "Qt"),
            gamma=None if lmi_absent else read_number(document, "gamma", "design"),
            tau=None if lmi_absent else read_number(document, "tau", "design"),
            theta=None if lmi_absent else read_number(document, "theta", "design"),
            gain_scale=read_number(document, "gain_scale", "design") if "gain_scale" in document else 1.0,
            certificates=Certificates.from_json(certificates) if certificates else None,
            q_filter=read_optional(document, "q_filter", lambda value: _read_q_filter(value, model.sample_time)),
        )


def _read_q_filter(value: Any, sample_time: float) -> QFilter:
    """The design's ``q_filter`` document (:meth:`~foilc_hil.design.qfilter.QFilter.to_json`) at ``sample_time``."""
    where = "design.q_filter"
    document = read_mapping(value, where)
    cutoff, order = read_number(document, "cutoff", where), read_typed(document, "order", int, where)
    phase = read_typed(document, "phase", str, where)
    try:
        return QFilter(cutoff, order, sample_time, QFilterPhase(phase))
    except ValueError as exc:  # an unknown phase, or a filter QFilter refuses (a ConfigError)
        raise InputError(f"{where}: {exc}") from None


def with_logged_q_filter(design: Design, document: Mapping[str, Any], section: QFilterConfig | None) -> Design:
    """``design``, read from a log's ``document``, with the Q-filter its run built: its own (a design records it
    since the addition), or, for a design logged before designs recorded it, the filter of the logged config's
    ``law.q_filter`` ``section``, which the run built (``replay --verify`` runs it, ``report`` draws it)."""
    if "q_filter" in document or section is None:
        return design
    return replace(design, q_filter=QFilter.of(section, design.sample_time))
