"""Playing a log back: its CAN frames onto a bus in their original timing, and its learning law bit for bit.

Frames
------
:func:`select_frames` picks the ``/can`` frames to re-emit (direction ``tx`` by default -- what the bench sent --,
a time window relative to the log's first frame, optional arbitration ids; never an error frame); :func:`play_frames`
sends them with their original relative timing scaled by ``rate``, each on an absolute deadline from one start
instant (no drift accumulates, a late frame does not delay the following ones' deadlines).

Verification
------------
:func:`verify_log` rebuilds the law the run used (``make_law`` from the ``foilc_hil.design`` and
``foilc_hil.config`` metadata), feeds it the logged feedback sample by sample, and checks every command against the
logged ``control`` bit for bit (float64 bytes, so ``-0.0 != 0.0`` and NaN payloads count). Between trials it calls
``end_trial`` with the trial's output array ``output[i] = y((i+1) Ts)``. Where those come from depends on the
``/ilc/sample`` layout (:data:`foilc_hil.io.schemas.SAMPLE_LAYOUT`, metadata ``foilc_hil.layout``):

- layout 2 (every field of row ``i`` at ``(i + 1) Ts``): the law's input at sample ``i`` is row ``i - 1``'s
  output, at sample 0 the trial's ``initial_output`` (``/ilc/trial``); the output array is the rows' outputs.
- layout 1 (logs written before layout 2; no ``foilc_hil.layout`` record): row ``i``'s output is the law's input
  at sample ``i``; the output array is the feedback of samples ``1 .. N-1`` plus the trial's ``final_output``. A
  log without ``final_output`` gets the last entry from the logged error: a float ``y`` with
  ``fl(reference - y) == error`` bit for bit, found within a few ulps of ``reference - error``; the law sees
  exactly the logged error either way (it learns from ``reference - output``).

Either way every row must satisfy ``error == reference - output[i]`` bit for bit.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from foilc_hil.errors import FoilcHilError, InputError, LogFormatError
from foilc_hil.logtools.audit import (
    Finding,
    check_closing,
    check_design,
    check_law_kind,
    check_trial_record,
    first_differing_row,
    promises_closing,
)
from foilc_hil.logtools.wire import WireMap, check_trial_wire, sync_windows, wire_map

if TYPE_CHECKING:
    import can

    from foilc_hil.config import Config
    from foilc_hil.io.mcap_log import LogContents
    from foilc_hil.metrics import NoiseFloorTracker

__all__ = [
    "Divergence",
    "LawLike",
    "Playback",
    "Verification",
    "law_from_log",
    "logged_config",
    "play_frames",
    "select_frames",
    "verify_log",
]


# --- frames ---------------------------------------------------------------------------------------------------


def select_frames(
    frames: Sequence[Mapping[str, Any]],
    *,
    directions: Iterable[str] = ("tx",),
    start: float = 0.0,
    duration: float | None = None,
    ids: Iterable[int] | None = None,
) -> list[Mapping[str, Any]]:
    """The ``/can`` records to replay, in log order.

    Parameters
    ----------
    frames
        ``/can`` records (:attr:`foilc_hil.io.mcap_log.LogContents.frames`).
    directions
        ``"tx"`` (what the bench sent; the default), ``"rx"``, or both.
    start, duration
        Window in seconds from the log's first frame (any direction): ``start <= t - t0 < start + duration``.
    ids
        Arbitration ids to keep (``None``: all).
    """
    if start < 0:
        raise InputError(f"--start: must be >= 0, got {start}")
    if duration is not None and duration <= 0:
        raise InputError(f"--duration: must be > 0, got {duration}")
    if not frames:
        return []
    wanted_dirs = set(directions)
    wanted_ids = None if ids is None else set(ids)
    t0 = min(float(frame["timestamp"]) for frame in frames)
    end = math.inf if duration is None else start + duration
    selected = []
    for frame in frames:
        offset = float(frame["timestamp"]) - t0
        if frame["dir"] not in wanted_dirs or not start <= offset < end or frame.get("error"):
            continue  # an error frame is a bus event, never a frame to transmit
        if wanted_ids is not None and int(frame["id"]) not in wanted_ids:
            continue
        selected.append(frame)
    return selected


@dataclass(frozen=True)
class Playback:
    """What :func:`play_frames` did: frames sent, wall-clock duration, and the worst lateness of a send."""

    frames_sent: int
    duration: float
    max_lateness: float


def play_frames(
    bus: can.BusABC,
    frames: Sequence[Mapping[str, Any]],
    *,
    rate: float = 1.0,
    clock: Callable[[], float] = time.perf_counter,
    sleep: Callable[[float], None] = time.sleep,
) -> Playback:
    """Send ``frames`` on ``bus`` with their logged relative timing divided by ``rate``.

    Frame ``k`` is due at ``t_start + (timestamp_k - timestamp_0) / rate``, an absolute deadline: sleeping
    too long before one frame shortens the wait before the next instead of shifting the rest of the log.
    """
    from foilc_hil.io.mcap_log import frame_to_message

    if not rate > 0 or not math.isfinite(rate):
        raise InputError(f"--rate: must be a positive number, got {rate}")
    if not frames:
        return Playback(0, 0.0, 0.0)
    messages = [frame_to_message(frame) for frame in frames]  # decode before the clock starts
    first = messages[0].timestamp
    started = clock()
    worst = 0.0
    for message in messages:
        due = started + (message.timestamp - first) / rate
        wait = due - clock()
        if wait > 0:
            sleep(wait)
        worst = max(worst, clock() - due)
        message.timestamp = 0.0  # the bus stamps what it sends
        bus.send(message)
    return Playback(len(messages), clock() - started, worst)


# --- verification ---------------------------------------------------------------------------------------------


class LawLike(Protocol):
    """The part of :class:`foilc_hil.laws.learning.LearningLaw` that verification drives."""

    n_samples: int

    def begin_trial(self) -> None: ...

    def command(self, t: int, output: np.ndarray) -> np.ndarray: ...

    def end_trial(self, reference: np.ndarray, output: np.ndarray, applied: np.ndarray | None = None) -> Any: ...


@dataclass(frozen=True)
class Divergence:
    """The first sample whose recomputed command differs from the log (or why verification stopped)."""

    trial: int
    sample: int
    t: float | None
    logged: Any
    recomputed: Any
    reason: str
    topic: str = "/ilc/sample"  # or "/can", "/ilc/trial", a metadata record: where the log disagrees

    def to_json(self) -> dict[str, Any]:
        return {
            "topic": self.topic,
            "trial": self.trial,
            "sample": self.sample,
            "t": self.t,
            "logged": _json_number(self.logged),
            "recomputed": _json_number(self.recomputed),
            "logged_hex": _hex(self.logged),
            "recomputed_hex": _hex(self.recomputed),
            "reason": self.reason,
        }


@dataclass(frozen=True)
class Verification:
    """Result of :func:`verify_log`."""

    verified: bool
    samples_checked: int
    trials_checked: int
    first_divergence: Divergence | None


def _as_vector(value: Any) -> np.ndarray | None:
    """A logged signal as a 1-D float64 array (``null`` -> NaN); ``None`` if it is not numeric."""
    try:
        return np.atleast_1d(np.asarray(value if value is not None else math.nan, dtype=np.float64)).ravel()
    except (TypeError, ValueError):
        return None


def _bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.tobytes() == b.tobytes()


def _json_number(value: Any) -> Any:
    array = _as_vector(value)
    if array is None:
        return None
    items = [x if math.isfinite(x) else repr(x) for x in array.tolist()]
    return items[0] if len(items) == 1 else items


def _hex(value: Any) -> Any:
    array = _as_vector(value)
    if array is None:
        return None
    items = [float(x).hex() for x in array.tolist()]
    return items[0] if len(items) == 1 else items


def _output_for_error(reference: float, error: float) -> float | None:
    """A float ``y`` with ``reference - y == error`` exactly (float64), searched around ``reference - error``."""
    guess = reference - error
    candidates = [guess]
    up = down = guess
    for _ in range(8):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, -math.inf)
        candidates += [up, down]
    for y in candidates:
        if struct.pack("<d", reference - y) == struct.pack("<d", error):
            return y
    return None


def logged_config(contents: LogContents) -> Config:
    """The run's :class:`~foilc_hil.config.Config` from the ``foilc_hil.config`` metadata.

    Raises
    ------
    LogFormatError
        The log lacks the record, or it does not load (the message says which).
    """
    import yaml

    from foilc_hil.config import Config
    from foilc_hil.schema import load_yaml_text, validate

    config_yaml = contents.config_yaml
    if config_yaml is None:
        raise LogFormatError(f"{contents.path}: no foilc_hil.config metadata; --verify needs the run's config")
    try:
        document = load_yaml_text(config_yaml) or {}  # a log is input too: the same bounds as a config file
    except yaml.YAMLError as exc:
        raise LogFormatError(f"{contents.path}: metadata foilc_hil.config is not YAML: {exc}") from None
    if not isinstance(document, dict):
        raise LogFormatError(f"{contents.path}: metadata foilc_hil.config is not a mapping")
    return validate(Config, document, source=f"{contents.path} (foilc_hil.config)")


def law_from_log(contents: LogContents, n_samples: int) -> LawLike:
    """Rebuild the run's law from the log's metadata.

    With a ``foilc_hil.design`` record: ``make_law(design, config.law, n_samples, limits=...)`` (the design names
    the law that ran), with the command limits the bench logged in ``/ilc/trial`` (``command_limits``; none in
    offline logs, whose laws do not clamp). Without one (an offline P-type run written before P-type designs were
    logged): the P-type design of the config's nominal model from the design pipeline
    (:func:`foilc_hil.design.pipeline.build_design`, no input delay), which gives the same gain.

    Raises
    ------
    LogFormatError
        The log lacks the records it needs, or they do not load (the message says which).
    """
    from foilc_hil.config import LawKind
    from foilc_hil.laws.learning import make_law

    config = logged_config(contents)
    design_doc = contents.design
    if design_doc is None:
        if config.law.kind is not LawKind.P_TYPE:
            raise LogFormatError(
                f"{contents.path}: no foilc_hil.design metadata; --verify needs the design the {config.law.kind} "
                "run used"
            )
        from foilc_hil.design.pipeline import build_design

        return make_law(build_design(config, LawKind.P_TYPE, n_samples, input_delay=0), config.law, n_samples)
    from foilc_hil.design.record import Design, with_logged_q_filter

    try:
        design = Design.from_json(design_doc)
    except InputError as exc:
        raise LogFormatError(f"{contents.path}: metadata foilc_hil.design: {exc}") from None
    return make_law(with_logged_q_filter(design, design_doc, config.law.q_filter), config.law, n_samples,
                    limits=_logged_limits(contents))


def _logged_limits(contents: LogContents) -> tuple[float, float] | None:
    """The ``command_limits`` the bench logged with each trial (the same for all), or ``None`` (offline run)."""
    found = {tuple(trial["command_limits"]) for trial in contents.trials if "command_limits" in trial}
    if not found:
        return None
    if len(found) > 1:
        raise LogFormatError(f"{contents.path}: /ilc/trial command_limits differ between trials: {sorted(found)}")
    limits = found.pop()
    if len(limits) != 2 or not all(isinstance(value, (int, float)) for value in limits):
        raise LogFormatError(f"{contents.path}: /ilc/trial command_limits must be [lower, upper], got {list(limits)}")
    return float(limits[0]), float(limits[1])


def _group_samples(samples: Sequence[Mapping[str, Any]]) -> dict[int, list[Mapping[str, Any]]]:
    trials: dict[int, list[Mapping[str, Any]]] = {}
    for sample in samples:
        trials.setdefault(int(sample["trial"]), []).append(sample)
    for rows in trials.values():
        if all("sample" in row for row in rows):
            rows.sort(key=lambda row: int(row["sample"]))
    return trials


def samples_per_trial(contents: LogContents) -> int:
    """``N``: the sample count of the log's completed trials (they all have the same)."""
    grouped = _group_samples(contents.samples)
    complete = {len(grouped.get(trial, [])) for trial in contents.completed_trials}
    complete.discard(0)
    if len(complete) > 1:
        raise LogFormatError(f"{contents.path}: completed trials have different sample counts {sorted(complete)}")
    if complete:
        return complete.pop()
    if grouped:
        return max(len(rows) for rows in grouped.values())
    raise LogFormatError(f"{contents.path}: no /ilc/sample messages to verify")


