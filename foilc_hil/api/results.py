""":class:`TrialResult`: one finished trial as arrays, the same whether it was run (``Bench``, ``simulate``) or read
back from a log (``open_log``)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from foilc_hil.errors import LogFormatError
from foilc_hil.metrics import TrialMetrics

if TYPE_CHECKING:
    from foilc_hil.loop.interfaces import TrialRecord

__all__ = ["TrialResult"]

#: the arrays of a trial, in the order of an ``/ilc/sample`` row
ARRAYS = ("reference", "output", "control", "error", "E")


@dataclass(frozen=True, eq=False)
class TrialResult:
    """One finished trial of ``N`` samples: row ``i`` of every array describes the instant ``(i + 1) Ts``.

    The layout is the log's ``/ilc/sample`` (``docs/interface.md``), so a trial read back from a log equals the one
    the run yielded: every array bit for bit (:meth:`same_as`).

    Attributes
    ----------
    index
        The trial's number, from 1.
    reference
        ``y_r((i + 1) Ts)``, shape ``(N,)``.
    output
        The measured output ``y((i + 1) Ts)``, shape ``(N,)``.
    control
        The law's command ``u_i`` (computed at ``i Ts``, applied from ``(i + 1) Ts``), before the bench's limiter,
        shape ``(N,)``.
    error
        ``reference - output``, shape ``(N,)``.
    E
        The law's learning signal (FOILC: the fractional PD function of the error; else the error), shape ``(N,)``.
    metrics
        SSE, RMSE, peak error (and their learnable parts), the noise floor: the trial's ``/ilc/trial`` record.
    sample_time
        ``Ts`` in seconds.
    """

    index: int
    reference: np.ndarray
    output: np.ndarray
    control: np.ndarray
    error: np.ndarray
    E: np.ndarray
    metrics: TrialMetrics
    sample_time: float

    @property
    def sse(self) -> float:
        """The sum of the squared errors of the trial."""
        return self.metrics.sse

    @property
    def rmse(self) -> float:
        """The root mean square of the error."""
        return self.metrics.rmse

    @property
    def time(self) -> np.ndarray:
        """The instants of the rows, ``(i + 1) Ts`` for ``i = 0 .. N-1``."""
        return (np.arange(self.reference.shape[0]) + 1) * self.sample_time

    def same_as(self, other: TrialResult) -> bool:
        """Whether ``other`` is the same trial: the same index, metrics and sample time, and every array equal
        (``np.array_equal``; NaN never equals)."""
        return (self.index == other.index and self.metrics == other.metrics and self.sample_time == other.sample_time
                and all(np.array_equal(getattr(self, name), getattr(other, name)) for name in ARRAYS))

    @classmethod
    def from_record(cls, record: TrialRecord) -> TrialResult:
        """The result of a trial the loop finished (the arrays it logs; the reference copied, not shared)."""
        return cls(int(record.trial), np.array(record.reference, dtype=float), record.output, record.control,
                   record.error, record.E, record.metrics, float(record.sample_time))

    @classmethod
    def from_log(cls, record: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], sample_time: float) -> TrialResult:
        """The result of one trial of a log: its ``/ilc/trial`` record and its ``/ilc/sample`` rows in sample order.

        Raises
        ------
        LogFormatError
            A row or the record lacks a field, or holds what is not a number.
        """
        try:
            columns = [np.array([math.nan if row[name] is None else row[name] for row in rows], dtype=float)
                       for name in ARRAYS]
            metrics = TrialMetrics(**{field.name: record[field.name] for field in fields(TrialMetrics)
                                      if field.name in record})
        except (KeyError, TypeError, ValueError) as exc:
            raise LogFormatError(f"trial {record.get('trial')}: /ilc/sample or /ilc/trial: {exc!r}") from None
        reference, output, control, error, learned = columns
        return cls(int(record["trial"]), reference, output, control, error, learned, metrics, sample_time)
