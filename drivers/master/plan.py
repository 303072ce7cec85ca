"""What the master configures on a drive for a mode, decided before anything is written (pure functions).

:func:`pdo_plan` gives the PDOs (only objects and PDOs the drive's EDS has), :func:`settings_rows` the objects written
after them, and :func:`interpolation_time_period` the 0x60C2 encoding of the cycle. ``commission`` uses them too, so a
drive ``run`` would refuse is refused there as well.
"""

from __future__ import annotations

from dataclasses import dataclass

from canopen.objectdictionary import ObjectDictionary

from drivers.cia301 import RPDO_BASES, TPDO_BASES, HeartbeatConsumerEntry, cob_id
from drivers.cia402 import Obj, OperationMode
from drivers.config import DriveConfig
from drivers.errors import ConfigError, DriveError
from drivers.master.sdo_client import I8, I16, U8, U16, U32, SdoFormat
from drivers.od import mapped_variable
from drivers.pdo import MappedVariable, PdoDirection, PdoLayout

__all__ = [
    "OPTIONAL_FEEDBACK",
    "PDO_PAYLOAD_BITS",
    "REQUIRED_FEEDBACK",
    "PdoPlan",
    "Setting",
    "demand_object",
    "interpolation_time_period",
    "pdo_plan",
    "settings_rows",
]

REQUIRED_FEEDBACK = (Obj.STATUSWORD, Obj.VELOCITY_ACTUAL_VALUE)
"""Feedback every mode needs: the 402 state and the axis output."""
OPTIONAL_FEEDBACK = (Obj.TORQUE_ACTUAL_VALUE, Obj.POSITION_ACTUAL_VALUE)
"""Feedback mapped when the drive has it (:class:`~drivers.drive.Feedback` has NaN torque / 0 position without)."""
PDO_PAYLOAD_BITS = 64  # a classic CAN PDO carries at most 8 bytes
DEMAND_ECHO_KEY = "drive.demand_echo"  # the config key that asks for the demand echo (named by its refusals)

Setting = tuple[int, int, SdoFormat, int, bool]
"""One object ``configure`` writes after the PDOs: index, sub-index, format, value, optional."""


def interpolation_time_period(sample_time: float) -> tuple[int, int]:
    """0x60C2 (interpolation time period) encoding of ``sample_time`` seconds: ``(value, exponent)`` with
    ``sample_time = value * 10**exponent``.

    The largest exponent (-1 .. -6) giving an exact integer ``1 <= value <= 255`` is chosen. Raises
    :class:`ConfigError` when none does (e.g. 0.3 ms needs value 3, exponent -4: fine; 1.2345 ms: none).
    """
    for exponent in range(-1, -7, -1):
        value = sample_time / 10.0**exponent
        if 1 <= round(value) <= 255 and abs(value - round(value)) <= 1e-9 * value:
            return round(value), exponent
    raise ConfigError(f"{sample_time} s is not expressible in 0x60C2 (1..255 x 10^-1..10^-6 s)", key="sample_time")


@dataclass(frozen=True, slots=True)
class PdoPlan:
    """The PDOs the master configures on one drive for one mode, and what it left out (and why).

    Attributes
    ----------
    rpdos, tpdos
        The layouts ``configure`` writes (numbers the drive's EDS has, in order).
    notes
        One line per optional object or PDO the drive lacks, e.g. ``"0x6077 not mapped: ..."``.
    """

    rpdos: tuple[PdoLayout, ...]
    tpdos: tuple[PdoLayout, ...]
    notes: tuple[str, ...] = ()


def _pdo_numbers(od: ObjectDictionary | None, communication: int, mapping: int) -> tuple[int, ...]:
    """PDO numbers 1..4 whose communication and mapping objects the EDS describes (all four without an EDS)."""
    numbers = range(1, len(TPDO_BASES) + 1)
    if od is None:
        return tuple(numbers)
    return tuple(n for n in numbers if communication + n - 1 in od and mapping + n - 1 in od)


