"""Built-in fault injection: what to inject and when (``inject:`` / ``--inject``), and a bus that does it.

An :class:`Injection` names a fault kind, when it starts and how long it lasts. Its clock is the SYNC: the
position of a frame is the number of SYNCs seen before it, counted from the start of a trial (``trial: T``; the
trial's first SYNC is ``cycle 0``) or, without a trial, from the bus's first SYNC. A fault starts at the first SYNC
at or after its position and lasts ``count`` SYNCs (``0``: to the end of the run); frames between two SYNCs belong
to the cycle of the first.

:class:`FaultyBus` is a ``can.BusABC`` that wraps any other bus (it uses only the inner bus's ``send``, ``recv``
and ``shutdown``) and applies the bus kinds to the frames passing through it in either direction: dropped SYNC,
RPDO or TPDO (every frame of the window, or at a seeded random ``rate``), delayed, reordered and duplicated frames,
a wrong DLC, a foreign node's frames, bus silence, and NMT commands from a third party. The emulator kinds (kill,
EMCY, heartbeat stop, parameter drift) are carried out by a callback the emulator's side provides
(:func:`plant_emulator.faults.emulator_actions`); the bus only says when.

The bus plays one of two roles: :attr:`Role.MASTER` (it wraps the bench's bus: SYNC and RPDOs are sent, TPDOs
received) or :attr:`Role.DRIVE` (it wraps a drive's bus, as ``plant-emulator --inject`` does). Frames a fault
adds for the drive (a third party's NMT) go out on a master's bus and come in on a drive's; frames for the master
(a foreign node) the other way round.

>>> spec = parse_injection("drop-tpdo@2+10:count=3")  # TPDO sets of cycles 10..12 of trial 2 dropped
>>> (spec.kind.value, spec.trial, spec.cycle, spec.count)
('drop-tpdo', 2, 10, 3)
"""

from __future__ import annotations

import collections
import contextlib
import enum
import random
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum

import can

from drivers.cia301 import (
    NMT_COB_ID,
    RPDO_BASES,
    SYNC_COB_ID,
    TPDO_BASES,
    EmcyCode,
    FunctionCode,
    NmtCommand,
    NmtState,
    cob_id,
    split_cob_id,
)
from drivers.errors import ConfigError

# the configuration side lives in drivers.injection (no python-can there: every config load imports it)
from drivers.injection import (
    EMULATOR_KINDS,
    FIXED_FRAMES,
    LOOP_KINDS,
    FrameClass,
    Injection,
    InjectionReport,
    InjectKind,
    parse_injection,
    require_actions,
    split_by_axis,
)

__all__ = [
    "EMULATOR_KINDS",
    "LOOP_KINDS",
    "FaultyBus",
    "FrameClass",
    "InjectKind",
    "Injection",
    "InjectionReport",
    "Role",
    "parse_injection",
    "require_actions",
    "split_by_axis",
]


@enum.unique
class Role(StrEnum):
    """Whose bus a :class:`FaultyBus` wraps."""

    MASTER = "master"
    DRIVE = "drive"


_NMT_COMMANDS = {InjectKind.NMT_STOP: NmtCommand.STOP, InjectKind.NMT_PRE_OPERATIONAL: NmtCommand.ENTER_PRE_OPERATIONAL}
#: the foreign node's EMCY code: a generic error, which the drive's master must not take as its drive's
FOREIGN_EMCY_CODE = EmcyCode.GENERIC


class _Window:
    """One injection's state: its start, end and the frames it touched (guarded by the bus's lock)."""

    def __init__(self, injection: Injection) -> None:
        self.injection = injection
        self.rng = random.Random(injection.seed)
        self.started: int | None = None
        self.frames = 0

    def reached(self, trial: int | None, trial_cycle: int, syncs: int) -> bool:
        """Start now if the position is reached (called at each SYNC); True on the SYNC it starts."""
        if self.started is not None:
            return False
        spec = self.injection
        if spec.trial is None:
            due = syncs - 1 >= spec.cycle
        else:
            due = trial is not None and (trial > spec.trial or (trial == spec.trial and trial_cycle >= spec.cycle))
        if due:
            self.started = syncs
        return due

    def active(self, syncs: int) -> bool:
        if self.started is None:
            return False
        return self.injection.count == 0 or syncs < self.started + self.injection.count

    def hits(self, frame: FrameClass | None) -> bool:
        """Whether this frame is hit (the target matches, and the rate's draw, if any, says so)."""
        target = self.injection.target
        if target is not FrameClass.ANY and target is not frame:  # ANY: every frame, SDO and NMT included
            return False
        rate = self.injection.rate
        return rate is None or self.rng.random() < rate


@dataclass
class _Held:
    """A frame held back: released (sent or received) at ``due`` or after the next frame in its direction."""

    message: can.Message
    outgoing: bool
    due: float
    until_next: bool


