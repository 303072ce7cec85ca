"""``commission check``: will ``run`` work on this drive, and why -- before any motion.

The drive is read, never changed: its EDS (``drive.eds``) and the drive itself over SDO (uploads only: no NMT
command, no controlword, no PDO or mode written). The checks are the ones ``run`` makes before it moves anything,
run on what the drive says now:

- **drive**: 0x1000 answers over SDO and names a CiA 402 device (else nothing more is asked); 0x1018 identity;
  the 402 state (a drive in FAULT is refused by ``run``'s enable) and 0x603F.
- **mode**: 0x6502 offers ``drive.mode`` (absent: a warning, ``run`` then tries the mode).
- **objects**: every object ``run`` maps or writes for the mode -- the :meth:`~drivers.cia402_master.Cia402Drive.
  preflight` plan (the same :func:`~drivers.cia402_master.pdo_plan` ``run`` uses) and the settings ``configure``
  writes -- is in the EDS and answers an SDO upload. What the mode needs and the drive lacks fails, naming the
  object; an optional setting the drive lacks is a warning (``run`` skips it), as is every note of the plan
  (optional feedback left unmapped).
- **bus load**: the worst-case load ``run`` checks (:func:`foilc_hil.commands.run.check_bus_load`), passed in.
- **heartbeat/SYNC**: 0x1017 and 0x1016 as ``run`` will set them (off is a warning: a lost drive or master is then
  noticed late), 0x1005 (the drive must consume SYNC on 0x080 and not produce it), 0x1006 exact in microseconds.
- **limits**: ``drive.velocity_limit``/``torque_limit`` times their scales within the target's data type and the
  EDS limits; the drive's own maxima (0x6080, 0x6072) when it has them; the reference's peak within
  ``drive.velocity_limit`` in the velocity modes.

A check that fails means ``run`` would refuse (or fail at start-up) on this drive: :attr:`CheckReport.runnable`.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from drivers.cia301 import COB_ID_INVALID, SYNC_COB_ID, CobIdEntry, emcy_text
from drivers.cia402 import SUPPORTED_MODE_BITS, IdentitySub, Obj, OperationMode, State402, decode_state
from drivers.cia402_master import CIA402_PROFILE, MASTER_HEARTBEATS_PER_CONSUMER_TIME, Cia402Drive
from drivers.od import mapped_variable
from foilc_hil.commission.info import read_optional
from foilc_hil.errors import ConfigError, DriveError, DriveTimeoutError, SdoError

if TYPE_CHECKING:
    from foilc_hil.config import Config

__all__ = ["Check", "CheckReport", "Verdict", "check_drive"]

_SYNC_PRODUCER_BIT = 1 << 30  # 0x1005 bit 30: this node generates SYNC (CiA 301)
_OBJECT = re.compile(r"0x[0-9A-Fa-f]{4}")


@enum.unique
class Verdict(StrEnum):
    """One check's outcome: ``fail`` means ``run`` would refuse the drive."""

    PASS = "pass"
    WARN = "warn"
    FAIL = "fail"


@dataclass(frozen=True)
class Check:
    """One line of the report: what was checked, the object (or config key) it is about, the verdict and why."""

    name: str
    verdict: Verdict
    subject: str  # "0x606C", "0x1016:01", "bus.load_limit", ...
    detail: str

    def to_json(self) -> dict[str, str]:
        return {"check": self.name, "verdict": str(self.verdict), "object": self.subject, "detail": self.detail}

    def render(self) -> str:
        return f"{self.verdict.upper():<4}  {self.name:<9} {self.subject:<20} {self.detail}"


@dataclass(frozen=True)
class CheckReport:
    """Every check of one drive for one mode, in order."""

    node_id: int
    mode: OperationMode
    checks: tuple[Check, ...]

    @property
    def runnable(self) -> bool:
        """No check failed: ``run`` will configure and enable this drive."""
        return all(check.verdict is not Verdict.FAIL for check in self.checks)

    @property
    def failures(self) -> tuple[Check, ...]:
        return tuple(check for check in self.checks if check.verdict is Verdict.FAIL)

    def to_json(self) -> dict[str, Any]:
        counts = {str(verdict): sum(check.verdict is verdict for check in self.checks) for verdict in Verdict}
        return {
            "node_id": self.node_id,
            "mode": self.mode.name,
            "runnable": self.runnable,
            "counts": counts,
            "checks": [check.to_json() for check in self.checks],
        }

    def render(self) -> str:
        lines = [f"node {self.node_id}, {self.mode.name}:", *(check.render() for check in self.checks)]
        counts = self.to_json()["counts"]
        verdict = "run will work" if self.runnable else "run would refuse this drive"
        lines.append(f"{counts['pass']} pass, {counts['warn']} warn, {counts['fail']} fail: {verdict}")
        return "\n".join(lines)