def sample_layout(contents: LogContents) -> int:
    """The log's ``/ilc/sample`` layout: ``foilc_hil.layout`` metadata, 1 for logs written before it existed."""
    from foilc_hil.io.schemas import METADATA_LAYOUT, SAMPLE_LAYOUT

    value = contents.metadata.get(METADATA_LAYOUT, {}).get("ilc_sample", "1")
    if value not in ("1", str(SAMPLE_LAYOUT)):
        raise LogFormatError(f"{contents.path}: metadata {METADATA_LAYOUT} names /ilc/sample layout {value!r}; "
                             f"this version reads 1 and {SAMPLE_LAYOUT}")
    return int(value)


def _law_inputs(rows: Sequence[Mapping[str, Any]], record: Mapping[str, Any] | None, layout: int) -> list[Any] | None:
    """The feedback the law was given at each sample of a trial (raw logged values); ``None``: not in the log."""
    if layout == 1:
        return [row["output"] for row in rows]
    if record is None or "initial_output" not in record:
        return None  # layout 2 holds y(0) in /ilc/trial, which a trial cut short by the end of the log lacks
    return [record["initial_output"], *(row["output"] for row in rows[:-1])]


@dataclass
class _Checks:
    """What each trial is held to besides its commands (nothing more where the caller hands in the law)."""

    records: bool  # /ilc/trial figures and E, from the law's own end_trial
    tracker: NoiseFloorTracker | None  # the bench's noise floor of a single-axis log, trial after trial
    wire: WireMap | None  # the node's PDOs, where the log has the mapping and its trials their first SYNC
    windows: list[Any]


