"""What the wire says: a trial's ``/can`` frames held against its ``/ilc/sample`` rows (``replay --verify``).

A run's ``/ilc/trial`` records carry ``first_sync``: the count of the trial's first SYNC among the SYNC frames the
bench sent, which the log holds in order (the frame tap logs every frame from the drive's connect on). Cycle ``i``
of the trial (``i = 0 .. N``) is the window of frames from its SYNC to the next one: the drive's TPDO set answering
that SYNC, then the bench's RPDO. So, with the PDO mapping the run installed (``foilc_hil.pdo_mapping``) and the
drive section of the logged config:

- the velocity in cycle ``i``'s TPDO is the feedback the law was given at sample ``i`` (``initial_output`` for
  ``i = 0``, the previous row's ``output`` after it): ``raw / drive.velocity_scale``, bit for bit, taken from the
  first complete set of the node's TPDOs in the window (every TPDO of the mapping, of the mapping's length; a later
  frame of one TPDO replaces the earlier before the set completes), as the master assembles its feedback; a cycle
  without a complete set (none, or one whose TPDOs straddle the next SYNC) is a lost feedback, for which the law
  was given the last good value again (``lost_feedback`` counts them), and so is one whose set the loop stopped
  waiting for (SYNC from the loop only: it stops before the next deadline), recognised by the law's input being
  the held value and not the set's;
- the bench sends one RPDO per cycle, in order, each after its cycle's SYNC: the ``j``-th of the node's RPDOs from
  the trial's first SYNC on is cycle ``j``'s, never in a window before its own (SYNC from a clock: a late one lands
  in a later window, a missed deadline); its target (``j < N``) is the row's ``control`` as the bench sent it:
  clamped to ``/ilc/trial`` ``command_limits`` and to the drive's limit, scaled and rounded (the master's
  ``set_target``); cycle ``N``'s is the zero command that ends the trial;
- ``latched`` (where the log has it): row ``i``'s is the target of the last RPDO before SYNC ``i + 1`` of the trial
  (the end of cycle ``i``'s window), in plant units (``raw / scale``, as the bench divides), bit for bit: the
  command the drive latched at that SYNC;
- a frame of the node's TPDOs whose length is not the mapping's is a bad frame (``bad_frames`` counts them);
- where the mapping carries the drive's demand echo (``drive.demand_echo``: 0x606B in CSV/PV, 0x6074 in CST, in the
  TPDO set like any other TPDO of the node), the echo in the set answering SYNC ``i + 1`` is held against row
  ``i``'s ``latched`` (without that column: the last RPDO before that SYNC), ``raw / scale`` bit for bit, and the
  samples where they differ are counted, a cycle without its set (a lost feedback) not; ``/ilc/trial``
  ``demand_mismatches`` must be that count (and present: the loop writes it whenever the echo is mapped).

Logs without ``first_sync`` (offline runs, logs written before it) have no wire to check; the caller says so.
"""

from __future__ import annotations

import base64
import itertools
import math
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from drivers.cia301 import SYNC_COB_ID
from drivers.cia402 import Obj
from drivers.pdo import PdoLayout
from foilc_hil.errors import LogFormatError

__all__ = ["PdoField", "WireMap", "WireMismatch", "check_trial_wire", "sync_windows", "wire_map"]

#: CiA 402 objects the check reads: target velocity (CSV, PV), target torque (CST), velocity actual value
_TARGET_VELOCITY, _TARGET_TORQUE, _VELOCITY_ACTUAL = 0x60FF, 0x6071, 0x606C


@dataclass(frozen=True)
class PdoField:
    """Where one mapped object sits in a PDO: its COB-ID, bit offset, width and sign."""

    cob_id: int
    offset: int
    bits: int
    signed: bool
    size: int  # the PDO's length in bytes

    def decode(self, data: bytes) -> int:
        raw = int.from_bytes(data, "little") >> self.offset & ((1 << self.bits) - 1)
        return raw - (1 << self.bits) if self.signed and raw >> (self.bits - 1) else raw


@dataclass(frozen=True)
class WireMap:
    """The node's target in its RPDO, its velocity in its TPDO, and how the bench scaled and limited them."""

    target: PdoField
    velocity: PdoField
    tpdo_sizes: Mapping[int, int]  # COB-ID -> bytes, every TPDO of the node
    target_scale: float
    target_limit: float
    velocity_scale: float
    demand: PdoField | None = None  # the mode's demand echo in the TPDO set (drive.demand_echo); None: not mapped