def _hex(index: int, subindex: int | None = None) -> str:
    return f"0x{index:04X}" if subindex is None else f"0x{index:04X}:{subindex:02X}"


def _subject(message: str, default: str) -> str:
    """The first object a refusal names (``"... lacks 0x606C (velocity_actual_value) ..."``), else ``default``."""
    found = _OBJECT.search(message)
    return f"0x{found.group(0)[2:].upper()}" if found else default


def _drive_checks(drive: Cia402Drive) -> Iterator[Check]:
    """0x1000 (a CiA 402 device answering SDO), 0x1018, the 402 state and 0x603F."""
    device_type = drive.read_object(Obj.DEVICE_TYPE)
    profile = device_type & 0xFFFF
    if profile != CIA402_PROFILE:
        yield Check("drive", Verdict.FAIL, _hex(Obj.DEVICE_TYPE),
                    f"device type 0x{device_type:08X}: profile {profile}, not a CiA 402 drive")
        return
    yield Check("drive", Verdict.PASS, _hex(Obj.DEVICE_TYPE), f"device type 0x{device_type:08X} (CiA 402)")
    identity = {sub.name.lower(): read_optional(drive, Obj.IDENTITY, sub) for sub in IdentitySub}
    shown = ", ".join(f"{key} 0x{value:08X}" for key, value in identity.items() if value is not None)
    yield Check("drive", Verdict.PASS, _hex(Obj.IDENTITY), f"identity: {shown or 'no sub-index readable'}")
    statusword = drive.read_object(Obj.STATUSWORD)
    try:
        state = decode_state(statusword)
    except ValueError:
        yield Check("drive", Verdict.FAIL, _hex(Obj.STATUSWORD), f"statusword 0x{statusword:04X} codes no 402 state")
        return
    code = read_optional(drive, Obj.ERROR_CODE) if Obj.ERROR_CODE in drive.od else None
    error = "" if not code else f"; 0x603F = 0x{code:04X} ({emcy_text(code)})"
    if state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
        yield Check("drive", Verdict.FAIL, _hex(Obj.STATUSWORD),
                    f"in {state.name}{error}: run's enable refuses it; `foilc-hil commission fault-reset` first")
    elif state is State402.OPERATION_ENABLED:
        yield Check("drive", Verdict.WARN, _hex(Obj.STATUSWORD),
                    f"OPERATION_ENABLED now{error}: run resets its communication and walks the 402 states again")
    else:
        yield Check("drive", Verdict.PASS, _hex(Obj.STATUSWORD), f"{state.name} (statusword 0x{statusword:04X})")


def _mode_check(drive: Cia402Drive, mode: OperationMode) -> Check:
    bits = read_optional(drive, Obj.SUPPORTED_DRIVE_MODES) if Obj.SUPPORTED_DRIVE_MODES in drive.od else None
    subject = _hex(Obj.SUPPORTED_DRIVE_MODES)
    if bits is None:
        return Check("mode", Verdict.WARN, subject, f"0x6502 absent: run tries {mode.name} unchecked")
    if bits & SUPPORTED_MODE_BITS[mode]:
        return Check("mode", Verdict.PASS, subject, f"0x{bits:08X} offers {mode.name}")
    return Check("mode", Verdict.FAIL, subject, f"0x{bits:08X} does not offer {mode.name}")


def _probe(drive: Cia402Drive, index: int, subindex: int, *, needed: bool, what: str) -> Check:
    """One object ``run`` maps or writes: in the EDS, and answering an SDO upload."""
    subject = _hex(index, subindex)
    missing = Verdict.FAIL if needed else Verdict.WARN
    consequence = "run needs it" if needed else "run skips it (optional)"
    if index not in drive.od:
        return Check("object", missing, subject, f"{what}: the drive's EDS lacks it; {consequence}")
    try:
        value = read_optional(drive, index, subindex)
    except SdoError as exc:
        return Check("object", Verdict.WARN, subject, f"{what}: upload aborted ({exc}); run will write it")
    if value is None:
        return Check("object", missing, subject, f"{what}: in the EDS, but the drive has no such object; "
                     f"{consequence}")
    return Check("object", Verdict.PASS, subject, f"{what}: present (now {value})")