def _checks(contents: LogContents, config: Config | None, layout: int) -> _Checks:
    if config is None or layout == 1:  # logs before layout 2: their figures were computed another way
        return _Checks(records=False, tracker=None, wire=None, windows=[])
    from foilc_hil.io.schemas import METADATA_PDO_MAPPING
    from foilc_hil.metrics import NoiseFloorTracker

    several = any("axis" in record for record in contents.trials)  # an axis's records carry no noise floor
    mapping = contents.metadata.get(METADATA_PDO_MAPPING)
    wire = wire_map(mapping, config.drive) if mapping is not None else None
    windows = sync_windows(contents.frames, frozenset({wire.target.cob_id})) if wire is not None else []
    return _Checks(records=True, tracker=None if several else NoiseFloorTracker(), wire=wire, windows=windows)


def verify_log(contents: LogContents, law: LawLike | None = None, *, whole_log: bool = True) -> Verification:
    """Prove what the log claims, as far as it goes (a truncated log as far as it was read).

    Re-runs the learning law on the logged feedback and checks every command bit for bit; holds every trial's
    ``E`` and ``/ilc/trial`` figures against the law's own update, and its ``/can`` frames against its samples
    (:mod:`foilc_hil.logtools.wire`); then the log as a whole (:mod:`foilc_hil.logtools.audit`): the closing
    record (``whole_log``; an axis's view of a log of several is checked as part of the whole), the config's law
    against the design's, and the design against the one the logged config gives.

    Parameters
    ----------
    contents
        The log (:func:`foilc_hil.io.mcap_log.read_log`).
    law
        The law to drive; by default :func:`law_from_log`. A law handed in is checked on its commands alone.
    whole_log
        Check the closing record too (``False`` for one axis's view, :func:`foilc_hil.logtools.axes.verify_axes`).
    """
    grouped = _group_samples(contents.samples)
    if not grouped:
        damage = f" ({contents.damage})" if contents.damage else ""
        raise LogFormatError(f"{contents.path}: no /ilc/sample messages to verify{damage}")
    layout = sample_layout(contents)
    n = samples_per_trial(contents)
    config = None
    if law is None:
        config = logged_config(contents)
        law = law_from_log(contents, n)
    result = _verify_trials(contents, grouped, layout, n, law, _checks(contents, config, layout))
    if not result.verified or config is None:
        return result
    finding = _log_finding(contents, config, n, whole_log)
    if finding is None:
        return result
    return Verification(False, result.samples_checked, result.trials_checked, _divergence(finding))


