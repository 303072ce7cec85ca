"""Zero-phase low-pass Q-filter applied to the learned feedforward between trials.

The filter is a Butterworth low-pass (``scipy.signal.butter``) run forward and then backward over the trial,
both passes from ZERO initial state and without padding (``scipy.signal.sosfilt`` twice; zero phase, squared
magnitude). With ``H`` the lower-triangular Toeplitz matrix of the causal filter on ``N`` samples, the forward
pass is ``H`` and the time-reversed pass ``J H J = H^T``, so the operator is ``Q = H^T H``: symmetric positive
semidefinite with ``||Q||_2 = ||H||_2^2 <= (sup_w |H(e^jw)|)^2 = 1`` (a Butterworth low-pass never amplifies).
A Q-filter with norm above one can break monotonic convergence of the learning loop.

Why not ``scipy.signal.filtfilt``: its edge handling (odd extension, the default; even, constant or no
extension with steady-state initial conditions; Gustafsson's method) makes the operator non-symmetric with
2-norms measured from 1.004 to 5.6 (and spectral radius above one for the odd extension) on typical trials.
The price of zero-state passes: the first and last few filter time constants of the trial are attenuated (the
operator does not reproduce a constant at the edges). :meth:`QFilter.matrix` -- the operator applied to the
columns of the identity -- is exactly the operator of :meth:`QFilter.apply`; the certificates use it.
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
        # second-order sections: the transfer-function form loses accuracy at high orders
        self._sos = np.asarray(signal.butter(self.order, self.cutoff / nyquist, btype="low", output="sos"), dtype=float)

    def apply(self, u: np.ndarray) -> np.ndarray:
        """Filter a whole trial along time (axis 0); ``u`` is ``(N,)`` or ``(N, m)``. Returns a new array.

        ``Q u = H^T H u``: zero-state forward pass, then zero-state pass over the reversed signal (module notes).
        """
        from scipy import signal

        x = np.asarray(u, dtype=float)
        forward = signal.sosfilt(self._sos, x, axis=0)
        backward = signal.sosfilt(self._sos, forward[::-1], axis=0)[::-1]
        return np.ascontiguousarray(backward, dtype=float)

    def matrix(self, n_samples: int) -> np.ndarray:
        """The ``(N, N)`` matrix ``Q`` with ``Q @ u == apply(u)`` for every ``(N,)`` signal ``u``."""
        return self.apply(np.eye(n_samples))

    def __repr__(self) -> str:
        return f"QFilter(cutoff={self.cutoff!r}, order={self.order!r}, sample_time={self.sample_time!r})"
