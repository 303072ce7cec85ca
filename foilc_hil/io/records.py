"""The typed records the trial loop hands to the log writer.

A sample is built once, as a :class:`SampleRecord`, by whoever produced it (the trial loop after a trial, a test,
a tool) and travels unchanged through :class:`~foilc_hil.io.log_process.ProcessLogWriter`'s pipe to
:class:`~foilc_hil.io.mcap_log.McapLogWriter`, which encodes it with :meth:`SampleRecord.to_json`: one form from
the loop to the file. A cycle's timing travels the same way as a :class:`TimingRecord` (``/timing``).

Both are named tuples: immutable, no ``__dict__``, and several times cheaper to build than a frozen slotted
dataclass: the loop builds one per sample and per cycle.

"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np

__all__ = ["SampleRecord", "Signal", "TimingBlock", "TimingRecord", "TrialSamples"]

#: a signal value: a float for a single-output axis, a sequence/array (one entry per output or input) otherwise
Signal = Any


def _scalar_or_list(value: Signal) -> Any:
    """A Python float for a scalar (SISO), a list for a vector; numpy values converted."""
    if isinstance(value, float):
        return value
    if isinstance(value, np.ndarray):
        return value.item() if value.ndim == 0 else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


class SampleRecord(NamedTuple):
    """One ``/ilc/sample`` message: sample ``sample`` of trial ``trial``.

    Attributes
    ----------
    trial
        The trial (from 1).
    t
        The instant every signal of the record refers to (the bench writes ``(i + 1) Ts``: layout 2 of
        :data:`foilc_hil.io.schemas.SAMPLE_LAYOUT`).
    reference, output, error, E
        The reference, the measured output, ``reference - output`` and the learning signal at ``t``; ``E`` may be
        ``None``.
    control
        The law's command ``u(i)``, applied from ``t`` when its RPDO reached the drive before the SYNC at ``t``.
    sample
        The index ``i`` within the trial; ``None`` writes no ``sample`` field (logs of other tools).
    axis
        The axis's node id in a run of several axes (``axes:``); ``None`` writes no ``axis`` field (one axis).
    latched
        The command the drive latched at the SYNC starting the sample (at ``t``), as sent (clamped, quantised, plant
        units): ``control`` as sent when its RPDO came before that SYNC, else the last RPDO before it; ``None``
        writes no ``latched`` field (logs of other tools; logs written before it existed have none).
    """

    trial: int
    t: float
    reference: Signal
    output: Signal
    control: Signal
    error: Signal
    E: Signal = None
    sample: int | None = None
    axis: int | None = None
    latched: Signal = None

    def to_json(self) -> dict[str, Any]:
        """The ``/ilc/sample`` document (:data:`foilc_hil.io.schemas.ILC_SAMPLE_SCHEMA`); values are not rounded."""
        document: dict[str, Any] = {
            "trial": self.trial,
            "t": self.t,
            "reference": _scalar_or_list(self.reference),
            "output": _scalar_or_list(self.output),
            "control": _scalar_or_list(self.control),
            "error": _scalar_or_list(self.error),
            "E": _scalar_or_list(self.E),
        }
        if self.latched is not None:
            document["latched"] = _scalar_or_list(self.latched)
        if self.sample is not None:
            document["sample"] = self.sample
        if self.axis is not None:
            document["axis"] = self.axis
        return document


class TrialSamples(NamedTuple):
    """The ``/ilc/sample`` messages of one trial as its columns (layout 2 of
    :data:`foilc_hil.io.schemas.SAMPLE_LAYOUT`): row ``i`` describes the instant ``(i + 1) Ts``.

    One object per trial instead of one :class:`SampleRecord` per sample: a writer in another process is sent the
    columns (:class:`~foilc_hil.io.log_process.ProcessLogWriter`) and builds the records there, with
    :meth:`records`, the one definition of a trial's rows.

    Attributes
    ----------
    trial
        The trial (from 1).
    sample_time
        ``Ts`` in seconds.
    reference, output, control, error, E
        ``(N,)`` columns (``control`` sets ``N``): ``output[i] = y((i + 1) Ts)``, ``error == reference - output``,
        ``control[i] = u_i``, applied from ``(i + 1) Ts``.
    axis
        The axis's node id in a run of several axes; ``None``: the only axis.
    latched
        ``(N,)``: ``latched[i]``, the command the drive latched at the SYNC at ``(i + 1) Ts`` (see
        :class:`SampleRecord`); ``None``: no ``latched`` field.
    """

    trial: int
    sample_time: float
    reference: np.ndarray
    output: np.ndarray
    control: np.ndarray
    error: np.ndarray
    E: np.ndarray
    axis: int | None = None
    latched: np.ndarray | None = None

    def columns(self) -> tuple[np.ndarray, ...]:
        """``reference, output, control, error, E`` as ``N`` contiguous float64 values each."""
        n = len(self.control)
        return tuple(
            np.ascontiguousarray(np.asarray(column, dtype=np.float64)[:n])
            for column in (self.reference, self.output, self.control, self.error, self.E)
        )

    def latched_column(self) -> np.ndarray | None:
        """``latched`` as ``N`` contiguous float64 values (``None``: none)."""
        if self.latched is None:
            return None
        return np.ascontiguousarray(np.asarray(self.latched, dtype=np.float64)[: len(self.control)])

    def records(self) -> Iterator[SampleRecord]:
        """The trial's :class:`SampleRecord` messages, in sample order (each value the Python float of its row)."""
        trial, sample_time, axis = self.trial, self.sample_time, self.axis
        rows = zip(*(column.tolist() for column in self.columns()), strict=True)
        latched = self.latched_column()
        held = latched.tolist() if latched is not None else [None] * len(self.control)
        for i, ((reference, output, control, error, big_e), value) in enumerate(zip(rows, held, strict=True)):
            yield SampleRecord(trial, (i + 1) * sample_time, reference, output, control, error, big_e, i, axis, value)