def _verify_trials(contents: LogContents, grouped: dict[int, list[Mapping[str, Any]]], layout: int, n: int,
                   law: LawLike, checks: _Checks) -> Verification:
    trial_records = {int(record["trial"]): record for record in contents.trials}
    checked = trials_checked = 0
    expected_trial = min(grouped)
    for trial in sorted(grouped):
        if trial != expected_trial:
            return _stop(checked, trials_checked, expected_trial, 0, None, None, None,
                         f"trial {expected_trial} is missing (the next in the log is trial {trial})")
        record = trial_records.get(trial)
        rows, count, divergence, complete = grouped[trial], 0, None, False
        inputs = _law_inputs(rows, record, layout)
        if inputs is not None:
            count, divergence, complete = _verify_trial(trial, rows, record, inputs, layout, n, law, checks)
        checked += count
        if divergence is not None:
            return Verification(False, checked, trials_checked, divergence)
        if not complete:
            break  # the trial in progress when the log ended: nothing to check after it
        trials_checked += 1
        expected_trial = trial + 1
    return Verification(True, checked, trials_checked, None)


def _verify_trial(trial: int, rows: Sequence[Mapping[str, Any]], record: Mapping[str, Any] | None,
                  inputs: list[Any], layout: int, n: int, law: LawLike,
                  checks: _Checks) -> tuple[int, Divergence | None, bool]:
    """One trial: its commands re-run, then (complete) its update and records; rows checked, the first
    divergence, and whether the trial was complete."""
    position = 0
    try:
        law.begin_trial()
        for i, row in enumerate(rows):
            position = i
            if int(row.get("sample", i)) != i:
                return i, _divergence(Finding("/ilc/sample", trial, i, "sample missing")), False
            y = _as_vector(inputs[i])
            logged = _as_vector(row["control"])
            if y is None or logged is None:
                return i, Divergence(trial, i, row.get("t"), row["control"], None, "not numeric"), False
            recomputed = np.asarray(law.command(i, y), dtype=np.float64).ravel()
            if not _bits_equal(recomputed, logged):
                return i, Divergence(trial, i, row.get("t"), logged, recomputed.copy(), "command differs"), False
        if record is None or len(rows) != n:
            return len(rows), None, False
        reference, output, problem, at = _trial_arrays(rows, record, layout)
        if problem:
            return len(rows), Divergence(trial, at, rows[at].get("t"), None, None, problem), False
        # the bench's law learned from what the drive latched (u_{k-1} is what ran): the log's latched, where it has
        latched = _latched(rows)
        update = law.end_trial(reference, output) if latched is None else law.end_trial(reference, output, latched)
    except FoilcHilError as exc:
        return position, Divergence(trial, position, None, None, None, f"the law refused: {exc}"), False
    finding = _trial_finding(trial, rows, record, inputs, update, output, checks)
    return len(rows), _divergence(finding) if finding is not None else None, True


