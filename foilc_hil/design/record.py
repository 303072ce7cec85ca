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
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, cast

import numpy as np

from foilc_hil.design.models import ssmatrix
from foilc_hil.errors import InputError

LawKind = Literal["foilc", "ioilc", "p-type"]
LAW_KINDS: tuple[str, ...] = ("foilc", "ioilc", "p-type")

_MATRIX_KEYS = ("A", "B", "C", "G1", "H1", "G2", "H2", "P", "Qb", "Qt")
_FLOAT_KEYS = ("gamma", "tau", "theta", "kp", "r", "sample_time", "gain_scale")


def _matrix(value: Any, name: str) -> np.ndarray:
    """``value`` as a finite 2-D float array (a copy, read-only); the error names ``design.<name>``."""
    return ssmatrix(value, f"design.{name}", allow_scalar=False)


def _rows(array: np.ndarray) -> list[list[float]]:
    """A matrix as JSON lists of rows (Python floats round-trip exactly through ``json``)."""
    return [[float(x) for x in row] for row in np.asarray(array, dtype=float)]


def jsonable(value: Any) -> Any:
    """Certificates as plain JSON values (numpy scalars/arrays converted, non-finite floats as strings)."""
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


@dataclass(frozen=True)
class Design:
    """A synthesized learning gain, the model it was designed on, and its convergence certificates.

    Attributes
    ----------
    law
        ``"foilc"``, ``"ioilc"`` (``kp = 0``: integer-order law, same 2D structure) or ``"p-type"``.
    A, B, C
        The discrete model ``x(t+1) = A x(t) + B u(t)``, ``y = C x`` the gain was designed on (``n x n``,
        ``n x m``, ``p x n``); includes ``input_delay`` augmentation states.
    G1, H1, G2, H2
        Norm-bounded uncertainty of that model: ``dA = G1 Delta H1``, ``dB = G2 Delta H2``, ``||Delta|| <= 1``.
    P
        The learning gain ``(p1 p2)``, ``m x (n + p)``.
    Qb, Qt
        The Lyapunov blocks of Theorem 1 (``n x n`` and ``p x p``).
    gamma
        The minimised ``gamma`` of LMI (31) (Remark 1).
    tau, theta
        The weights of ``Q(tau, theta) = diag(tau Qb, theta Qt)``.
    kp, r
        The fractional PD function ``E = (I + kp D^r) e``; ``kp = 0`` for IOILC.
    sample_time
        Seconds per sample.
    input_delay
        Cycles of input transport delay folded into ``(A, B, C)`` by augmentation (0 offline, 1 over CAN).
    gain_scale
        ``1.0`` unless the certificate step rescaled ``p2`` (``P`` holds the rescaled gain).
    certificates
        Convergence certificates of the law as it runs (see :mod:`foilc_hil.design.certificates`).
    C_measured
        The measured output ``y = C_measured z`` of the (augmented) state; ``None`` means ``C`` (allowed only
        without input delay). Always an array after construction.
    """

    law: str
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    G1: np.ndarray
    H1: np.ndarray
    G2: np.ndarray
    H2: np.ndarray
    P: np.ndarray
    Qb: np.ndarray
    Qt: np.ndarray
    gamma: float
    tau: float
    theta: float
    kp: float
    r: float
    sample_time: float
    input_delay: int = 0
    gain_scale: float = 1.0
    certificates: dict[str, Any] = field(default_factory=dict)
    C_measured: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.law not in LAW_KINDS:
            raise InputError(f"design.law: must be one of {', '.join(LAW_KINDS)}, got {self.law!r}")
        for name in _MATRIX_KEYS:
            object.__setattr__(self, name, _matrix(getattr(self, name), name))
        n, m, p = self.n_states, self.n_inputs, self.n_outputs
        expected = {
            "A": (n, n),
            "B": (n, m),
            "C": (p, n),
            "P": (m, n + p),
            "Qb": (n, n),
            "Qt": (p, p),
        }
        for name, shape in expected.items():
            actual = getattr(self, name).shape
            if actual != shape:
                raise InputError(f"design.{name}: must be {shape[0]}x{shape[1]}, got {actual[0]}x{actual[1]}")
        if self.G1.shape[0] != n or self.H1.shape[1] != n:
            raise InputError(f"design.G1/H1: dA = G1 Delta H1 must be {n}x{n}")
        if self.G2.shape[0] != n or self.H2.shape[1] != m:
            raise InputError(f"design.G2/H2: dB = G2 Delta H2 must be {n}x{m}")
        if self.G1.shape[1] != self.H1.shape[0] or self.G2.shape[1] != self.H2.shape[0]:
            raise InputError("design.G1/H1/G2/H2: Delta must fit between G and H")
        for name in _FLOAT_KEYS:
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise InputError(f"design.{name}: must be finite")
            object.__setattr__(self, name, value)
        if self.sample_time <= 0:
            raise InputError("design.sample_time: must be positive")
        if int(self.input_delay) != self.input_delay or self.input_delay < 0:
            raise InputError("design.input_delay: must be a non-negative integer")
        object.__setattr__(self, "input_delay", int(self.input_delay))
        object.__setattr__(self, "certificates", dict(self.certificates))
        if self.C_measured is None:
            if self.input_delay:
                raise InputError("design.C_measured: is required when input_delay > 0")
            object.__setattr__(self, "C_measured", self.C)
        else:
            measured = _matrix(self.C_measured, "C_measured")
            if measured.shape != self.C.shape:
                raise InputError(f"design.C_measured: must have the shape of C {self.C.shape}, got {measured.shape}")
            object.__setattr__(self, "C_measured", measured)

    # --- dimensions and gain blocks -------------------------------------------------------------------------

    @property
    def n_states(self) -> int:
        """``n``, the states of the (augmented) design model."""
        return int(self.A.shape[0])

    @property
    def n_inputs(self) -> int:
        """``m``, the plant inputs."""
        return int(self.B.shape[1])

    @property
    def n_outputs(self) -> int:
        """``p``, the plant outputs."""
        return int(self.C.shape[0])

    @property
    def p1(self) -> np.ndarray:
        """The state-difference gain, ``m x n``."""
        return self.P[:, : self.n_states]

    @property
    def p2(self) -> np.ndarray:
        """The error gain (acting on ``E_{k-1}(t+1)``), ``m x p``."""
        return self.P[:, self.n_states :]

    @property
    def error_lead(self) -> int:
        """Extra samples of lead on the error: the law uses ``E_{k-1}[i + error_lead]`` (``= input_delay``)."""
        return self.input_delay

    @property
    def measured_output(self) -> np.ndarray:
        """``C_measured`` as an array (never ``None`` after construction)."""
        assert self.C_measured is not None
        return self.C_measured

    # --- JSON -----------------------------------------------------------------------------------------------

    def to_json(self) -> dict[str, Any]:
        """The interface document of ``synthesize --json`` (matrices as lists of rows), plus ``law``,
        ``input_delay``, ``gain_scale``, ``p1``, ``p2`` and ``C_measured``."""
        document: dict[str, Any] = {name: _rows(getattr(self, name)) for name in ("A", "B", "C")}
        document.update({name: _rows(getattr(self, name)) for name in ("G1", "H1", "G2", "H2", "P", "Qb", "Qt")})
        document.update(
            {
                "gamma": self.gamma,
                "tau": self.tau,
                "theta": self.theta,
                "kp": self.kp,
                "r": self.r,
                "sample_time": self.sample_time,
                "certificates": jsonable(self.certificates),
                "law": self.law,
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
        """Rebuild a design from :meth:`to_json` output (exact round trip).

        Raises
        ------
        foilc_hil.errors.InputError
            Naming the missing or malformed key.
        """
        if not isinstance(document, Mapping):
            raise InputError("design: must be a JSON object")
        for key in (*_MATRIX_KEYS, "gamma", "tau", "theta", "kp", "r", "sample_time"):
            if key not in document:
                raise InputError(f"design.{key}: is required")
        floats: dict[str, float] = {}
        for key in ("gamma", "tau", "theta", "kp", "r", "sample_time", "gain_scale"):
            raw = document.get(key, 1.0)
            if isinstance(raw, bool) or not isinstance(raw, (int, float)):
                raise InputError(f"design.{key}: must be a number")
            floats[key] = float(raw)
        delay = document.get("input_delay", 0)
        if isinstance(delay, bool) or not isinstance(delay, int):
            raise InputError("design.input_delay: must be an integer")
        certificates = document.get("certificates", {})
        if not isinstance(certificates, Mapping):
            raise InputError("design.certificates: must be an object")
        return cls(
            law=cast(str, document.get("law", "foilc")),
            A=_matrix(document["A"], "A"),
            B=_matrix(document["B"], "B"),
            C=_matrix(document["C"], "C"),
            G1=_matrix(document["G1"], "G1"),
            H1=_matrix(document["H1"], "H1"),
            G2=_matrix(document["G2"], "G2"),
            H2=_matrix(document["H2"], "H2"),
            P=_matrix(document["P"], "P"),
            Qb=_matrix(document["Qb"], "Qb"),
            Qt=_matrix(document["Qt"], "Qt"),
            input_delay=delay,
            certificates=dict(certificates),
            C_measured=_matrix(document["C_measured"], "C_measured") if "C_measured" in document else None,
            **floats,
        )
