"""What to inject and when: the ``inject:`` entries and ``--inject KIND@WHEN[:KEY=VALUE,...]`` (:class:`Injection`).

The configuration side of :mod:`drivers.faults`, kept apart from its bus (:class:`drivers.faults.FaultyBus`) so that
reading a config does not import python-can: ``foilc_hil.config`` validates ``inject:`` with these types, and every
command loads a config, ``synthesize`` and ``tune`` included. :mod:`drivers.faults` re-exports every name here.

>>> spec = parse_injection("drop-tpdo@2+10:count=3")  # TPDO sets of cycles 10..12 of trial 2 dropped
>>> (spec.kind.value, spec.trial, spec.cycle, spec.count)
('drop-tpdo', 2, 10, 3)
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

from pydantic import Field, model_validator

from drivers.errors import ConfigError, InputError
from drivers.schema import Section, validate

__all__ = [
    "DEFAULT_FRAMES",
    "EMULATOR_KINDS",
    "FIXED_FRAMES",
    "LOOP_KINDS",
    "FrameClass",
    "InjectKind",
    "Injection",
    "InjectionReport",
    "parse_injection",
    "require_actions",
    "split_by_axis",
]


@enum.unique
class InjectKind(StrEnum):
    """The faults that can be injected (the ``kind`` of an :class:`Injection`)."""

    DROP_SYNC = "drop-sync"  # SYNCs lost on the bus
    DROP_RPDO = "drop-rpdo"  # the master's RPDOs lost
    DROP_TPDO = "drop-tpdo"  # the drive's TPDOs lost
    DELAY = "delay"  # frames held back ``delay`` seconds
    REORDER = "reorder"  # a frame swapped with the next one in the same direction
    DUPLICATE = "duplicate"  # frames delivered twice
    WRONG_DLC = "wrong-dlc"  # frames one byte short
    FOREIGN_NODE = "foreign-node"  # another node's TPDO1, heartbeat and EMCY at every SYNC
    SILENCE = "silence"  # nothing passes, either way
    NMT_STOP = "nmt-stop"  # NMT stop for the drive from a third party
    NMT_PRE_OPERATIONAL = "nmt-pre-operational"  # NMT enter pre-operational from a third party
    EMULATOR_KILL = "emulator-kill"  # the emulated drive stops responding (no frame at all, no physics)
    EMCY_OVER_CURRENT = "emcy-over-current"  # the emulated drive detects over-current (EMCY, FAULT)
    EMCY_OVER_SPEED = "emcy-over-speed"  # the emulated drive detects over-speed (EMCY, FAULT)
    HEARTBEAT_STOP = "heartbeat-stop"  # the emulated drive's heartbeat producer stops, the rest goes on
    DRIFT = "drift"  # the plant's input gain multiplied by ``factor`` from then on
    STALL = "stall"  # the bench's loop thread alone sleeps ``duration`` seconds in the cycle (its command goes late)


#: kinds carried out by the bench's trial loop itself (``foilc_hil.loop.stalls``), neither by the bus nor the emulator
LOOP_KINDS = frozenset({InjectKind.STALL})

#: kinds carried out by the emulator (:func:`plant_emulator.faults.emulator_actions`), not by the bus
EMULATOR_KINDS = frozenset(
    {
        InjectKind.EMULATOR_KILL,
        InjectKind.EMCY_OVER_CURRENT,
        InjectKind.EMCY_OVER_SPEED,
        InjectKind.HEARTBEAT_STOP,
        InjectKind.DRIFT,
    }
)


@enum.unique
class FrameClass(StrEnum):
    """Which frames of the drive's node a frame fault hits."""

    SYNC = "sync"
    RPDO = "rpdo"
    TPDO = "tpdo"
    HEARTBEAT = "heartbeat"
    EMCY = "emcy"
    ANY = "any"


#: the frames a kind hits when the kind itself fixes them
DEFAULT_FRAMES = {
    InjectKind.DROP_SYNC: FrameClass.SYNC,
    InjectKind.DROP_RPDO: FrameClass.RPDO,
    InjectKind.DROP_TPDO: FrameClass.TPDO,
    InjectKind.SILENCE: FrameClass.ANY,
}
#: kinds whose frame class is fixed by the kind itself
FIXED_FRAMES = frozenset(DEFAULT_FRAMES)