def _plan_checks(drive: Cia402Drive, mode: OperationMode) -> list[Check]:
    """The preflight ``run`` makes, then every object of its plan and settings probed over SDO."""
    try:
        plan = drive.preflight(mode)
    except (DriveError, ConfigError) as exc:
        message = str(exc)
        return [Check("plan", Verdict.FAIL, _subject(message, "PDO plan"), message)]
    mapped = "; ".join(f"{layout.name}: " + ", ".join(_hex(v.index) for v in layout.variables)
                       for layout in (*plan.rpdos, *plan.tpdos))
    checks = [Check("plan", Verdict.PASS, "PDO plan", f"run maps {mapped}")]
    checks += [Check("plan", Verdict.WARN, _subject(note, "PDO plan"), note) for note in plan.notes]
    for layout in (*plan.rpdos, *plan.tpdos):
        checks.append(_probe(drive, layout.communication_index, 1, needed=True, what=f"{layout.name} COB-ID"))
        checks += [_probe(drive, v.index, v.subindex, needed=True, what=f"mapped in {layout.name}")
                   for v in layout.variables]
    for index, subindex, value, optional in drive.settings(mode):
        if optional and index not in drive.od:
            continue  # the plan's notes said so already
        checks.append(_probe(drive, index, subindex, needed=not optional, what=f"run writes {value}"))
    return checks


def _heartbeat_checks(drive: Cia402Drive) -> Iterator[Check]:
    cfg = drive.cfg
    producer = _hex(Obj.PRODUCER_HEARTBEAT_TIME)
    if cfg.heartbeat_producer_ms == 0:
        yield Check("heartbeat", Verdict.WARN, producer, "drive.heartbeat_producer_ms = 0: the drive sends no "
                    "heartbeat, so a lost drive shows only as missing feedback")
    else:
        loss = cfg.heartbeat_timeout_factor * cfg.heartbeat_producer_ms / 1000
        yield Check("heartbeat", Verdict.PASS, producer, f"the drive beats every {cfg.heartbeat_producer_ms} ms; "
                    f"the master declares it lost after {loss:g} s")
    consumer = _hex(Obj.CONSUMER_HEARTBEAT_TIME, 1)
    if cfg.heartbeat_consumer_ms == 0 or Obj.CONSUMER_HEARTBEAT_TIME not in drive.od:
        yield Check("heartbeat", Verdict.WARN, consumer, "the drive will not watch the master's heartbeat "
                    "(0x1016 absent or drive.heartbeat_consumer_ms = 0): a dead master leaves it to its SYNC loss")
    else:
        beat = cfg.heartbeat_consumer_ms / MASTER_HEARTBEATS_PER_CONSUMER_TIME
        yield Check("heartbeat", Verdict.PASS, consumer, f"the drive watches node {cfg.master_node_id} within "
                    f"{cfg.heartbeat_consumer_ms} ms; the master beats every {beat:g} ms")


def _sync_checks(drive: Cia402Drive, sample_time: float) -> Iterator[Check]:
    subject = _hex(Obj.COB_ID_SYNC)
    raw = read_optional(drive, Obj.COB_ID_SYNC) if Obj.COB_ID_SYNC in drive.od else None
    if raw is None:
        yield Check("sync", Verdict.WARN, subject, f"0x1005 absent: the drive is assumed to consume SYNC on "
                    f"0x{SYNC_COB_ID:03X}")
    elif raw & _SYNC_PRODUCER_BIT:
        yield Check("sync", Verdict.FAIL, subject, f"0x{raw:08X}: the drive produces SYNC itself; the master is "
                    "the SYNC producer of a run")
    elif CobIdEntry.decode(raw & ~COB_ID_INVALID).can_id != SYNC_COB_ID:
        yield Check("sync", Verdict.FAIL, subject, f"0x{raw:08X}: the drive consumes SYNC on another COB-ID than "
                    f"the master's 0x{SYNC_COB_ID:03X}")
    else:
        yield Check("sync", Verdict.PASS, subject, f"SYNC consumed on 0x{SYNC_COB_ID:03X}")
    micros = sample_time * 1e6
    period = _hex(Obj.COMMUNICATION_CYCLE_PERIOD)
    if abs(micros - round(micros)) > 1e-6 * micros:
        yield Check("sync", Verdict.WARN, period, f"sample_time {sample_time} s is not a whole number of us: "
                    f"0x1006 gets {round(micros)} us")
    else:
        yield Check("sync", Verdict.PASS, period, f"SYNC every {sample_time:g} s = {round(micros)} us")