def _pack_feedback(groups: list[list[MappedVariable]], slots: int) -> tuple[list[list[MappedVariable]], list[int]]:
    """The feedback groups in ``slots`` PDOs: one group per PDO while PDOs remain, else first fit in 8 bytes.

    Returns the PDO contents and the objects that fit nowhere (the caller decides whether they were optional).
    """
    if len(groups) <= slots:
        return groups, []
    bins: list[list[MappedVariable]] = [[] for _ in range(slots)]
    dropped: list[int] = []
    for variable in (v for group in groups for v in group):
        fit = next((b for b in bins if sum(v.bits for v in b) + variable.bits <= PDO_PAYLOAD_BITS), None)
        if fit is None:
            dropped.append(variable.index)
        else:
            fit.append(variable)
    return [b for b in bins if b], dropped


def demand_object(mode: OperationMode) -> Obj:
    """The object that echoes ``mode``'s latched target: 0x6074 torque demand in CST, else 0x606B velocity demand
    value (in the target's units: 0x6071's, 0x60FF's)."""
    return Obj.TORQUE_DEMAND if mode is OperationMode.CYCLIC_SYNC_TORQUE else Obj.VELOCITY_DEMAND_VALUE


def _place_demand(contents: list[list[MappedVariable]], spare: int, demand: MappedVariable,
                  node_id: int) -> list[list[MappedVariable]]:
    """``contents`` with the demand echo in the first TPDO with room for it, else in a TPDO of its own (``spare``:
    TPDOs the EDS has beyond ``contents``); a :class:`ConfigError` of ``drive.demand_echo`` when neither is."""
    for variables in contents:
        if sum(v.bits for v in variables) + demand.bits <= PDO_PAYLOAD_BITS:
            variables.append(demand)
            return contents
    if spare < 1:
        raise ConfigError(f"node {node_id}: the echo of 0x{demand.index:04X} needs room in a TPDO, and the drive's "
                          f"{len(contents)} TPDO(s) have none left", key=DEMAND_ECHO_KEY)
    return [*contents, [demand]]


