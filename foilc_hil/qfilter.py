"""Zero-phase low-pass Q-filter applied to the learned feedforward between trials.

The filter is a Butterworth low-pass (``scipy.signal.butter``) run forward and backward with
``scipy.signal.filtfilt`` (zero phase, squared magnitude). The padding is fixed: odd extension of
``3 * max(len(a), len(b))`` samples at each end with ``method="pad"`` (scipy's defaults, written out so that
a scipy default change cannot silently alter the operator). ``filtfilt`` with that padding is linear in the
signal, so :meth:`QFilter.matrix` -- the operator applied to the columns of the identity -- is exactly the
operator of :meth:`QFilter.apply`; the certificates use it to build the lifted trial-to-trial map.
"""

from __future__ import annotations

import math

import numpy as np

from foilc_hil.errors import ConfigError

__all__ = ["QFilter"]


class QFilter:
    """Zero-phase Butterworth low-pass.

    Parameters
    ----------
    cutoff
        -3 dB frequency of ONE pass, rad/s (the forward-backward pair is -6 dB there); must be below Nyquist.
    order
        Butterworth order of one pass.
    sample_time
        ``Ts`` in seconds.
    """

    def __init__(self, cutoff: float, order: int, sample_time: float) -> None:
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
        self.cutoff = float(cutoff)
        self.order = int(order)
        self.sample_time = float(sample_time)
        b, a = signal.butter(self.order, self.cutoff / nyquist, btype="low")
        self._b = np.asarray(b, dtype=float)
        self._a = np.asarray(a, dtype=float)
        self.padlen = 3 * max(len(self._a), len(self._b))

    def apply(self, u: np.ndarray) -> np.ndarray:
        """Filter a whole trial along time (axis 0); ``u`` is ``(N,)`` or ``(N, m)``. Returns a new array.

        Raises
        ------
        foilc_hil.errors.ConfigError
            When the trial is too short for the padding (``N <= padlen``).
        """
        from scipy import signal

        x = np.asarray(u, dtype=float)
        if x.shape[0] <= self.padlen:
            raise ConfigError(
                f"a trial of {x.shape[0]} samples is too short for an order-{self.order} zero-phase filter "
                f"(needs more than {self.padlen})",
                key="law.q_filter.order",
            )
        out = signal.filtfilt(self._b, self._a, x, axis=0, padtype="odd", padlen=self.padlen, method="pad")
        return np.ascontiguousarray(out, dtype=float)

    def matrix(self, n_samples: int) -> np.ndarray:
        """The ``(N, N)`` matrix ``Q`` with ``Q @ u == apply(u)`` for every ``(N,)`` signal ``u``."""
        return self.apply(np.eye(n_samples))

    def __repr__(self) -> str:
        return f"QFilter(cutoff={self.cutoff!r}, order={self.order!r}, sample_time={self.sample_time!r})"