def _trial_finding(trial: int, rows: Sequence[Mapping[str, Any]], record: Mapping[str, Any], inputs: list[Any],
                   update: Any, output: np.ndarray, checks: _Checks) -> Finding | None:
    """A complete trial's ``E``, ``/ilc/trial`` figures and ``/can`` frames against what the law recomputed."""
    if not checks.records:
        return None
    n = len(rows)
    E = np.asarray(update.E, dtype=np.float64).reshape(n, -1)
    at = first_differing_row([row.get("E") for row in rows], E)
    if at is not None:
        return Finding("/ilc/sample", trial, at, "E is not the law's E recomputed from the trial's errors",
                       rows[at].get("E"), E[at].tolist())
    metrics = update.metrics
    if checks.tracker is not None:
        metrics = checks.tracker.measured(metrics, np.asarray(update.error, dtype=np.float64))
    limits = _record_limits(record)
    finding = check_trial_record(record, metrics.to_json(), rows, limits)
    if finding is not None or checks.wire is None or "first_sync" not in record or E.shape[1] != 1:
        return finding
    feedback = [_as_float(value) for value in inputs] + [float(output[-1].ravel()[0])]
    controls = [_as_float(row["control"]) for row in rows]
    latched = [_as_float(row["latched"]) for row in rows] if all("latched" in row for row in rows) else None
    mismatch = check_trial_wire(checks.windows, record, feedback, controls, checks.wire, latched)
    if mismatch is None:
        return None
    return Finding("/can", mismatch.trial, mismatch.sample, mismatch.reason, mismatch.logged, mismatch.on_wire)


def _latched(rows: Sequence[Mapping[str, Any]]) -> np.ndarray | None:
    """The trial's ``latched`` column, ``(N, m)``; ``None`` for a log without it (written before it existed)."""
    if not rows or any("latched" not in row for row in rows):
        return None
    values = [_as_vector(row["latched"]) for row in rows]
    if any(value is None for value in values):
        return None
    return np.array(values, dtype=np.float64)


