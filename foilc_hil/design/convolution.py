"""Linear convolution along axis 0 by zero-padded real FFTs, without importing ``scipy.signal``.

:func:`fft_convolve` performs the operations of ``scipy.signal.fftconvolve(in1, in2, mode="full", axes=0)`` for
real arrays, in the same order, on the same ``scipy.fft`` calls: the same result bit for bit (``tests`` check it
against scipy), so a design or a replayed law gives what it gave with scipy's function. Why not scipy's own:
importing ``scipy.signal`` imports all of it (filter design, spline filters, ``scipy.stats``, ``scipy.interpolate``),
about a second of a process's start, which a command such as ``synthesize`` paid for one convolution
(docs/interface-additions.md, "What synthesize imports").
"""

from __future__ import annotations

import numpy as np

from foilc_hil.errors import InputError

__all__ = ["fft_convolve"]


def fft_convolve(in1: np.ndarray, in2: np.ndarray) -> np.ndarray:
    """The full linear convolution of ``in1`` and ``in2`` along axis 0 (``len(in1) + len(in2) - 1`` rows).

    Parameters
    ----------
    in1, in2
        Real arrays with the same number of dimensions; along every other axis their lengths are equal or one of
        them is 1 (broadcast), as for ``scipy.signal.fftconvolve(..., axes=0)``.

    Returns
    -------
    numpy.ndarray
        Float64, a new array: both operands padded with zeros to ``next_fast_len`` of the full length, real
        FFTs multiplied, inverted, and cut to the full length (no wrap-around). An empty operand gives an empty
        array; an operand of length 1 along axis 0 is a plain (broadcast) product, as in scipy.

    Raises
    ------
    foilc_hil.errors.InputError
        Operands of different dimensions, complex operands, or lengths that do not broadcast.
    """
    from scipy import fft  # cheap beside scipy.signal; the design imports it for its sweeps anyway

    a = np.asarray(in1)
    b = np.asarray(in2)
    if a.ndim != b.ndim or a.ndim == 0:
        raise InputError(f"fft_convolve: operands of shapes {a.shape} and {b.shape} need one number of dimensions >= 1")
    if np.iscomplexobj(a) or np.iscomplexobj(b):
        raise InputError("fft_convolve: operands must be real")
    if a.size == 0 or b.size == 0:
        return np.zeros(0)
    if any(x != y and 1 not in (x, y) for x, y in zip(a.shape[1:], b.shape[1:], strict=True)):
        raise InputError(f"fft_convolve: shapes {a.shape} and {b.shape} do not broadcast beyond axis 0")
    a = a.astype(np.float64, copy=False)
    b = b.astype(np.float64, copy=False)
    if a.shape[0] == 1 or b.shape[0] == 1:
        return np.asarray(a * b)  # scipy skips the transform of a length-1 axis: the product is the convolution
    length = a.shape[0] + b.shape[0] - 1
    padded = [fft.next_fast_len(length, True)]
    spectrum = fft.rfftn(a, padded, axes=[0]) * fft.rfftn(b, padded, axes=[0])
    full = fft.irfftn(spectrum, padded, axes=[0])
    return np.array(full[:length], copy=True)