def pdo_plan(mode: OperationMode, node_id: int, od: ObjectDictionary | None, *,
             demand_echo: bool = False) -> PdoPlan:
    """The RPDOs and TPDOs the master configures for ``mode`` on a drive described by ``od`` (standard objects).

    RPDO1 = controlword + target (0x60FF for CSV/PV, 0x6071 for CST); TPDO1 = statusword + velocity actual;
    TPDO2 = torque actual + position actual. All synchronous (transmission type 1), default COB-IDs. Only objects
    and PDOs the EDS has are used: a drive without 0x6077 or 0x6064 gets them left out (a note says so), one
    without TPDO2 gets what fits into TPDO1. What the mode truly needs -- controlword, target, statusword, velocity
    actual, an RPDO and a TPDO -- is refused with a :class:`~drivers.errors.DriveError` naming the object.

    ``demand_echo`` (``drive.demand_echo``) also maps the mode's :func:`demand_object` into the first TPDO with
    room for it, else into a TPDO of its own (CSV/PV on the shipped EDS: 0x606B in TPDO3; CST: 0x6074 in TPDO1); a
    drive whose EDS lacks the object, or has no TPDO left for it, is refused with a
    :class:`~drivers.errors.ConfigError` whose key is ``drive.demand_echo`` (exit 2) naming the object. Without it
    the plan is the one above, unchanged.
    """
    target = Obj.TARGET_TORQUE if mode is OperationMode.CYCLIC_SYNC_TORQUE else Obj.TARGET_VELOCITY
    needed = (Obj.CONTROLWORD, target, *REQUIRED_FEEDBACK)
    if od is not None:
        lacking = [f"0x{int(index):04X} ({index.name.lower()})" for index in needed if index not in od]
        if lacking:
            raise DriveError(f"node {node_id}: the drive's EDS lacks {', '.join(lacking)}, which {mode.name} needs")
    rpdo_numbers = _pdo_numbers(od, Obj.RPDO_COMMUNICATION, Obj.RPDO_MAPPING)
    tpdo_numbers = _pdo_numbers(od, Obj.TPDO_COMMUNICATION, Obj.TPDO_MAPPING)
    for kind, numbers, base in (("RPDO", rpdo_numbers, Obj.RPDO_COMMUNICATION),
                                ("TPDO", tpdo_numbers, Obj.TPDO_COMMUNICATION)):
        if not numbers:
            raise DriveError(f"node {node_id}: the drive's EDS has no {kind} (0x{int(base):04X}.. with its mapping), "
                             f"which {mode.name} needs")
    demand = demand_object(mode)
    if demand_echo and od is not None and demand not in od:
        raise ConfigError(f"node {node_id}: the drive's EDS lacks 0x{int(demand):04X} ({demand.name.lower()}), the "
                          f"demand {mode.name} would echo", key=DEMAND_ECHO_KEY)
    notes = [f"0x{int(index):04X} ({index.name.lower()}) not mapped: the drive's EDS lacks it"
             for index in OPTIONAL_FEEDBACK if od is not None and index not in od]
    present = [index for index in OPTIONAL_FEEDBACK if od is None or index in od]
    groups = [[mapped_variable(od, index) for index in REQUIRED_FEEDBACK]]
    if present:
        groups.append([mapped_variable(od, index) for index in present])
    contents, dropped = _pack_feedback(groups, len(tpdo_numbers))
    room = f"the drive's {len(tpdo_numbers)} TPDO(s) have no room left"
    notes += [f"0x{index:04X} not mapped: {room}" for index in dropped]
    if demand_echo:
        contents = _place_demand(contents, len(tpdo_numbers) - len(contents), mapped_variable(od, demand), node_id)
    rpdo = rpdo_numbers[0]
    rpdos = (PdoLayout(PdoDirection.RPDO, rpdo, cob_id(RPDO_BASES[rpdo - 1], node_id),
                       (mapped_variable(od, Obj.CONTROLWORD), mapped_variable(od, target))),)
    tpdos = tuple(PdoLayout(PdoDirection.TPDO, number, cob_id(TPDO_BASES[number - 1], node_id), tuple(variables))
                  for number, variables in zip(tpdo_numbers, contents, strict=False))
    return PdoPlan(rpdos, tpdos, tuple(notes))


def settings_rows(cfg: DriveConfig, od: ObjectDictionary, mode: OperationMode, sample_time: float) -> list[Setting]:
    """The objects ``configure`` writes after the PDOs, in order: (index, sub, format, value, optional).

    ``sample_time`` (seconds) goes to the drive in its two wire encodings, derived here and nowhere else: 0x1006,
    the communication cycle period, in whole microseconds; 0x60C2, the interpolation time period, as
    :func:`interpolation_time_period`'s ``value x 10^exponent`` seconds.
    """
    consumer = HeartbeatConsumerEntry(cfg.master_node_id, cfg.heartbeat_consumer_ms).encode()
    rows: list[Setting] = [
        (Obj.MODES_OF_OPERATION, 0, I8, int(mode), False),
        (Obj.QUICK_STOP_OPTION, 0, I16, cfg.quick_stop_option, True),  # optional in CiA 402
        (Obj.ABORT_CONNECTION_OPTION, 0, I16, cfg.abort_connection_option, True),  # optional
        (Obj.COMMUNICATION_CYCLE_PERIOD, 0, U32, round(sample_time * 1e6), True),  # optional in CiA 301
    ]
    if Obj.INTERPOLATION_TIME_PERIOD in od:  # cyclic synchronous modes take their cycle from here
        value, exponent = interpolation_time_period(sample_time)
        rows += [
            (Obj.INTERPOLATION_TIME_PERIOD, 1, U8, value, True),
            (Obj.INTERPOLATION_TIME_PERIOD, 2, I8, exponent, True),
        ]
    rows += [
        (Obj.PRODUCER_HEARTBEAT_TIME, 0, U16, cfg.heartbeat_producer_ms, False),
        (Obj.CONSUMER_HEARTBEAT_TIME, 1, U32, consumer, True),  # optional: the drive then cannot watch us
    ]
    return rows
