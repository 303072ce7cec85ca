"""Bus load of a cyclic CANopen schedule: computed before a run, measured from a log afterwards.

Classical CAN (ISO 11898-1) only. A data frame with ``s`` data bytes has ``g + 8s`` bits exposed to bit stuffing
(``g = 34`` for an 11-bit identifier: SOF, identifier, RTR, IDE, r0, DLC and the 15-bit CRC; ``g = 54`` for a 29-bit
one), followed by 13 bits that are never stuffed (CRC delimiter, ACK slot and delimiter, 7 EOF bits, 3 bits of
interframe space). A stuff bit follows every five equal bits, and stuff bits count towards the next run, so at most
``floor((g + 8s - 1) / 4)`` of them are inserted. The worst case is therefore

    ``C(s) = g + 8s + 13 + floor((g + 8s - 1) / 4)``  bits

(Davis, Burns, Bril, Lukkien: "Controller Area Network (CAN) schedulability analysis: refuted, revisited and
revised", Real-Time Systems 35, 2007, eq. 1). A schedule is planned on that worst case, because the payload (and so
the actual stuffing) is not known in advance. :func:`wire_bits` counts the bits of one real frame exactly (CRC-15
computed, stuff bits inserted), which is what a log's measured load uses.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import can

from drivers.cia402_master import PdoPlan
from drivers.errors import ConfigError

__all__ = [
    "DEFAULT_BITRATE",
    "BusLoad",
    "CyclicFrame",
    "crc15",
    "drive_schedule",
    "measured_load",
    "schedule_load",
    "stuffed_bits",
    "wire_bits",
    "worst_case_bits",
]

_STUFFED_OVERHEAD_STANDARD = 34  # SOF 1 + ID 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + CRC 15
_STUFFED_OVERHEAD_EXTENDED = 54  # SOF 1 + ID 11 + SRR 1 + IDE 1 + ID 18 + RTR 1 + r1 r0 2 + DLC 4 + CRC 15
_UNSTUFFED_TAIL = 13  # CRC delimiter 1 + ACK 2 + EOF 7 + interframe space 3
_CRC15_POLY = 0x4599  # x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1
_STUFF_RUN = 5
_CLASSICAL_MAX_DATA = 8
DEFAULT_BITRATE = 1_000_000  # bit/s assumed when the config leaves bus.bitrate unset (the CANopen maximum)
_HEARTBEAT_BYTES = 1  # the NMT state


def worst_case_bits(data_bytes: int, *, extended: bool = False) -> int:
    """Worst-case length on the wire, in bits, of a classical data frame with ``data_bytes`` bytes.

    Includes stuff bits and the 3-bit interframe space (see the module docstring for the formula).
    """
    if not 0 <= data_bytes <= _CLASSICAL_MAX_DATA:
        raise ValueError(f"a classical CAN frame carries 0..8 data bytes, not {data_bytes}")
    stuffed = (_STUFFED_OVERHEAD_EXTENDED if extended else _STUFFED_OVERHEAD_STANDARD) + 8 * data_bytes
    return stuffed + _UNSTUFFED_TAIL + (stuffed - 1) // 4


def crc15(bits: Sequence[int]) -> int:
    """The CAN CRC-15 of a bit sequence (SOF through the last data bit), as ISO 11898-1 computes it."""
    crc = 0
    for bit in bits:
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CRC15_POLY
    return crc


def _bits(value: int, width: int) -> list[int]:
    return [(value >> shift) & 1 for shift in range(width - 1, -1, -1)]


def _stuffed_section(msg: can.Message) -> list[int]:
    """SOF through CRC of a classical frame, before stuffing (dominant = 0)."""
    dlc = msg.dlc
    remote = 1 if msg.is_remote_frame else 0
    if msg.is_extended_id:
        head = [0, *_bits(msg.arbitration_id >> 18, 11), 1, 1, *_bits(msg.arbitration_id & 0x3FFFF, 18), remote,
                0, 0]
    else:
        head = [0, *_bits(msg.arbitration_id, 11), remote, 0, 0]
    head += _bits(dlc, 4)
    if not msg.is_remote_frame:
        for byte in bytes(msg.data)[:dlc]:
            head += _bits(byte, 8)
    return head + _bits(crc15(head), 15)


def stuffed_bits(msg: can.Message) -> list[int]:
    """SOF through CRC of one classical frame as sent: a stuff bit of the opposite value after five equal bits.

    Raises
    ------
    ValueError
        For CAN FD and error frames, which this classical model does not describe.
    """
    if msg.is_fd or msg.is_error_frame:
        raise ValueError("the classical frame model describes data and remote frames only")
    out: list[int] = []
    run_value, run_length = -1, 0
    for bit in _stuffed_section(msg):
        out.append(bit)
        if bit == run_value:
            run_length += 1
        else:
            run_value, run_length = bit, 1
        if run_length == _STUFF_RUN:
            # the stuff bit has the opposite value and starts the next run
            out.append(1 - bit)
            run_value, run_length = 1 - bit, 1
    return out


def wire_bits(msg: can.Message) -> int:
    """Exact length on the wire, in bits, of one classical frame (stuff bits and interframe space included)."""
    return len(stuffed_bits(msg)) + _UNSTUFFED_TAIL


@dataclass(frozen=True, slots=True)
class CyclicFrame:
    """One frame of a cyclic schedule: sent ``per_cycle`` times per SYNC period (fractions for slower frames)."""

    name: str
    data_bytes: int
    per_cycle: float = 1.0
    extended: bool = False

    @property
    def bits(self) -> int:
        """Worst-case bits of one transmission."""
        return worst_case_bits(self.data_bytes, extended=self.extended)


@dataclass(frozen=True, slots=True)
class BusLoad:
    """The worst-case load of a cyclic schedule on a classical CAN bus.

    Attributes
    ----------
    frames
        The schedule.
    bitrate
        Bits per second.
    period
        The SYNC period in seconds.
    limit
        The largest acceptable fraction of the bit rate.
    """

    frames: tuple[CyclicFrame, ...]
    bitrate: int
    period: float
    limit: float

    @property
    def bits_per_cycle(self) -> float:
        """Worst-case bits on the bus per SYNC period."""
        return sum(frame.bits * frame.per_cycle for frame in self.frames)

    @property
    def load(self) -> float:
        """Fraction of the bit rate used (1.0 = saturated)."""
        return self.bits_per_cycle / (self.bitrate * self.period)

    @property
    def fits(self) -> bool:
        """The load is within :attr:`limit`."""
        return self.load <= self.limit * (1 + 1e-12)  # min_period itself must fit despite rounding

    @property
    def min_period(self) -> float:
        """The shortest SYNC period that keeps this schedule within :attr:`limit`, in seconds."""
        return self.bits_per_cycle / (self.bitrate * self.limit)

    def describe(self) -> str:
        """One line with the figures: load, limit, bits per cycle, and the shortest period that would fit."""
        load = f"{self.load:.1%}" if self.load < 100 else f"{100 * self.load:.3g}%"  # 1e300 % as a number
        return (f"bus load {load} of {self.bitrate / 1e3:g} kbit/s at a {self.period * 1e3:g} ms period "
                f"(limit {self.limit:.0%}): {self.bits_per_cycle:g} worst-case bits per cycle in "
                f"{sum(f.per_cycle for f in self.frames):g} frames; a period of at least "
                f"{math.ceil(self.min_period * 1e6) / 1e3:g} ms would fit")

    def check(self, *, key: str = "bus.load_limit") -> BusLoad:
        """Return self if the schedule fits, else raise :class:`ConfigError` naming ``key`` with the figures."""
        if not self.fits:
            raise ConfigError(f"refused: {self.describe()}", key=key)
        return self

    def to_json(self) -> dict[str, object]:
        """The figures as a JSON object (``run --json``'s ``bus_load``)."""
        return {
            "bitrate": self.bitrate,
            "period": self.period,
            "limit": self.limit,
            "bits_per_cycle": self.bits_per_cycle,
            "load": self.load,
            "min_period": self.min_period,
            "frames": [{"name": f.name, "data_bytes": f.data_bytes, "per_cycle": f.per_cycle, "bits": f.bits}
                       for f in self.frames],
        }


def drive_schedule(plan: PdoPlan, *, period: float, drive_heartbeat: float, master_heartbeat: float,
                   name: str = "") -> list[CyclicFrame]:
    """The cyclic frames one drive adds to a SYNC period: its RPDOs and TPDOs (every period, sizes as mapped), its
    heartbeat every ``drive_heartbeat`` s and the master's every ``master_heartbeat`` s (0: none).

    ``name`` prefixes the frame names (e.g. ``"node 2 "``); the SYNC itself is the caller's, once per bus.
    """
    frames = [CyclicFrame(f"{name}{layout.direction.name}{layout.number}", sum(v.bits for v in layout.variables) // 8)
              for layout in (*plan.rpdos, *plan.tpdos)]
    for what, every in (("heartbeat", drive_heartbeat), ("master heartbeat", master_heartbeat)):
        if every > 0:
            frames.append(CyclicFrame(f"{name}{what}", _HEARTBEAT_BYTES, per_cycle=period / every))
    return frames


def schedule_load(frames: Iterable[CyclicFrame], *, bitrate: int, period: float, limit: float = 0.7) -> BusLoad:
    """The worst-case load of ``frames`` repeated every ``period`` seconds on a bus at ``bitrate``."""
    if bitrate <= 0 or not period > 0 or not 0 < limit <= 1:
        raise ValueError(f"need bitrate > 0, period > 0 and 0 < limit <= 1, got {bitrate}, {period}, {limit}")
    return BusLoad(tuple(frames), bitrate, period, limit)


def measured_load(messages: Iterable[can.Message], *, bitrate: int) -> float:
    """The load a log shows: exact wire bits of its classical frames over the span of their timestamps.

    Frames the classical model does not describe (FD, error frames) are left out. Returns 0.0 for fewer than two
    frames (no span to divide by).
    """
    timed = sorted((msg.timestamp, wire_bits(msg)) for msg in messages if not (msg.is_fd or msg.is_error_frame))
    if len(timed) < 2 or timed[-1][0] <= timed[0][0]:
        return 0.0
    # the span runs from the first frame's start to the last frame's start: the last frame's bits lie outside it
    return sum(bits for _, bits in timed[:-1]) / (bitrate * (timed[-1][0] - timed[0][0]))