class FaultyBus(can.BusABC):
    """A python-can bus that wraps ``inner`` and injects faults into the frames passing through it.

    Parameters
    ----------
    inner
        Any python-can bus; this one owns it (:meth:`shutdown` shuts it down).
    injections
        What to inject.
    node_id
        The drive's node id: which RPDOs, TPDOs, heartbeat and EMCY are "the drive's".
    role
        Whose bus ``inner`` is (see the module docstring).
    actions
        The emulator's actions for :data:`EMULATOR_KINDS`; an injection of such a kind without an action is an
        :class:`InputError` (the emulator is not in this process).
    clock
        ``time.monotonic`` (injected in tests).

    Notes
    -----
    Thread safety: ``send`` runs on any thread, ``recv`` on the Notifier's; the fault state is under one lock,
    which is never held while the inner bus sends or receives or while an action runs. Held frames are released by
    the next ``send`` or ``recv`` call after they fall due (no thread of its own); a receive wait is shortened to
    the next due frame.
    """

    def __init__(
        self,
        inner: can.BusABC,
        injections: Sequence[Injection],
        *,
        node_id: int,
        role: Role = Role.MASTER,
        actions: Mapping[InjectKind, Callable[[Injection], None]] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._actions = dict(actions or {})
        require_actions([i for i in injections if i.kind not in self._actions], emulator=False)
        for injection in injections:
            if injection.kind is InjectKind.FOREIGN_NODE and injection.node == node_id:
                raise ConfigError(f"must differ from the drive's node id {node_id}", key="inject.node")
            if injection.kind in LOOP_KINDS:  # the loop's own (foilc_hil.loop.stalls): nothing a bus can do
                raise ConfigError(f"'{injection.kind}' acts in the bench's loop, not on the bus", key="inject.kind")
        self._inner = inner
        self._node_id = node_id
        self._role = role
        self._clock = clock
        self._lock = threading.Lock()
        self._windows = [_Window(injection) for injection in injections]
        self._held: list[_Held] = []
        self._ready: collections.deque[can.Message] = collections.deque()
        self._syncs = 0
        self._trial: int | None = None
        self._trial_cycle = -1
        self.channel_info = f"faults({getattr(inner, 'channel_info', inner)})"
        super().__init__(channel=self.channel_info)

    # --- the clock ------------------------------------------------------------------------------------------------

    def begin_trial(self, trial: int) -> None:
        """Trial ``trial`` starts with the next SYNC (the bench calls this just before a trial's first SYNC)."""
        with self._lock:
            self._trial = trial
            self._trial_cycle = -1

    def reports(self) -> list[InjectionReport]:
        """What each injection did so far."""
        with self._lock:
            return [InjectionReport(w.injection, w.started, w.frames) for w in self._windows]

    # --- can.BusABC -----------------------------------------------------------------------------------------------

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` through the faults (it may be dropped, held, doubled or shortened)."""
        for message in self._filter(msg, outgoing=True):
            self._inner.send(message, timeout)
        self._release_due(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else self._clock() + timeout
        while True:
            self._release_due(None)
            with self._lock:
                if self._ready:
                    return self._ready.popleft(), False
                wait = self._next_wait(deadline)
            msg = self._inner.recv(wait)
            if msg is not None:
                passed = self._filter(msg, outgoing=False)
                with self._lock:
                    self._ready.extend(passed)
                continue
            if deadline is not None and self._clock() >= deadline:
                with self._lock:
                    return (self._ready.popleft() if self._ready else None), False

    def shutdown(self) -> None:
        """Send what is still held back, then shut the inner bus down."""
        if self._is_shutdown:
            return
        with self._lock:
            held, self._held = self._held, []
        for item in held:
            if item.outgoing:
                self._send_quietly(item.message)
        super().shutdown()
        self._inner.shutdown()

    # --- the faults -----------------------------------------------------------------------------------------------

    def _filter(self, msg: can.Message, *, outgoing: bool) -> list[can.Message]:
        actions: list[tuple[Callable[[Injection], None], Injection]] = []
        with self._lock:
            passed = self._filter_locked(msg, outgoing=outgoing, actions=actions)
        for action, injection in actions:  # outside the lock: an action takes the emulator's own lock
            action(injection)
        return passed

    def _filter_locked(
        self, msg: can.Message, *, outgoing: bool, actions: list[tuple[Callable[[Injection], None], Injection]]
    ) -> list[can.Message]:
        """The frames that pass now for ``msg`` (caller holds the lock); the rest is held or dropped."""
        frame = self._classify(msg)
        if frame is FrameClass.SYNC:
            self._tick(actions)
        passed = [msg]
        for window in self._windows:
            if not window.active(self._syncs) or not passed:
                continue
            passed = self._apply(window, frame, passed, outgoing=outgoing)
        self._release_reordered(outgoing=outgoing, into=passed)
        return passed

    def _tick(self, actions: list[tuple[Callable[[Injection], None], Injection]]) -> None:
        """A SYNC passes: advance the clock, start what is due, add the frames of the faults that add frames."""
        self._syncs += 1
        self._trial_cycle += 1
        for window in self._windows:
            if window.reached(self._trial, self._trial_cycle, self._syncs):
                kind = window.injection.kind
                if kind in self._actions:  # run by the caller once the lock is released
                    actions.append((self._actions[kind], window.injection))
                    window.frames = 1
                elif kind in _NMT_COMMANDS:
                    self._add_frame(self._nmt_frame(_NMT_COMMANDS[kind]), to_drive=True)
                    window.frames = 1
            if window.injection.kind is InjectKind.FOREIGN_NODE and window.active(self._syncs):
                for foreign in self._foreign_frames(window):
                    self._add_frame(foreign, to_drive=False)
                window.frames += 3

    def _apply(self, window: _Window, frame: FrameClass | None, passed: list[can.Message], *, outgoing: bool
               ) -> list[can.Message]:
        """One active window's effect on the frames that pass so far."""
        kind = window.injection.kind
        if kind in EMULATOR_KINDS or kind in _NMT_COMMANDS or kind is InjectKind.FOREIGN_NODE:
            return passed
        if not window.hits(frame):
            return passed
        window.frames += len(passed)
        if kind in FIXED_FRAMES:  # drop-sync, drop-rpdo, drop-tpdo, silence
            return []
        if kind is InjectKind.DUPLICATE:
            return [message for message in passed for _ in range(2)]
        if kind is InjectKind.WRONG_DLC:
            return [_one_byte_short(message) for message in passed]
        due = self._clock() + window.injection.delay
        self._held.extend(_Held(message, outgoing, due, kind is InjectKind.REORDER) for message in passed)
        return []

    def _release_reordered(self, *, outgoing: bool, into: list[can.Message]) -> None:
        """A frame passed in this direction: the reordered frames held for it follow it."""
        if not into:
            return
        keep: list[_Held] = []
        for item in self._held:
            if item.until_next and item.outgoing == outgoing:
                into.append(item.message)
            else:
                keep.append(item)
        self._held = keep

    def _release_due(self, timeout: float | None) -> None:
        now = self._clock()
        with self._lock:
            due = [item for item in self._held if item.due <= now]
            self._held = [item for item in self._held if item.due > now]
            self._ready.extend(item.message for item in due if not item.outgoing)
        for item in due:
            if item.outgoing:
                self._inner.send(item.message, timeout)

    def _next_wait(self, deadline: float | None) -> float | None:
        now = self._clock()
        waits = [item.due - now for item in self._held]
        if deadline is not None:
            waits.append(deadline - now)
        return max(0.0, min(waits)) if waits else None

    def _send_quietly(self, message: can.Message) -> None:
        with contextlib.suppress(can.CanError):  # shutting down: a held frame that cannot go out is simply lost
            self._inner.send(message)

    def _add_frame(self, message: can.Message, *, to_drive: bool) -> None:
        """Add a frame from a third party: out on the bus when it is for the other end, else received here."""
        # due now, so the next release puts it right after the frame being filtered (the SYNC that started it)
        outgoing = to_drive == (self._role is Role.MASTER)
        self._held.append(_Held(message, outgoing, self._clock(), False))

    # --- frames ---------------------------------------------------------------------------------------------------

    def _classify(self, msg: can.Message) -> FrameClass | None:
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            return None
        if msg.arbitration_id == SYNC_COB_ID:
            return FrameClass.SYNC
        function, node = split_cob_id(msg.arbitration_id)
        if node != self._node_id:
            return None
        if function in RPDO_BASES:
            return FrameClass.RPDO
        if function in TPDO_BASES:
            return FrameClass.TPDO
        if function == FunctionCode.HEARTBEAT:
            return FrameClass.HEARTBEAT
        if function == FunctionCode.EMCY:
            return FrameClass.EMCY
        return None

    def _nmt_frame(self, command: NmtCommand) -> can.Message:
        return can.Message(arbitration_id=NMT_COB_ID, data=[int(command), self._node_id], is_extended_id=False)

    @staticmethod
    def _foreign_frames(window: _Window) -> list[can.Message]:
        node = window.injection.node
        payload = bytes(window.rng.getrandbits(8) for _ in range(8))
        emcy = int(FOREIGN_EMCY_CODE).to_bytes(2, "little") + bytes(6)
        return [
            can.Message(arbitration_id=cob_id(FunctionCode.TPDO1, node), data=payload, is_extended_id=False),
            can.Message(arbitration_id=cob_id(FunctionCode.HEARTBEAT, node), data=[int(NmtState.OPERATIONAL)],
                        is_extended_id=False),
            can.Message(arbitration_id=cob_id(FunctionCode.EMCY, node), data=emcy, is_extended_id=False),
        ]


def _one_byte_short(msg: can.Message) -> can.Message:
    """``msg`` with its last data byte cut off (a frame of no data gets one byte instead)."""
    data = bytes(msg.data)[:-1] if msg.dlc else b"\x00"
    return can.Message(arbitration_id=msg.arbitration_id, data=data, is_extended_id=msg.is_extended_id,
                       timestamp=msg.timestamp)
