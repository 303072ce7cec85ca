"""The live view's messages: the JSON payloads of each channel, built as the log builds them.

``/ilc/sample``, ``/ilc/trial``, ``/timing`` and ``/can`` payloads are the documents the MCAP log holds for the same
trial, cycle or frame (the same functions of :mod:`foilc_hil.io.mcap_writer`, or the same fields in the same order),
so a viewer sees what the file will hold; ``/drive/state`` (:data:`~foilc_hil.io.schemas.DRIVE_STATE_SCHEMA`) is the
live view's own. Pure functions: the publisher thread (:mod:`foilc_hil.live.publisher`) and the log streamer
(:mod:`foilc_hil.live.replay`) call them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import orjson

from foilc_hil.io.mcap_writer import frame_json, trial_samples_documents
from foilc_hil.io.schemas import DRIVE_STATES

if TYPE_CHECKING:
    from foilc_hil.io.mcap_writer import Direction, FrameFields
    from foilc_hil.io.records import TrialSamples
    from foilc_hil.loop.interfaces import TrialRecord
    from foilc_hil.loop.scheduler import CycleBlock

__all__ = [
    "DriveState",
    "decimation",
    "drive_state_document",
    "frame_document",
    "sample_documents",
    "timing_documents",
    "trial_document",
]


def _dumps(document: dict[str, Any]) -> bytes:
    """Compact JSON as the log's writer spells it (orjson: shortest round-trip floats, ``null`` for non-finite)."""
    return orjson.dumps(document, option=orjson.OPT_SERIALIZE_NUMPY)


def decimation(rows: int, limit: int) -> int:
    """Every how many rows of a trial of ``rows`` one is published so that at most ``limit`` are (0: no limit)."""
    return 1 if limit <= 0 or rows <= limit else math.ceil(rows / limit)


def sample_documents(samples: TrialSamples, limit: int) -> list[bytes]:
    """The trial's ``/ilc/sample`` documents as the log holds them (byte for byte), every
    :func:`decimation`-th row from row 0 when the trial has more than ``limit`` rows."""
    documents = trial_samples_documents(samples)
    if documents is None:  # vector columns: one record a row, as the writer does
        documents = [_dumps(record.to_json()) for record in samples.records()]
    return documents[:: decimation(len(documents), limit)]


def trial_document(record: TrialRecord, limits: Sequence[float] | None) -> bytes:
    """The ``/ilc/trial`` document the log writes for ``record`` (``foilc_hil.loop.log_sink.McapSink``'s fields, in its
    order): the metrics, the ends of the output, the axis and first SYNC where known, and with ``limits`` (the limits
    the law clamped to) the clamp count, the limits and the fault counts."""
    ends: dict[str, Any] = {"initial_output": float(record.seen[0]), "final_output": float(record.seen[-1])}
    if record.axis is not None:
        ends["axis"] = record.axis
    if record.first_sync is not None:
        ends["first_sync"] = record.first_sync
    mismatches = record.demand_mismatches
    if mismatches is not None:
        ends["demand_mismatches"] = mismatches
    own = limits if record.command_limits is None else record.command_limits
    document = record.metrics.to_json()
    if own is None:
        document.update(ends)
    else:
        document.update(clamped=record.clamped, **ends, command_limits=[float(x) for x in own],
                        **record.faults.to_json())
    return _dumps(document)


def timing_documents(block: CycleBlock, previous: float | None) -> tuple[list[bytes], float | None]:
    """The ``/timing`` documents of a block of cycles and the block's last SYNC time (``previous``: the one before
    the block, for the first cycle's period): :meth:`~foilc_hil.loop.scheduler.CycleBlock.messages`, as
    ``foilc_hil.loop.log_sink.McapSink.timing`` logs them."""
    messages, previous = block.messages(previous)
    return [_dumps(record.to_json()) for record in messages.records()], previous


def frame_document(fields: FrameFields, direction: Direction, log_time_ns: int) -> bytes:
    """A ``/can`` document as the log writes it; a frame without a timestamp (the bench's own) gets its log time."""
    return frame_json(fields, fields[0] or log_time_ns / 1e9, direction)


@dataclass(frozen=True)
class DriveState:
    """One ``/drive/state`` message (:data:`~foilc_hil.io.schemas.DRIVE_STATE_SCHEMA`).

    Attributes
    ----------
    node
        The drive's node id.
    cycle
        The SYNC the feedback answered.
    state
        The CiA 402 state (an index into :data:`~foilc_hil.io.schemas.DRIVE_STATES`, ``drivers.cia402.State402``).
    statusword, controlword
        0x6041 and 0x6040 (``None``: not known).
    velocity
        0x606C in plant units (``None``: not mapped).
    """

    node: int
    cycle: int
    state: int
    statusword: int
    controlword: int | None
    velocity: float | None

    def changed_from(self, other: DriveState | None) -> bool:
        """What a viewer must see at once: another state or control/status word (the velocity moves every cycle)."""
        return other is None or (self.statusword, self.controlword, self.state) != (
            other.statusword, other.controlword, other.state)


def drive_state_document(state: DriveState) -> bytes:
    """The ``/drive/state`` payload."""
    velocity = state.velocity if state.velocity is None or math.isfinite(state.velocity) else None
    return _dumps({"node": int(state.node), "cycle": int(state.cycle), "state": DRIVE_STATES[int(state.state)],
                   "statusword": int(state.statusword),
                   "controlword": None if state.controlword is None else int(state.controlword),
                   "velocity": None if velocity is None else float(velocity)})
