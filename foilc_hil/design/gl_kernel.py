"""The compiled near field of the fractional filter of a 2-D signal (:func:`direct_columns`), numba.

:mod:`foilc_hil.design.fractional` imports this module on its first 2-D direct convolution -- the learning law's,
between trials -- and not at its own import: the design (tuning, LMI, certificates) filters 1-D signals only and
so never loads numba (about 0.6 s of a process's start). Importing this module compiles the kernel, or loads it
from numba's cache, once per process.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["direct_columns"]


@njit(cache=True)
def direct_columns(weights: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``out[i, c] = sum_{j <= i} weights[j] g[i - j, c]`` for ``i < len(g)``: the first ``len(g)`` rows of the
    linear convolution of ``weights`` with every column of ``g`` (shape ``(N, p)``).

    Each sum starts from ``0.0`` and adds ``weights[j] * g[i - j, c]`` in ascending ``j``, one rounding per product
    and per addition: the order of scipy's 2-D direct ``signal.convolve``, so the result is the same bit for bit
    (``replay --verify`` of logs written with scipy's 2-D call needs it; tests check it against scipy). The loops
    run ``j`` outside and ``i`` inside over a contiguous copy of the column, which keeps every output's order and
    lets the compiler vectorise across outputs: much faster than scipy's N-d direct loop.

    """
    n, p = g.shape
    taps = min(n, weights.shape[0])
    out = np.empty((n, p))
    column = np.empty(n)
    acc = np.empty(n)
    for c in range(p):
        for i in range(n):
            column[i] = g[i, c]
            acc[i] = 0.0
        for j in range(taps):
            wj = weights[j]
            for i in range(j, n):
                acc[i] += wj * column[i - j]
        for i in range(n):
            out[i, c] = acc[i]
    return out


# At import, compiled or loaded from numba's cache (C-contiguous float64 only, as fractional._direct passes)
direct_columns(np.ones(1), np.ones((1, 1)))
