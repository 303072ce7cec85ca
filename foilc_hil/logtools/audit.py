"""What ``replay --verify`` holds a log to beyond the law's commands: each ``/ilc/trial`` record against its samples,
the closing record against what the file holds, the config's law against the design's, and the design against the
one the logged config gives.

Each check returns the first :class:`Finding` (the topic, trial and sample where the log disagrees with itself) or
``None``. :mod:`foilc_hil.logtools.replay` runs them; ``docs/interface-additions.md`` ("What replay --verify
proves") lists what they prove and what they cannot.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from foilc_hil.io.schemas import METADATA_CLOSING, METADATA_LAYOUT

if TYPE_CHECKING:
    from foilc_hil.config import Config
    from foilc_hil.io.mcap_log import LogContents

__all__ = [
    "METRIC_KEYS",
    "Finding",
    "check_closing",
    "check_design",
    "check_law_kind",
    "check_trial_record",
    "first_differing_row",
    "promises_closing",
]

#: the /ilc/trial fields recomputed from the trial's samples
METRIC_KEYS = ("sse", "rmse", "max_abs_error", "rmse_learnable", "max_abs_error_learnable", "noise_floor")
_REQUIRED = ("sse", "rmse", "max_abs_error")
#: relative tolerance of a rebuilt design's certified figures (an LMI solver's last digits may differ between
#: machines; the gains the law ran with are checked bit for bit through its commands)
DESIGN_RTOL = 1e-6


@dataclass(frozen=True)
class Finding:
    """Where a log disagrees with itself: the topic (or metadata record), the trial, the sample, why."""

    topic: str
    trial: int
    sample: int
    reason: str
    logged: Any = None
    recomputed: Any = None


def _same(logged: Any, recomputed: Any) -> bool:
    """Equal as the log holds numbers: floats bit for bit through JSON (``null`` for a non-finite one)."""
    if recomputed is None or (isinstance(recomputed, float) and not math.isfinite(recomputed)):
        return logged is None
    if isinstance(logged, bool) or not isinstance(logged, (int, float)):
        return False
    return float(logged) == float(recomputed)


def check_trial_record(record: Mapping[str, Any], metrics: Mapping[str, Any], rows: Sequence[Mapping[str, Any]],
                       limits: tuple[float, float] | None) -> Finding | None:
    """The trial's ``/ilc/trial`` figures against ``metrics`` recomputed from its samples, and ``clamped``
    against the rows' commands outside ``limits``."""
    trial = int(record["trial"])
    for key in METRIC_KEYS:
        # the schema's three always; the later figures where the record has them (older logs lack them)
        if key in metrics and (key in record or key in _REQUIRED) and not _same(record.get(key), metrics[key]):
            return Finding("/ilc/trial", trial, len(rows) - 1, f"{key} is not what the trial's samples give",
                           record.get(key), metrics[key])
    if "clamped" in record and limits is not None:
        controls = [row["control"] for row in rows]
        clamped = sum(1 for u in controls if isinstance(u, (int, float)) and not limits[0] <= u <= limits[1])
        if int(record["clamped"]) != clamped:
            return Finding("/ilc/trial", trial, len(rows) - 1, "clamped is not the count of commands outside "
                           "command_limits", record["clamped"], clamped)
    return None


def first_differing_row(logged: Sequence[Any], recomputed: np.ndarray) -> int | None:
    """The first row whose logged value (scalar or list, ``null`` for NaN) is not ``recomputed``'s bit for bit."""
    for i, value in enumerate(logged):
        row = np.atleast_1d(np.asarray(math.nan if value is None else value, dtype=np.float64)).ravel()
        expected = np.atleast_1d(recomputed[i]).astype(np.float64).ravel()
        # the log writes a non-finite value as null: compare it as the NaN it stands for
        expected = np.where(np.isfinite(expected), expected, math.nan)
        if row.shape != expected.shape or row.tobytes() != expected.tobytes():
            return i
    return None


def _closing(contents: LogContents) -> Mapping[str, Any] | None:
    record = contents.metadata.get(METADATA_CLOSING)
    if record is None:
        return None
    try:
        return {key: json.loads(value) for key, value in record.items()}
    except ValueError:
        return {}


def check_closing(contents: LogContents) -> Finding | None:
    """The closing record (what the writer wrote) against the file: the ``/ilc/trial`` records in order, each
    trial's samples and the ``/can`` messages; trial numbers without gaps. A log without the record was cut."""
    trials = [int(record["trial"]) for record in contents.trials]
    distinct = list(dict.fromkeys(trials))
    if distinct != list(range(1, len(distinct) + 1)):
        missing = next(k for k in range(1, len(distinct) + 2) if k not in distinct)
        return Finding("/ilc/trial", missing, 0, f"trial {missing} is missing (the log has trials {distinct})")
    closing = _closing(contents)
    if closing is None:
        if not promises_closing(contents):
            return None  # written before the writer closed logs with the record: nothing to hold the file against
        return Finding(METADATA_CLOSING, 0, 0, "the log has no closing record, though its layout record says the "
                       "writer closes every log with one")
    for finding in _closing_findings(contents, closing, trials, distinct):
        return finding
    return None


