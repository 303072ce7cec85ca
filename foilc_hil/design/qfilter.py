"""The low-pass Q-filter applied to the learned feedforward between trials: zero-phase or causal.

The filter is a Butterworth low-pass (``scipy.signal.butter``, second-order sections) run over the whole trial
from ZERO initial state, without padding. ``phase`` (``law.q_filter.phase``, :class:`~foilc_hil.config.QFilterPhase`)
says how:

``zero`` (the default)
    forward, then backward over the reversed trial (``scipy.signal.sosfilt`` twice: zero phase, squared
    magnitude). With ``H`` the lower-triangular Toeplitz matrix of the causal filter on ``N`` samples, the forward
    pass is ``H`` and the time-reversed pass ``J H J = H^T``, so the operator is ``Q = H^T H``: symmetric positive
    semidefinite with ``||Q||_2 = ||H||_2^2 <= (sup_w |H(e^jw)|)^2 = 1`` (a Butterworth low-pass never amplifies).
``causal``
    one forward pass, ``Q = H``: ``||Q||_2 <= 1`` too, with the filter's phase lag; the trial-to-trial map of a
    causal law stays causal (lower triangular), which makes its spectral radius exact
    (:mod:`foilc_hil.design.qmap`).

A Q-filter with norm above one can break monotonic convergence of the learning loop. Why not
``scipy.signal.filtfilt``: its edge handling (odd extension, the default; even, constant or no extension with
steady-state initial conditions; Gustafsson's method) makes the operator non-symmetric with 2-norms measured from
1.004 to 5.6 (and spectral radius above one for the odd extension) on typical trials. The price of zero-state
passes: the first (causal) or last (zero-phase, the backward pass) few filter time constants of the trial are
attenuated.

One home: the design pipeline (:func:`foilc_hil.design.pipeline.law_structure`) builds the filter once, with
:meth:`QFilter.of` from the ``law.q_filter`` section; the certificates take it on the trial (:meth:`QFilter.on`),
the :class:`~foilc_hil.design.record.Design` holds that same object (and records its parameters, :meth:`to_json`),
and the law (:mod:`foilc_hil.laws.learning`) runs the design's. :meth:`QFilter.apply` is what the law runs,
:meth:`QFilter.matrix` is that operator on the columns of the identity, :meth:`QFilter.realization` the
state-space form of one pass that the structured certificates use (the tests check all three agree), and
:meth:`QFilter.response` its frequency response, which the picture of convergence draws.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from foilc_hil.config import QFilterConfig, QFilterPhase
from foilc_hil.errors import ConfigError, InputError

__all__ = ["FilterRealization", "QFilter", "TrialQFilter"]


@dataclass(frozen=True)
class FilterRealization:
    """One causal pass as a state-space system: ``x[t+1] = A x[t] + B u[t]``, ``y[t] = C x[t] + D u[t]``, ``x[0] = 0``
    (``A`` ``n x n``, ``B`` ``n x 1``, ``C`` ``1 x n``, ``D`` ``1 x 1``)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray


