"""Test helper: a ``Design`` from a given model and gain, with no uncertainty and placeholder LMI values
(:func:`plain_design`), or a P-type design with none (:func:`p_type_design`).

Tests of laws, simulation and replay need a design whose gain they choose themselves; the LMI fields
(``Qb``, ``Qt``, ``gamma``, ``tau``, ``theta``) are then placeholders the laws never read.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from foilc_hil.config import LawKind
from foilc_hil.design.certificate_record import Certificates
from foilc_hil.design.models import DiscreteModel, Uncertainty
from foilc_hil.design.ptype import p_type_gain
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.record import Design


def plain_design(
    A: Any,
    B: Any,
    C: Any,
    P: Any,
    *,
    kp: float,
    r: float,
    sample_time: float,
    law: str = "foilc",
    input_delay: int = 0,
    C_measured: Any = None,
    certificates: Certificates | None = None,
    q_filter: QFilter | None = None,
) -> Design:
    """``Design`` of ``(A, B, C)`` with gain ``P``, zero ``G1/H1/G2/H2`` and identity ``Qb``, ``Qt`` (and the
    Q-filter its law runs, if any)."""
    A, B, C, P = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, B, C, P))
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    return Design(
        law=LawKind(law),
        model=DiscreteModel(A, B, C, sample_time, input_delay=input_delay, C_measured=C_measured),
        uncertainty=Uncertainty(np.zeros((n, 1)), np.zeros((1, n)), np.zeros((n, 1)), np.zeros((1, m))),
        P=P,
        kp=kp,
        r=r,
        Qb=np.eye(n),
        Qt=np.eye(p),
        gamma=1.0,
        tau=0.868,
        theta=0.868,
        certificates=certificates,
        q_filter=q_filter,
    )


def p_type_design(
    A: Any,
    B: Any,
    C: Any,
    gain: float | np.ndarray | None = None,
    *,
    sample_time: float,
    input_delay: int = 0,
    q_filter: QFilter | None = None,
) -> Design:
    """A P-type ``Design`` ``P = (0 Gamma)`` of ``(A, B)`` with measured output ``C`` (augmented by ``input_delay``
    like a design's), no uncertainty and no LMI: ``Gamma`` from ``gain`` as ``law.p_type_gain`` gives it (a scalar
    ``g I``, a matrix as is, ``None`` the default of :func:`foilc_hil.design.ptype.p_type_default_gain`)."""
    A, B, C = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, B, C))
    gamma = p_type_gain(gain, A, B, C, input_delay)
    n, m = A.shape[0], B.shape[1]
    return Design(
        law=LawKind.P_TYPE,
        model=DiscreteModel(A, B, C, sample_time, input_delay=input_delay, C_measured=C),
        uncertainty=Uncertainty(np.zeros((n, 1)), np.zeros((1, n)), np.zeros((n, 1)), np.zeros((1, m))),
        P=np.hstack([np.zeros((m, n)), gamma]),
        kp=0.0,
        r=1.0,
        q_filter=q_filter,
    )
