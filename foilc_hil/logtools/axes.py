"""Logs of several axes (``axes:`` runs): which axes a log has, and one axis's view of it.

A run of several axes writes every ``/ilc/sample`` and ``/ilc/trial`` message with ``axis`` (the node id), and per
axis its own config and design (``foilc_hil.axis.<node>.config`` / ``.design``, :mod:`foilc_hil.io.schemas`).
:func:`axis_view` turns such a log into the log a single-axis run of that axis would have written -- its messages,
its config and its design in the places the log tools read -- so ``replay --verify``, ``report`` and ``export``
handle each axis with the single-axis code. A log without ``axis`` fields (every single-axis log) has no axes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from foilc_hil.errors import LogFormatError
from foilc_hil.io.schemas import METADATA_AXIS_PREFIX, METADATA_CONFIG, METADATA_DESIGN, METADATA_PDO_MAPPING
from foilc_hil.logtools.audit import check_closing, promises_closing
from foilc_hil.logtools.replay import Divergence, Verification, verify_log

if TYPE_CHECKING:
    from foilc_hil.io.mcap_log import LogContents

__all__ = ["AxisVerification", "axis_view", "log_axes", "verify_axes"]


def log_axes(contents: LogContents) -> tuple[int, ...]:
    """The node ids of the axes the log's samples and trials name, in order; ``()`` for a single-axis log."""
    return tuple(sorted({int(record["axis"]) for record in (*contents.samples, *contents.trials) if "axis" in record}))


def axis_view(contents: LogContents, node: int) -> LogContents:
    """The log of axis ``node`` alone: its samples and trials, its config and design as the log's.

    Raises :class:`~foilc_hil.errors.LogFormatError` when the log lacks the axis's config or design record.
    """
    metadata = dict(contents.metadata)
    for kind, name in (("config", METADATA_CONFIG), ("design", METADATA_DESIGN)):
        record = contents.metadata.get(f"{METADATA_AXIS_PREFIX}.{node}.{kind}")
        if record is None:
            raise LogFormatError(f"{contents.path}: no {METADATA_AXIS_PREFIX}.{node}.{kind} metadata for axis {node}")
        metadata[name] = record
    mapping = contents.metadata.get(f"{METADATA_AXIS_PREFIX}.{node}.pdo_mapping")
    if mapping is not None:  # the axis's own PDOs, for the check of its frames
        metadata[METADATA_PDO_MAPPING] = mapping
    return replace(
        contents,
        metadata=metadata,
        samples=[sample for sample in contents.samples if sample.get("axis") == node],
        trials=[trial for trial in contents.trials if trial.get("axis") == node],
    )


@dataclass(frozen=True)
class AxisVerification:
    """``replay --verify`` of one axis: its node id and :func:`~foilc_hil.logtools.replay.verify_log`'s result."""

    node_id: int
    verification: Verification

    def to_json(self) -> dict[str, Any]:
        divergence = self.verification.first_divergence
        return {
            "node_id": self.node_id,
            "verified": self.verification.verified,
            "samples_checked": self.verification.samples_checked,
            "trials_checked": self.verification.trials_checked,
            "first_divergence": divergence.to_json() if divergence is not None else None,
        }


def verify_axes(contents: LogContents) -> tuple[Verification, list[AxisVerification]]:
    """Every axis verified bit for bit on its own law, and the log's closing record; the log's result: verified
    when every axis and the record are, the counts summed, the first divergence of the first axis that has one
    (the record's after them)."""
    axes = [AxisVerification(node, verify_log(axis_view(contents, node), whole_log=False))
            for node in log_axes(contents)]
    failed = [axis.verification for axis in axes if not axis.verification.verified]
    # the writer's record is the whole log's: checked once, on all of it
    closing = check_closing(contents) if promises_closing(contents) and not contents.truncated else None
    if closing is not None:
        failed.append(Verification(False, 0, 0, Divergence(closing.trial, closing.sample, None, closing.logged,
                                                           closing.recomputed, closing.reason, closing.topic)))
    total = Verification(
        verified=not failed,
        samples_checked=sum(axis.verification.samples_checked for axis in axes),
        trials_checked=min((axis.verification.trials_checked for axis in axes), default=0),
        first_divergence=failed[0].first_divergence if failed else None,
    )
    return total, axes