class Injection(Section):
    """One fault to inject: ``inject:`` list entries and ``--inject KIND@WHEN[:KEY=VALUE,...]``.

    Attributes
    ----------
    kind
        What (:class:`InjectKind`).
    trial
        The trial it starts in; ``None``: ``cycle`` counts the SYNCs from the bus's first.
    cycle
        SYNCs after the trial's first (or the bus's first) at which it starts.
    count
        SYNC cycles it lasts; ``0``: to the end of the run. Emulator kinds and NMT act once.
    rate
        Frame kinds only: the probability that a frame of the window is hit (a seeded RNG); ``None``: every frame.
    seed
        The seed of ``rate``'s generator.
    frames
        Which frames ``delay``, ``reorder``, ``duplicate`` and ``wrong-dlc`` hit (default ``tpdo``); fixed for the
        drop kinds and ``silence``.
    delay
        Seconds a ``delay`` holds a frame back; the longest a ``reorder`` holds one for the next frame in its
        direction (released on its own after it, so a frame with no successor is late, not lost).
    node
        ``foreign-node``: the foreign node's id (it must differ from the drive's).
    factor
        ``drift``: the factor on the plant's input gain (``b`` of a first-order plant, the torque or velocity gain
        of a PMSM axis); ``-1`` reverses the input's sign.
    axis
        The node id of the axis it acts on (its frames, its emulated drive); ``None``: the first axis (the only
        one of a single-axis run). :func:`split_by_axis` refuses a node id that is not one of the run's axes.
    duration
        ``stall``: seconds the loop thread sleeps in each stalled cycle, between the law's command and its RPDO
        (the SYNC clock goes on meanwhile: the command misses its SYNC). A stall needs a trial
        (``stall@TRIAL+CYCLE``: ``cycle`` is the trial's sample); ``count`` cycles in a row stall.
    """

    kind: InjectKind
    trial: int | None = Field(default=None, ge=1)
    cycle: int = Field(default=0, ge=0)
    count: int = Field(default=1, ge=0)
    rate: float | None = Field(default=None, gt=0, le=1)
    seed: int = 0
    frames: FrameClass | None = None
    delay: float = Field(default=0.005, gt=0, le=10.0)  # seconds (kind delay)
    node: int = Field(default=0x7E, ge=1, le=127)
    factor: float = 2.0
    axis: int | None = Field(default=None, ge=1, le=127)
    duration: float = Field(default=0.005, gt=0, le=1.0)  # seconds (kind stall)

    @model_validator(mode="after")
    def _frames_fit_the_kind(self) -> Injection:
        if self.kind in FIXED_FRAMES and self.frames not in (None, DEFAULT_FRAMES[self.kind]):
            raise ValueError(f"'{self.kind}' hits {DEFAULT_FRAMES[self.kind]} frames; drop 'frames'")
        if self.kind in LOOP_KINDS and self.trial is None:
            raise ValueError(f"'{self.kind}' acts in a trial's cycle: give it as {self.kind}@TRIAL+CYCLE")
        if self.kind in LOOP_KINDS and self.count < 1:
            raise ValueError(f"'{self.kind}' lasts count >= 1 cycles")
        return self

    @property
    def target(self) -> FrameClass:
        """The frames this injection hits."""
        return DEFAULT_FRAMES.get(self.kind, self.frames or FrameClass.TPDO)

    def describe(self) -> str:
        """``KIND@WHEN`` as given on the command line."""
        when = f"c{self.cycle}" if self.trial is None else f"{self.trial}+{self.cycle}"
        return f"{self.kind}@{when}"


def parse_injection(spec: str, *, key: str = "--inject") -> Injection:
    """``KIND@WHEN[:KEY=VALUE,...]`` as an :class:`Injection`; ``WHEN`` is ``TRIAL``, ``TRIAL+CYCLE`` or ``cCYCLE``.

    Raises
    ------
    ConfigError
        Naming ``key`` (and the field) for a spec that does not parse or a value out of range.
    """
    head, _, options = spec.strip().partition(":")
    kind, at, when = head.partition("@")
    if not at or not when:
        raise ConfigError(f"{spec!r} is not KIND@WHEN[:KEY=VALUE,...] (WHEN: TRIAL, TRIAL+CYCLE or cCYCLE)", key=key)
    document: dict[str, object] = {"kind": kind.strip()}
    try:
        if when.startswith("c"):
            document["cycle"] = int(when[1:])
        else:
            trial, _, cycle = when.partition("+")
            document["trial"] = int(trial)
            document["cycle"] = int(cycle) if cycle else 0
    except ValueError:
        raise ConfigError(f"{spec!r}: WHEN must be TRIAL, TRIAL+CYCLE or cCYCLE (integers)", key=key) from None
    for item in filter(None, (part.strip() for part in options.split(","))):
        name, eq, value = item.partition("=")
        if not eq:
            raise ConfigError(f"{spec!r}: option {item!r} is not KEY=VALUE", key=key)
        document[name.strip()] = value.strip()
    try:
        return validate(Injection, document)
    except ConfigError as exc:
        raise ConfigError(exc.message, key=f"{key} {spec}: {exc.key}" if exc.key else key) from None


def require_actions(injections: Sequence[Injection], *, emulator: bool, key: str = "inject") -> None:
    """Refuse emulator kinds when there is no emulator in this process to carry them out (exit 2)."""
    if emulator:
        return
    for index, injection in enumerate(injections):
        if injection.kind in EMULATOR_KINDS:
            raise InputError(
                f"{key}[{index}].kind: '{injection.kind}' acts on the embedded emulator (--emulator embedded); "
                "for a drive in another process give it to plant-emulator --inject"
            )


def split_by_axis(injections: Sequence[Injection], node_ids: Sequence[int], *, key: str = "inject"
                  ) -> dict[int, tuple[Injection, ...]]:
    """Each axis's injections (keyed by node id, in ``node_ids`` order; axes without any left out).

    An injection without ``axis`` goes to the first axis. Raises :class:`InputError` naming ``key[i].axis`` for a
    node id that is not one of ``node_ids`` (exit 2: a fault that would silently act on nothing).
    """
    split: dict[int, list[Injection]] = {}
    for index, injection in enumerate(injections):
        node = node_ids[0] if injection.axis is None else injection.axis
        if node not in node_ids:
            raise InputError(f"{key}[{index}].axis: node {node} is not an axis of this run "
                             f"(axes: {', '.join(str(n) for n in node_ids)})")
        split.setdefault(node, []).append(injection)
    return {node: tuple(split[node]) for node in node_ids if node in split}


@dataclass(frozen=True)
class InjectionReport:
    """What one injection did: whether and when it started, and how many frames it touched."""

    injection: Injection
    started_at_sync: int | None  # the bus's SYNC count when it started; None: never reached
    frames: int  # frames dropped, held, duplicated, shortened or added; 1 for a one-shot action (NMT, emulator)

    def to_json(self) -> dict[str, object]:
        return {
            "inject": self.injection.describe(),
            "kind": str(self.injection.kind),
            "started_at_sync": self.started_at_sync,
            "frames": self.frames,
        }