def _limit_check(drive: Cia402Drive, target: Obj, limit: float, scale: float, key: str,
                 maximum: Callable[[], int | None]) -> Iterator[Check]:
    """``limit`` (plant units) times ``scale`` against the target's data type, its EDS limits and the drive's
    maximum (``maximum()``, None when the drive has none)."""
    raw = limit * scale
    variable = mapped_variable(drive.od, target)
    top = (1 << (variable.bits - 1)) - 1 if variable.signed else (1 << variable.bits) - 1
    eds_high = getattr(drive.od[target], "max", None) if target in drive.od else None
    if raw > top:
        yield Check("limits", Verdict.FAIL, key, f"{limit:g} x {scale:g} = {raw:g} does not fit {_hex(target)} "
                    f"({variable.bits}-bit)")
        return
    if eds_high is not None and raw > eds_high:
        yield Check("limits", Verdict.WARN, key, f"{raw:g} drive units over the EDS HighLimit {eds_high} of "
                    f"{_hex(target)}: the drive may refuse or clamp")
        return
    drive_max = maximum()
    if drive_max is not None and drive_max > 0 and raw > drive_max:
        yield Check("limits", Verdict.WARN, key, f"{raw:g} drive units over the drive's own maximum {drive_max}: "
                    "it clamps there and the law learns a saturated loop")
        return
    yield Check("limits", Verdict.PASS, key, f"{limit:g} (= {raw:g} drive units) fits {_hex(target)}")


def _limit_checks(drive: Cia402Drive, config: Config, mode: OperationMode) -> Iterator[Check]:
    from foilc_hil.references import reference_profile

    cfg = drive.cfg

    def own_maximum(index: Obj) -> Callable[[], int | None]:
        return lambda: read_optional(drive, index) if index in drive.od else None

    if mode is OperationMode.CYCLIC_SYNC_TORQUE:
        yield from _limit_check(drive, Obj.TARGET_TORQUE, cfg.torque_limit, cfg.torque_scale, "drive.torque_limit",
                                own_maximum(Obj.MAX_TORQUE))
        return
    yield from _limit_check(drive, Obj.TARGET_VELOCITY, cfg.velocity_limit, cfg.velocity_scale,
                            "drive.velocity_limit", lambda: None)
    peak = float(abs(reference_profile(config.reference, config.sample_time)).max())
    if peak > cfg.velocity_limit:
        yield Check("limits", Verdict.WARN, "reference", f"peaks at {peak:g}, over drive.velocity_limit "
                    f"{cfg.velocity_limit:g}: the command clamps before the output can follow")
    else:
        yield Check("limits", Verdict.PASS, "reference", f"peaks at {peak:g} within drive.velocity_limit "
                    f"{cfg.velocity_limit:g}")


def check_drive(drive: Cia402Drive, config: Config, bus_load: Check) -> CheckReport:
    """Every check of the module docstring on ``drive`` (listening, never reset) for ``drive.cfg``'s mode.

    ``bus_load`` is the bus-load check, made by the caller with ``run``'s own function. A drive that does not
    answer SDO is one failed check (nothing else can be asked).
    """
    mode = drive.cfg.operation_mode
    checks: list[Check] = []
    try:
        checks += _drive_checks(drive)
    except DriveTimeoutError as exc:
        checks.append(Check("drive", Verdict.FAIL, _hex(Obj.DEVICE_TYPE), str(exc)))
    if any(check.verdict is Verdict.FAIL and check.subject == _hex(Obj.DEVICE_TYPE) for check in checks):
        return CheckReport(drive.node_id, mode, (*checks, bus_load))
    checks.append(_mode_check(drive, mode))
    checks += _plan_checks(drive, mode)
    checks.append(bus_load)
    checks += _heartbeat_checks(drive)
    checks += _sync_checks(drive, config.sample_time)
    checks += _limit_checks(drive, config, mode)
    return CheckReport(drive.node_id, mode, tuple(checks))


def bus_load_check(describe: str, verdict: Verdict) -> Check:
    """The line of the bus-load check (its figures: :meth:`drivers.busload.BusLoad.describe`, or the refusal)."""
    return Check("bus load", verdict, "bus.load_limit", describe)