def _closing_findings(contents: LogContents, closing: Mapping[str, Any], trials: list[int],
                      distinct: list[int]) -> Iterator[Finding]:
    written = closing.get("trials")
    if written != trials:
        first = next((k for k in (written or []) if k not in trials), (written or [0])[-1] if written else 0)
        yield Finding(METADATA_CLOSING, int(first), 0, f"the writer wrote /ilc/trial records {written}, the log "
                      f"holds {trials}", written, trials)
    per_trial: dict[int, int] = {}
    for sample in contents.samples:
        per_trial[int(sample["trial"])] = per_trial.get(int(sample["trial"]), 0) + 1
    for trial, count in zip(distinct, closing.get("samples") or [], strict=False):
        if per_trial.get(trial, 0) != count:
            yield Finding("/ilc/sample", trial, 0, f"the writer wrote {count} rows of trial {trial}, the log holds "
                          f"{per_trial.get(trial, 0)}", count, per_trial.get(trial, 0))
    frames = sum(contents.frame_directions.values())
    if str(closing.get("frames")) != str(frames):
        yield Finding("/can", 0, 0, f"the writer wrote {closing.get('frames')} frames, the log holds {frames}",
                      closing.get("frames"), frames)


def promises_closing(contents: LogContents) -> bool:
    """The log's layout record says its writer closes it with the closing record (``foilc_hil.layout``
    ``closing``): its absence is then damage, not age."""
    return contents.metadata.get(METADATA_LAYOUT, {}).get("closing") == "1"


def check_law_kind(config: Config, design: Mapping[str, Any]) -> Finding | None:
    """The config's ``law.kind`` is the law the design was made for (``foilc`` with ``kp = 0`` is IOILC's)."""
    kind = str(getattr(config.law.kind, "value", config.law.kind))
    law = str(design.get("law", kind))
    if kind == law or (kind == "ioilc" and law == "foilc" and design.get("kp") == 0):
        return None
    return Finding("foilc_hil.config", 0, 0, f"law.kind is {kind!r} but the design is {law!r}'s", kind, law)


#: design fields that record how long the design took, not what it is
_TIMES = ("seconds",)
#: the gains the law runs with: rebuilt bit for bit or the design is not the one the config gives
_GAINS = ("law", "kp", "r", "input_delay", "sample_time", "gain_scale", "P", "p1", "p2")
#: what the law runs that designs record since an addition: compared where the log has it (earlier logs lack it)
_ADDED = ("q_filter",)


def check_design(logged: Mapping[str, Any], rebuilt: Mapping[str, Any]) -> Finding | None:
    """The logged design against the one the logged config gives: the gains equal, the certificates within
    :data:`DESIGN_RTOL` (their solver's last digits); the first field that differs."""
    for key in (*_GAINS, *(added for added in _ADDED if added in logged)):
        if key in logged or key in rebuilt:
            path = _differs(logged.get(key), rebuilt.get(key), key, rtol=1e-9)
            if path:
                return Finding("foilc_hil.design", 0, 0, f"{path} is not what the logged config designs",
                               logged.get(key), rebuilt.get(key))
    certificates = logged.get("certificates") or {}
    fresh = rebuilt.get("certificates") or {}
    for key in sorted(set(certificates) | set(fresh)):
        if key in _TIMES or key == "lmi":  # the solver's own diagnostics: not what is certified
            continue
        path = _differs(certificates.get(key), fresh.get(key), f"certificates.{key}", rtol=DESIGN_RTOL)
        if path:
            return Finding("foilc_hil.design", 0, 0, f"{path} is not what the logged config certifies",
                           certificates.get(key), fresh.get(key))
    return None


def _differs(a: Any, b: Any, path: str, *, rtol: float) -> str:
    """The path of the first leaf where ``a`` and ``b`` differ (numbers within ``rtol``), ``""`` if none."""
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        for key in sorted(set(a) | set(b), key=str):
            if key not in _TIMES:
                found = _differs(a.get(key), b.get(key), f"{path}.{key}", rtol=rtol)
                if found:
                    return found
        return ""
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return path
        return next((found for i, (x, y) in enumerate(zip(a, b, strict=True))
                     if (found := _differs(x, y, f"{path}[{i}]", rtol=rtol))), "")
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        return "" if math.isclose(float(a), float(b), rel_tol=rtol, abs_tol=1e-12) else path
    return "" if a == b else path