class QFilter:
    """Butterworth low-pass run zero-phase (forward-backward) or causal (forward) over a trial.

    Parameters
    ----------
    cutoff
        -3 dB frequency of ONE pass, rad/s (a zero-phase pair is -6 dB there); must be below Nyquist.
    order
        Butterworth order of one pass.
    sample_time
        ``Ts`` in seconds.
    phase
        ``zero`` or ``causal`` (:class:`~foilc_hil.config.QFilterPhase`).
    """

    def __init__(
        self, cutoff: float, order: int, sample_time: float, phase: QFilterPhase | str = QFilterPhase.ZERO
    ) -> None:
        from scipy import signal

        if not (sample_time > 0 and math.isfinite(sample_time)):
            raise ConfigError("must be positive and finite", key="sample_time")
        nyquist = math.pi / sample_time
        if not (0 < cutoff < nyquist):
            raise ConfigError(
                f"must be between 0 and the Nyquist frequency {nyquist:g} rad/s, got {cutoff:g}",
                key="law.q_filter.cutoff",
            )
        if order < 1:
            raise ConfigError("must be at least 1", key="law.q_filter.order")
        try:
            self.phase = QFilterPhase(phase)
        except ValueError:
            raise ConfigError(f"must be 'zero' or 'causal', got {phase!r}", key="law.q_filter.phase") from None
        self.cutoff = float(cutoff)
        self.order = int(order)
        self.sample_time = float(sample_time)
        # second-order sections: the transfer-function form loses accuracy at high orders
        self._sos = np.asarray(signal.butter(self.order, self.cutoff / nyquist, btype="low", output="sos"), dtype=float)

    @classmethod
    def of(cls, config: QFilterConfig, sample_time: float) -> QFilter:
        """The filter of a ``law.q_filter`` section (the design pipeline's one build of the law's filter)."""
        return cls(config.cutoff, config.order, sample_time, config.phase)

    def is_of(self, config: QFilterConfig | None) -> bool:
        """Whether this is the filter of the ``law.q_filter`` section ``config`` (at this filter's sample time)."""
        return config is not None and (float(config.cutoff), int(config.order), QFilterPhase(config.phase)) == (
            self.cutoff,
            self.order,
            self.phase,
        )

    def to_json(self) -> dict[str, Any]:
        """``{"cutoff", "order", "phase"}``: the design's ``q_filter`` (its sample time is the design's)."""
        return {"cutoff": self.cutoff, "order": self.order, "phase": str(self.phase)}

    def apply(self, u: np.ndarray) -> np.ndarray:
        """Filter a whole trial along time (axis 0); ``u`` is ``(N,)`` or ``(N, m)``. Returns a new array.

        Zero-phase: ``Q u = H^T H u`` (a zero-state forward pass, then a zero-state pass over the reversed
        signal); causal: ``Q u = H u`` (module notes).
        """
        from scipy import signal

        x = np.asarray(u, dtype=float)
        forward = signal.sosfilt(self._sos, x, axis=0)
        if self.phase is QFilterPhase.CAUSAL:
            return np.ascontiguousarray(forward, dtype=float)
        backward = signal.sosfilt(self._sos, forward[::-1], axis=0)[::-1]
        return np.ascontiguousarray(backward, dtype=float)

    def response(self, w: np.ndarray) -> np.ndarray:
        """``Q(e^jw)`` at ``w`` rad/sample: the frequency response of the operator :meth:`apply` runs, away from the
        trial's zero-state edges (the picture of convergence, :mod:`foilc_hil.design.frequency_picture`): ``|H|^2``
        (zero phase) or ``H`` (causal), ``H`` one pass of this filter's second-order sections."""
        from scipy import signal

        _, h = signal.sosfreqz(self._sos, worN=w)
        return np.asarray(np.abs(h) ** 2 if self.phase is QFilterPhase.ZERO else h)

    def matrix(self, n_samples: int) -> np.ndarray:
        """The ``(N, N)`` matrix ``Q`` with ``Q @ u == apply(u)`` for every ``(N,)`` signal ``u``."""
        return self.apply(np.eye(n_samples))

    def realization(self) -> FilterRealization:
        """One causal pass as a state-space system (the second-order sections in series, the first section first:
        ``sosfilt``'s order), for the structured certificates; ``Q = H`` (causal) or ``H^T H`` (zero phase) with
        ``H`` this system's lower-triangular Toeplitz matrix on the trial."""
        from scipy import signal

        A, B = np.zeros((0, 0)), np.zeros((0, 1))
        C, D = np.zeros((1, 0)), np.ones((1, 1))
        for section in self._sos:
            a, b, c, d = (np.atleast_2d(np.asarray(x, dtype=float)) for x in signal.tf2ss(section[:3], section[3:]))
            # the section after the cascade so far: its input is the cascade's output C x + D u
            n_old, n_new = A.shape[0], a.shape[0]
            joined = np.zeros((n_old + n_new, n_old + n_new))
            joined[:n_old, :n_old] = A
            joined[n_old:, :n_old] = b @ C
            joined[n_old:, n_old:] = a
            A, B = joined, np.vstack([B, b @ D])
            C, D = np.hstack([d @ C, c]), d @ D
        return FilterRealization(A, B, C, D)

    def on(self, n_samples: int) -> TrialQFilter:
        """This filter on trials of ``n_samples`` samples (what a :class:`~foilc_hil.design.lifted.LawStructure`
        holds)."""
        return TrialQFilter(self, n_samples)

    def __repr__(self) -> str:
        return (
            f"QFilter(cutoff={self.cutoff!r}, order={self.order!r}, sample_time={self.sample_time!r}, "
            f"phase={str(self.phase)!r})"
        )


@dataclass(frozen=True)
class TrialQFilter:
    """A :class:`QFilter` on trials of ``n_samples``: the ``N x N`` operator ``Q`` the certificates take as given.

    Nothing ``N x N`` is stored: the structured certificates use the filter's realization; dense code paths (small
    trials, the reference maps of the tests, the lifted laws' dense input map) get the matrix from
    :meth:`matrix`, or from ``numpy.asarray(q)`` (the array protocol gives the same matrix).
    """

    filter: QFilter
    n_samples: int

    def __post_init__(self) -> None:
        if not (isinstance(self.n_samples, int) and self.n_samples >= 1):
            raise InputError(f"n_samples: must be a positive integer, got {self.n_samples!r}")

    @property
    def phase(self) -> QFilterPhase:
        """``zero`` or ``causal``."""
        return self.filter.phase

    def apply(self, u: np.ndarray) -> np.ndarray:
        """``Q u`` for a whole trial ``u`` (:meth:`QFilter.apply`)."""
        return self.filter.apply(u)

    def matrix(self) -> np.ndarray:
        """``Q`` as a dense ``(N, N)`` matrix."""
        return self.filter.matrix(self.n_samples)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return np.asarray(self.matrix(), dtype=dtype)