class TimingRecord(NamedTuple):
    """One ``/timing`` message (:data:`foilc_hil.io.schemas.TIMING_SCHEMA`): cycle ``cycle`` of the run.

    Attributes
    ----------
    cycle
        The cycle counter over the whole run.
    trial, sample
        The trial (0 outside trials) and the cycle's index within its block.
    lateness_us
        How late the SYNC went out after its absolute deadline.
    period_us
        Time since the previous cycle's SYNC (0 for a block's first cycle).
    feedback_latency_us
        SYNC to feedback; ``None`` when no feedback arrived.
    missed
        The cycle missed its deadline.
    lost_feedback
        No TPDO set answered the SYNC within its bound (the law held the last good feedback).
    """

    cycle: int
    trial: int
    sample: int
    lateness_us: float
    period_us: float
    feedback_latency_us: float | None
    missed: bool
    lost_feedback: bool = False

    def to_json(self) -> dict[str, Any]:
        """The ``/timing`` document; booleans as JSON booleans, numpy scalars as Python numbers."""
        return {
            "cycle": int(self.cycle),
            "trial": int(self.trial),
            "sample": int(self.sample),
            "lateness_us": _scalar_or_list(self.lateness_us),
            "period_us": _scalar_or_list(self.period_us),
            "feedback_latency_us": _scalar_or_list(self.feedback_latency_us),
            "missed": bool(self.missed),
            "lost_feedback": bool(self.lost_feedback),
        }


class TimingBlock(NamedTuple):
    """A block of consecutive ``/timing`` messages as columns: cycle ``first_cycle + k`` is row ``k`` (its
    ``sample``), all of trial ``trial``.

    One object per block instead of one :class:`TimingRecord` per cycle, as :class:`TrialSamples` is for a trial's
    samples: a writer in another process is sent the columns and builds the records there, with :meth:`records`.
    Why: built in the loop's process, the 6000 records of a trial cost 55-90 ms of Python, in the update thread
    that runs beside the loop's settle cycles, whose every wait for the GIL then lasted up to a switch interval
    (2.9 % of settle cycles missed their deadline, against 0.23 % of trial cycles, in 14 runs).

    Attributes
    ----------
    first_cycle, trial
        The first row's cycle over the run, and the block's trial (as :class:`TimingRecord`).
    lateness_us, period_us
        ``(n,)`` float64.
    feedback_latency_us
        ``(n,)`` float64, NaN where no feedback came (``None`` in the record).
    missed, lost_feedback
        ``(n,)`` bool.
    """

    first_cycle: int
    trial: int
    lateness_us: np.ndarray
    period_us: np.ndarray
    feedback_latency_us: np.ndarray
    missed: np.ndarray
    lost_feedback: np.ndarray

    def columns(self) -> tuple[bytes, ...]:
        """The five columns as bytes (float64, then bool as one byte each), for a pipe."""
        floats = (self.lateness_us, self.period_us, self.feedback_latency_us)
        flags = (self.missed, self.lost_feedback)
        return (*(np.ascontiguousarray(c, dtype=np.float64).tobytes() for c in floats),
                *(np.ascontiguousarray(c, dtype=np.bool_).tobytes() for c in flags))

    @classmethod
    def from_columns(cls, first_cycle: int, trial: int, columns: tuple[bytes, ...]) -> TimingBlock:
        """The block :meth:`columns` packed."""
        lateness, period, latency = (np.frombuffer(c, dtype=np.float64) for c in columns[:3])
        missed, lost = (np.frombuffer(c, dtype=np.bool_) for c in columns[3:5])
        return cls(first_cycle, trial, lateness, period, latency, missed, lost)

    def records(self) -> Iterator[TimingRecord]:
        """The block's :class:`TimingRecord` messages, in cycle order (each value the Python scalar of its row)."""
        first, trial = int(self.first_cycle), int(self.trial)
        rows = zip(self.lateness_us.tolist(), self.period_us.tolist(), self.feedback_latency_us.tolist(),
                   self.missed.tolist(), self.lost_feedback.tolist(), strict=True)
        for k, (lateness, period, latency, missed, lost) in enumerate(rows):
            yield TimingRecord(first + k, trial, k, lateness, period, None if latency != latency else latency,
                               missed, lost)

