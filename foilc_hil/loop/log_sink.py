"""The trial loop's log: :class:`McapSink`, the loop's :class:`~foilc_hil.loop.interfaces.LogSink` over an MCAP writer
(the records of :mod:`foilc_hil.loop.interfaces` into the layout of ``docs/interface.md``), and :func:`logged_trials`,
what a run's report may list (the trials its log holds).
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from foilc_hil.io.log_process import ProcessLogWriter
    from foilc_hil.io.mcap_log import McapLogWriter
    from foilc_hil.loop.interfaces import TrialRecord
    from foilc_hil.loop.safety import StopRequest
    from foilc_hil.loop.scheduler import CycleBlock
    from foilc_hil.metrics import TrialMetrics

__all__ = ["McapSink", "logged_trials"]


class McapSink:
    """The loop's :class:`~foilc_hil.loop.interfaces.LogSink` over an MCAP writer (``run`` gives it a
    :class:`~foilc_hil.io.log_process.ProcessLogWriter`: the loop's process only packs tuples, a child writes).

    Parameters
    ----------
    writer
        Where the trials go.
    command_limits
        The limits the law clamped to (the bench's limiter); ``None``: no limiter (the offline simulator), and
        ``/ilc/trial`` then has neither ``clamped`` nor ``command_limits``.
    """

    def __init__(
        self, writer: McapLogWriter | ProcessLogWriter, command_limits: tuple[float, float] | None
    ) -> None:
        from foilc_hil.io.schemas import METADATA_LAYOUT, SAMPLE_LAYOUT

        self.writer = writer
        self.command_limits = None if command_limits is None else [float(limit) for limit in command_limits]
        # replay --verify reads rows by it, and requires the closing record the writer ends every log with
        writer.add_metadata(METADATA_LAYOUT, {"ilc_sample": str(SAMPLE_LAYOUT), "closing": "1"})
        self._previous_sync: float | None = None  # across blocks: a settle phase's first period_us is a real one

    def ready(self) -> None:
        """Block until the writer keeps pace with the loop (a writer process has started): before the enable."""
        self.writer.started()

    def stop_on_failure(self, stop: StopRequest) -> None:
        """A writer process that stalls, dies or fails a write stops the loop at its next cycle (the drive is
        quick-stopped, then disabled, as for any abort): the log never holds a moving axis."""
        from foilc_hil.io.log_process import ProcessLogWriter

        if isinstance(self.writer, ProcessLogWriter):
            self.writer.on_failure = stop.fail

    def written_trials(self) -> frozenset[int] | None:
        """The trials the file holds: as its writer process acknowledged them, or, after the writer failed, as the
        damage-tolerant reader finds them complete in the file (a write can fail after a trial's chunk is on
        disk); ``None``: a writer in this process (what it was given is what it holds, or it raised)."""
        from foilc_hil.io.log_process import ProcessLogWriter
        from foilc_hil.io.mcap_log import McapLogReader

        writer = self.writer
        if not isinstance(writer, ProcessLogWriter):
            return None
        if writer.failed:
            with contextlib.suppress(Exception), McapLogReader(writer.path) as reader:  # a file too damaged to read
                return frozenset(reader.read().completed_trials)  # holds what was acknowledged, at most
        return frozenset(writer.written_trials)

    def trial_finished(self, record: TrialRecord) -> None:
        self.writer.write_trial_samples(record.samples())  # one call a trial: the rows are built by the writer
        # initial_output = y(0): the law's input at sample 0, which no row holds (replay --verify);
        # final_output = y(N Ts), also the last row's output (kept: the interface names it)
        ends = {"initial_output": float(record.seen[0]), "final_output": float(record.seen[-1])}
        if record.axis is not None:  # a run of several axes: every /ilc/trial names its axis
            ends["axis"] = record.axis
        if record.first_sync is not None:  # replay --verify finds the trial's frames in /can from it
            ends["first_sync"] = record.first_sync
        mismatches = record.demand_mismatches  # drive.demand_echo: replay --verify recounts it from /can
        if mismatches is not None:
            ends["demand_mismatches"] = mismatches
        limits = self.command_limits if record.command_limits is None else [float(x) for x in record.command_limits]
        if limits is None:
            self.writer.log_trial(record.metrics, **ends)
        else:  # command_limits: the limits the law clamped to (replay --verify rebuilds the law with them)
            self.writer.log_trial(
                record.metrics,
                clamped=record.clamped,
                **ends,
                command_limits=limits,
                **record.faults.to_json(),
            )
        self.writer.end_trial()

    def timing(self, block: CycleBlock) -> None:
        """The block's ``/timing`` messages, handed to the writer as columns
        (:class:`~foilc_hil.io.records.TimingBlock`): a writer process builds the records, not the loop's process."""
        messages, self._previous_sync = block.messages(self._previous_sync)
        self.writer.write_timing_block(messages)


def logged_trials(trials: list[TrialMetrics], sinks: Sequence[McapSink]) -> list[TrialMetrics]:
    """The ``trials`` the run's log holds (all of them without a log): a report lists what the file has, and a
    trial whose write failed is not in it."""
    for sink in sinks:
        written = sink.written_trials()
        if written is not None:
            trials = [metrics for metrics in trials if metrics.trial in written]
    return trials