@dataclass(frozen=True)
class WireMismatch:
    """Where the wire disagrees with the samples: the trial, the sample (cycle), what, and both values."""

    trial: int
    sample: int
    reason: str
    logged: Any
    on_wire: Any


def _field(layouts: Sequence[PdoLayout], index: int) -> PdoField | None:
    for layout in layouts:
        offset = 0
        for variable in layout.variables:
            if variable.index == index:
                size = sum(v.bits for v in layout.variables) // 8
                return PdoField(layout.cob_id, offset, variable.bits, variable.signed, size)
            offset += variable.bits
    return None


def wire_map(mapping: Mapping[str, str], drive: Any) -> WireMap:
    """The :class:`WireMap` of the logged mapping record and the config's ``drive`` section."""
    from foilc_hil.io.pdo_mapping import decode_pdo_mapping

    try:
        rpdos, tpdos = decode_pdo_mapping(dict(mapping))
    except (KeyError, TypeError, ValueError) as exc:
        raise LogFormatError(f"metadata foilc_hil.pdo_mapping is malformed: {exc}") from None
    torque = getattr(drive.mode, "value", drive.mode) == "cst"
    target = _field(rpdos, _TARGET_TORQUE if torque else _TARGET_VELOCITY)
    velocity = _field(tpdos, _VELOCITY_ACTUAL)
    demand = _field(tpdos, Obj.TORQUE_DEMAND if torque else Obj.VELOCITY_DEMAND_VALUE)
    if target is None or velocity is None:
        raise LogFormatError("metadata foilc_hil.pdo_mapping maps no target or no velocity actual value")
    return WireMap(
        target=target,
        velocity=velocity,
        tpdo_sizes={layout.cob_id: sum(v.bits for v in layout.variables) // 8 for layout in tpdos},
        target_scale=float(drive.torque_scale if torque else drive.velocity_scale),
        target_limit=float(drive.torque_limit if torque else drive.velocity_limit),
        velocity_scale=float(drive.velocity_scale),
        demand=demand,
    )


@dataclass(frozen=True)
class _Frame:
    cob_id: int
    tx: bool
    data: bytes


def sync_windows(frames: Sequence[Mapping[str, Any]], own: frozenset[int] = frozenset()) -> list[list[_Frame]]:
    """The log's frames cut at each SYNC the bench sent: window ``k - 1`` starts with the ``k``-th SYNC.

    Where the log holds the bus's echo of the bench's own frames (``udp_multicast`` delivers them back, and a bus
    opened with ``receive_own_messages``), the windows are the received frames alone, cut at the SYNC echoes, and
    the echoes of the COB-IDs in ``own`` (the node's RPDO) count as the bench's: one stream, in the order the bus
    delivered it (the frames the bench sent are logged by the sending thread, the ones received by the receive
    thread: two threads, whose order in the log is not the bus's when a SYNC comes from a clock of its own).
    """
    echoed = any(frame.get("dir") == "rx" and int(frame["id"]) == SYNC_COB_ID for frame in frames)
    windows: list[list[_Frame]] = []
    for frame in frames:
        cob, tx = int(frame["id"]), frame.get("dir") == "tx"
        if echoed:
            if tx:
                continue
            tx = cob in own
        if cob == SYNC_COB_ID and (tx or echoed):
            windows.append([])
        elif windows:
            windows[-1].append(_Frame(cob, tx, base64.b64decode(frame.get("data") or "")))
    return windows


def _sent_raw(control: float, limits: tuple[float, float] | None, wire: WireMap) -> int:
    """The target the master sent for the law's ``control``: the bench's limiter, then ``set_target``'s clamp,
    scale and rounding."""
    value = control
    if limits is not None:
        value = min(max(value, limits[0]), limits[1])
    value = min(max(value, -wire.target_limit), wire.target_limit)
    return round(value * wire.target_scale)


def check_trial_wire(
    windows: Sequence[Sequence[_Frame]], record: Mapping[str, Any], inputs: Sequence[float],
    controls: Sequence[float], wire: WireMap, latched: Sequence[float] | None = None,
) -> WireMismatch | None:
    """Hold one trial's ``N + 1`` cycles on the wire against the law's inputs (``N + 1``: ``y_0 .. y_N``), its
    ``N`` commands and (given) the ``N`` commands the drive latched; the first disagreement, or ``None``."""
    trial, first = int(record["trial"]), int(record["first_sync"])
    n = len(controls)
    if first < 1 or first + n > len(windows):
        return WireMismatch(trial, 0, f"/can holds {len(windows)} SYNCs, not the trial's from SYNC {first}",
                            first, len(windows))
    lost = bad = 0
    held = math.nan
    echoes: list[int | None] = []  # cycle i's demand echo (raw), None: no set (or no echo mapped)
    for i in range(n + 1):
        window = windows[first - 1 + i]
        bad += sum(1 for f in window if not f.tx and f.cob_id in wire.tpdo_sizes
                   and len(f.data) != wire.tpdo_sizes[f.cob_id])
        parts = _answer(window, wire)
        raw = wire.velocity.decode(parts[wire.velocity.cob_id]) if parts is not None else None
        # a cycle without its complete TPDO set is a lost feedback: the law was given the last good value again; so
        # is one whose set completed after a loop that sends SYNC itself stopped waiting (the law was given the held
        # value, not the late set's: the count below holds it to the record, so a changed TPDO is still found)
        answered = raw is not None
        y = raw / wire.velocity_scale if raw is not None else held
        if answered and _bits(y) != _bits(inputs[i]) and _bits(held) == _bits(inputs[i]):
            answered, y = False, held
        lost += not answered
        held = y
        echoes.append(wire.demand.decode(parts[wire.demand.cob_id])
                      if answered and parts is not None and wire.demand is not None else None)
        if not (math.isnan(y) and not answered) and _bits(y) != _bits(inputs[i]):
            what = "the TPDO's velocity" if answered else "the value held for a lost TPDO"
            return WireMismatch(trial, i, f"{what} is not the feedback the law was given", inputs[i], y)
    mismatch = _check_commands(windows, record, controls, wire, latched)
    if mismatch is not None:
        return mismatch
    for key, count in (("lost_feedback", lost), ("bad_frames", bad)):
        if key in record and int(record[key]) != count:
            return WireMismatch(trial, n, f"/ilc/trial {key} is {record[key]}, the wire shows {count}",
                                record[key], count)
    return _check_demand(windows, record, echoes, wire, latched)


def _check_demand(windows: Sequence[Sequence[_Frame]], record: Mapping[str, Any], echoes: Sequence[int | None],
                  wire: WireMap, latched: Sequence[float] | None) -> WireMismatch | None:
    """``/ilc/trial`` ``demand_mismatches`` against the count on the wire: row ``i``'s echo (in the set answering
    SYNC ``i + 1``, ``echoes[i + 1]``) against its ``latched``, else the last RPDO before that SYNC."""
    trial, n = int(record["trial"]), len(echoes) - 1
    if wire.demand is None:
        if "demand_mismatches" in record:
            return WireMismatch(trial, n, "/ilc/trial has demand_mismatches, the PDO mapping no demand echo",
                                record["demand_mismatches"], None)
        return None
    count = 0
    on_wire = _latched_on_wire(windows, int(record["first_sync"]) - 1, n, wire)
    for i, last in enumerate(on_wire):
        echo = echoes[i + 1]
        if echo is None:
            continue  # no set answered the SYNC: no echo to compare (the loop counts none either)
        if latched is not None:
            expected = _bits(float(latched[i]))
        elif last is not None:
            expected = _bits(last / wire.target_scale)
        else:
            continue  # no RPDO before the trial in the log: nothing to hold it against
        count += _bits(echo / wire.target_scale) != expected
    if "demand_mismatches" not in record or int(record["demand_mismatches"]) != count:
        logged = record.get("demand_mismatches")
        return WireMismatch(trial, n, f"/ilc/trial demand_mismatches is {logged}, the wire shows {count}", logged,
                            count)
    return None


def _answer(window: Sequence[_Frame], wire: WireMap) -> dict[int, bytes] | None:
    """The first complete TPDO set in ``window`` (each TPDO's frame by COB-ID), assembled as the master does;
    None: none.

    The master's feedback is the node's whole TPDO set (every mapped TPDO,
    :meth:`drivers.master.cyclic.CyclicPath.on_tpdo`): each frame of the right length replaces its TPDO's part,
    the set is the feedback once every TPDO has a part, and the loop takes the first one. A velocity TPDO alone is
    not an answer: the drive's TPDOs of one SYNC may straddle the next SYNC (the velocity before it, the rest
    after), and the loop, which waits until that next SYNC, was given the held value.
    """
    parts: dict[int, bytes] = {}
    for frame in window:
        if frame.tx or len(frame.data) != wire.tpdo_sizes.get(frame.cob_id, -1):
            continue  # the bench's own frames, other nodes', and bad frames (counted apart): no part of the set
        parts[frame.cob_id] = frame.data
        if len(parts) == len(wire.tpdo_sizes):
            return parts
    return None


def _rpdos(windows: Sequence[Sequence[_Frame]], wire: WireMap, start: int) -> Iterator[tuple[int, int]]:
    """``(window, target)`` of the node's RPDOs the bench sent, from window ``start`` on, in order."""
    cob, target = wire.target.cob_id, wire.target
    return ((w, target.decode(f.data)) for w in range(start, len(windows)) for f in windows[w]
            if f.tx and f.cob_id == cob and len(f.data) == target.size)


def _check_commands(windows: Sequence[Sequence[_Frame]], record: Mapping[str, Any], controls: Sequence[float],
                    wire: WireMap, latched: Sequence[float] | None) -> WireMismatch | None:
    """The trial's ``N + 1`` RPDOs (module docstring) against its commands, and its ``latched`` column against the
    last RPDO before each SYNC."""
    trial, first = int(record["trial"]), int(record["first_sync"])
    limits = tuple(record["command_limits"]) if "command_limits" in record else None
    n, start = len(controls), first - 1
    # after the last trial's zero command the stop's own RPDOs may follow: only the trial's N + 1 count
    sent = list(itertools.islice(_rpdos(windows, wire, start), n + 1))
    if len(sent) != n + 1:
        return WireMismatch(trial, len(sent), f"/can holds {len(sent)} RPDOs from the trial's first SYNC on, not "
                            f"{n + 1}", n + 1, len(sent))
    for j, (window, raw) in enumerate(sent):
        if window < start + j:  # before its own SYNC: not this cycle's (an RPDO too many)
            return WireMismatch(trial, j, "an RPDO in the cycle before its command's SYNC", start + j, window)
        expected = _sent_raw(controls[j], limits, wire) if j < n else 0
        if raw != expected:
            logged = controls[j] if j < n else 0.0
            return WireMismatch(trial, j, "the RPDO's target is not the logged control as the bench sends it",
                                logged, raw / wire.target_scale)
    return None if latched is None else _check_latched(windows, trial, start, latched, wire)


def _last_rpdo(window: Sequence[_Frame], wire: WireMap, last: int | None) -> int | None:
    """The target of the node's last RPDO in ``window``; ``last`` when it has none."""
    cob, target = wire.target.cob_id, wire.target
    for frame in window:
        if frame.tx and frame.cob_id == cob and len(frame.data) == target.size:
            last = target.decode(frame.data)
    return last


def _latched_on_wire(windows: Sequence[Sequence[_Frame]], start: int, n: int, wire: WireMap) -> Iterator[int | None]:
    """For rows ``0 .. n - 1``: the target of the last RPDO before SYNC ``i + 1`` of the trial whose first SYNC opens
    window ``start`` (what the drive latched there), raw; None while the log holds no RPDO before it."""
    last: int | None = None
    for w in range(start):  # the RPDO the drive held when the trial began
        last = _last_rpdo(windows[w], wire, last)
    for i in range(n):
        last = _last_rpdo(windows[start + i], wire, last)
        yield last


def _check_latched(windows: Sequence[Sequence[_Frame]], trial: int, start: int, latched: Sequence[float],
                   wire: WireMap) -> WireMismatch | None:
    """Row ``i``'s ``latched`` against the last RPDO in the windows up to ``start + i`` (before SYNC ``i + 1``)."""
    for i, (logged, last) in enumerate(zip(latched, _latched_on_wire(windows, start, len(latched), wire), strict=True)):
        if last is None:
            continue  # no RPDO before the trial in the log: nothing to hold it against
        on_wire = last / wire.target_scale
        if _bits(on_wire) != _bits(float(logged)):
            return WireMismatch(trial, i, "latched is not the last RPDO's target before the sample's SYNC", logged,
                                on_wire)
    return None


def _bits(value: float) -> bytes:
    """A float's IEEE 754 bits (``-0.0`` and ``0.0`` differ, NaNs compare by their payload)."""
    return struct.pack("<d", value)