def _record_limits(record: Mapping[str, Any]) -> tuple[float, float] | None:
    limits = record.get("command_limits")
    return (float(limits[0]), float(limits[1])) if isinstance(limits, list) and len(limits) == 2 else None


def _as_float(value: Any) -> float:
    vector = _as_vector(value)
    return float(vector[0]) if vector is not None and vector.size == 1 else math.nan


def _log_finding(contents: LogContents, config: Config, n: int, whole_log: bool) -> Finding | None:
    """The log as a whole: its closing record, the config's law against the design's, the design rebuilt."""
    if not promises_closing(contents):
        return None  # a log written before these records, or by hand: its commands and figures are what is checked
    if whole_log and not contents.truncated:  # a cut log is reported as partial, the closing record with it
        finding = check_closing(contents)
        if finding is not None:
            return finding
    design = contents.design
    if design is None:
        return None
    return check_law_kind(config, design) or check_design(design, _rebuilt_design(config, design, n))


def _rebuilt_design(config: Config, design: Mapping[str, Any], n: int) -> dict[str, Any]:
    """The design the logged config gives for the logged law and input delay, as the log would hold it."""
    import json

    from foilc_hil.design.pipeline import build_design, model_delay_samples
    from foilc_hil.io.mcap_writer import encode_design

    # the design's input delay is the loop's transport delay plus the plant's own (plant.delay), which the pipeline
    # adds again: the transport delay is what it is given
    transport = int(design.get("input_delay", 0)) - model_delay_samples(config)
    try:
        rebuilt = build_design(config, str(design.get("law")), n, input_delay=transport)
    except FoilcHilError as exc:
        return {"law": f"not designable: {exc}"}
    return {key: json.loads(value) for key, value in encode_design(rebuilt.to_json()).items()}


def _divergence(finding: Finding) -> Divergence:
    return Divergence(finding.trial, finding.sample, None, finding.logged, finding.recomputed, finding.reason,
                      finding.topic)



def _stop(
    checked: int,
    trials_checked: int,
    trial: int,
    sample: int,
    t: Any,
    logged: Any,
    recomputed: Any,
    reason: str,
) -> Verification:
    return Verification(False, checked, trials_checked, Divergence(trial, sample, t, logged, recomputed, reason))


def _trial_arrays(
    rows: Sequence[Mapping[str, Any]], record: Mapping[str, Any], layout: int
) -> tuple[np.ndarray, np.ndarray, str, int]:
    """``end_trial``'s ``(reference, output)`` (module docstring: per layout); or why not, and the sample."""
    reference = np.array([_as_vector(row["reference"]) for row in rows], dtype=np.float64)
    if layout == 1:
        output, problem = _layout1_output(rows, record, reference)
        if problem:
            return reference, reference, problem, len(rows) - 1
    else:
        output = np.array([_as_vector(row["output"]) for row in rows], dtype=np.float64)
    # The log must agree with itself: the error it records is reference - output for every sample.
    for i, row in enumerate(rows):
        logged_error = _as_vector(row["error"])
        if logged_error is None or not _bits_equal(reference[i] - output[i], logged_error):
            return reference, output, f"logged error of sample {i} is not reference - output", i
    return reference, output, "", 0


def _layout1_output(
    rows: Sequence[Mapping[str, Any]], record: Mapping[str, Any], reference: np.ndarray
) -> tuple[np.ndarray, str]:
    """Layout 1: the feedback of samples 1..N-1 plus ``y(N Ts)`` (``final_output``, or found from the error)."""
    seen = [_as_vector(row["output"]) for row in rows]
    final = record.get("final_output")
    if final is not None:
        last = _as_vector(final)
    else:
        error = _as_vector(rows[-1]["error"])
        if error is None:
            return reference, "no final_output and no numeric error to recover y(N Ts)"
        found = [_output_for_error(float(r), float(e)) for r, e in zip(reference[-1], error, strict=True)]
        if any(y is None for y in found):
            return reference, "no final_output, and no float output reproduces the logged error"
        last = np.array(found, dtype=np.float64)
    return np.array([*seen[1:], last], dtype=np.float64), ""
