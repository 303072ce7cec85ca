"""Bus load of a cyclic CANopen schedule, computed before a run.

Classical CAN (ISO 11898-1) only. A data frame with ``s`` data bytes has ``g + 8s`` bits exposed to bit stuffing
(``g = 34`` for an 11-bit identifier: SOF, identifier, RTR, IDE, r0, DLC and the 15-bit CRC; ``g = 54`` for a 29-bit
one), followed by 13 bits that are never stuffed (CRC delimiter, ACK slot and delimiter, 7 EOF bits, 3 bits of
interframe space). A stuff bit follows every five equal bits, and stuff bits count towards the next run, so at most
``floor((g + 8s - 1) / 4)`` of them are inserted. The worst case is therefore

    ``C(s) = g + 8s + 13 + floor((g + 8s - 1) / 4)``  bits

(Davis, Burns, Bril, Lukkien: "Controller Area Network (CAN) schedulability analysis: refuted, revisited and
revised", Real-Time Systems 35, 2007, eq. 1). A schedule is planned on that worst case, because the payload (and so
the actual stuffing) is not known in advance. (The exact bits of one real frame, CRC-15 computed and stuff bits
inserted, are the benchmark's and the tests' business: ``benchmarks/can_wire.py``, the oracle of this bound.)
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from drivers.cia402_master import PdoPlan
from drivers.errors import ConfigError

__all__ = [
    "DEFAULT_BITRATE",
    "BusLoad",
    "CyclicFrame",
    "drive_schedule",
    "schedule_load",
    "worst_case_bits",
]

_STUFFED_OVERHEAD_STANDARD = 34  # SOF 1 + ID 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + CRC 15
_STUFFED_OVERHEAD_EXTENDED = 54  # SOF 1 + ID 11 + SRR 1 + IDE 1 + ID 18 + RTR 1 + r1 r0 2 + DLC 4 + CRC 15
_UNSTUFFED_TAIL = 13  # CRC delimiter 1 + ACK 2 + EOF 7 + interframe space 3
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

    def to_json(self) -> dict[str, Any]:
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
