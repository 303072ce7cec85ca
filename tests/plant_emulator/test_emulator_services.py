"""The virtual drive's service objects on their own: no bus, no threads, one ``EmulatedNode`` each.

The bus-level behaviour (frames, timing) is covered by ``test_emulator_*``; here each service is driven through
its own methods, which the composition makes possible.
"""

from __future__ import annotations

import threading

import pytest
from canopen.sdo import SdoAbortedError

from drivers.cia301 import RPDO_BASES, EmcyCode, ErrorRegister, FunctionCode, NmtCommand, SdoAbortCode, cob_id
from drivers.cia402 import AbortConnectionOption, Command402, Controlword, Obj, State402
from drivers.pdo import MappingEntry
from plant_emulator.application import Cia402Application, FaultKind
from plant_emulator.axis import Axis, Units
from plant_emulator.node import EmulatedNode, load_object_dictionary
from plant_emulator.pdo_engine import PdoEngine
from plant_emulator.sdo_guard import SdoGuard
from plant_emulator.settings import EmulatorConfig
from tests.support.emulator_harness import ABORT_REACTIONS

NODE_ID = 3


@pytest.fixture
def node() -> EmulatedNode:
    emulated = EmulatedNode(NODE_ID, load_object_dictionary(NODE_ID))
    emulated.reset_store(None)
    return emulated


def _raw(node: EmulatedNode, index: int, subindex: int, value: int) -> bytes:
    return node.variable(index, subindex).encode_raw(value)


def _abort_code(guard: SdoGuard, node: EmulatedNode, index: int, subindex: int, value: int) -> int | None:
    try:
        guard.validate_write(index, subindex, node.variable(index, subindex), _raw(node, index, subindex, value))
    except SdoAbortedError as exc:
        return int(exc.code)
    return None


def test_node_produce_saturates_at_the_object_type(node: EmulatedNode) -> None:
    node.produce(Obj.STATUSWORD, 70_000)  # UNSIGNED16
    assert node.read(Obj.STATUSWORD) == 0xFFFF
    node.produce(Obj.VELOCITY_ACTUAL_VALUE, -1e12)  # INTEGER32
    assert node.read(Obj.VELOCITY_ACTUAL_VALUE) == -(1 << 31)


def test_sdo_guard_refuses_what_a_drive_refuses(node: EmulatedNode) -> None:
    guard = SdoGuard(node, threading.RLock())
    statusword = MappingEntry(Obj.STATUSWORD, 0, 16).encode()
    assert _abort_code(guard, node, Obj.RPDO_MAPPING, 1, statusword) == SdoAbortCode.CANNOT_MAP  # read-only
    assert _abort_code(guard, node, Obj.TPDO_MAPPING, 1, statusword) is None  # readable: fine in a TPDO
    wrong_size = MappingEntry(Obj.STATUSWORD, 0, 32).encode()
    assert _abort_code(guard, node, Obj.TPDO_MAPPING, 1, wrong_size) == SdoAbortCode.GENERAL_PARAMETER
    missing = MappingEntry(0x5FFF, 0, 16).encode()
    assert _abort_code(guard, node, Obj.TPDO_MAPPING, 1, missing) == SdoAbortCode.NO_OBJECT
    assert _abort_code(guard, node, Obj.MODES_OF_OPERATION, 0, 1) == SdoAbortCode.VALUE_TOO_LOW  # below the EDS min
    assert _abort_code(guard, node, Obj.MODES_OF_OPERATION, 0, 8) == SdoAbortCode.INVALID_VALUE  # csp: unsupported
    assert _abort_code(guard, node, Obj.MODES_OF_OPERATION, 0, 9) is None  # csv
    assert _abort_code(guard, node, Obj.QUICK_STOP_OPTION, 0, 9) == SdoAbortCode.VALUE_TOO_HIGH  # the EDS max
    node.variable(Obj.QUICK_STOP_OPTION).max = None  # an EDS without limits: CiA 402 defines 0..8 only
    assert _abort_code(guard, node, Obj.QUICK_STOP_OPTION, 0, 9) == SdoAbortCode.INVALID_VALUE
    assert _abort_code(guard, node, Obj.QUICK_STOP_OPTION, 0, 8) is None


def test_pdo_engine_latches_a_synchronous_rpdo_at_sync(node: EmulatedNode) -> None:
    written: list[tuple[int, int]] = []
    length_errors: list[None] = []
    engine = PdoEngine(node, threading.RLock(), on_write=lambda index, sub: written.append((index, sub)),
                       on_length_error=lambda: length_errors.append(None))
    engine.rebuild()
    node.alive = True
    node.nmt.send_command(NmtCommand.START)
    entries = [MappingEntry.decode(node.read(Obj.RPDO_MAPPING, sub))
               for sub in range(1, node.read(Obj.RPDO_MAPPING, 0) + 1)]
    values: dict[int, int] = {Obj.CONTROLWORD: 0x000F, Obj.TARGET_VELOCITY: -1234}
    frame = b"".join(_raw(node, e.index, e.subindex, values[e.index]) for e in entries)
    rpdo1 = cob_id(RPDO_BASES[0], NODE_ID)

    engine.on_rpdo(rpdo1, bytearray(frame), 0.0)
    assert written == [] and node.read(Obj.CONTROLWORD) != 0x000F  # held until the SYNC
    engine.latch()
    assert node.read(Obj.CONTROLWORD) == 0x000F and node.read(Obj.TARGET_VELOCITY) == -1234
    assert written == [(Obj.CONTROLWORD, 0)]  # the application hears of the controlword, not of the target
    engine.latch()
    assert written == [(Obj.CONTROLWORD, 0)]  # latched once

    engine.on_rpdo(rpdo1, bytearray(frame[:-1]), 0.0)
    engine.latch()
    assert len(length_errors) == 1 and written == [(Obj.CONTROLWORD, 0)]  # a short frame is ignored


def _application(node: EmulatedNode, changes: list[None]) -> Cia402Application:
    application = Cia402Application(node, EmulatorConfig(), Axis(), Units(),
                                    on_state_change=lambda: changes.append(None))
    application.power_on()
    return application


def _command(node: EmulatedNode, application: Cia402Application, controlword: int) -> None:
    node.produce(Obj.CONTROLWORD, controlword)
    application.react(Obj.CONTROLWORD)


def test_application_fault_and_fault_reset(node: EmulatedNode) -> None:
    changes: list[None] = []
    application = _application(node, changes)
    for command in (Command402.SHUTDOWN, Command402.ENABLE_OPERATION):
        _command(node, application, command)
    assert application.machine.state is State402.OPERATION_ENABLED

    application.detect(FaultKind.OVER_CURRENT)
    register = ErrorRegister.GENERIC | ErrorRegister.CURRENT
    assert application.machine.state is State402.FAULT
    assert application.emcy_log[-1] == (EmcyCode.OVER_CURRENT, register)
    assert node.read(Obj.ERROR_CODE) == EmcyCode.OVER_CURRENT and node.read(Obj.ERROR_REGISTER) == register
    assert changes, "a fault must reach the event-driven TPDOs"

    _command(node, application, Controlword.FAULT_RESET)
    assert application.machine.state is State402.SWITCH_ON_DISABLED
    assert application.emcy_log[-1] == (EmcyCode.NO_ERROR, 0)
    assert node.read(Obj.ERROR_CODE) == 0 and node.read(Obj.ERROR_REGISTER) == 0


@pytest.mark.parametrize(
    ("option", "after"),
    ABORT_REACTIONS,
)
def test_application_leaving_operational_applies_0x6007(
    node: EmulatedNode, option: AbortConnectionOption, after: State402
) -> None:
    application = _application(node, [])
    node.produce(Obj.ABORT_CONNECTION_OPTION, int(option))
    application.left_operational()  # not powered: nothing happens
    assert application.machine.state is State402.SWITCH_ON_DISABLED and application.emcy_log == []
    for command in (Command402.SHUTDOWN, Command402.ENABLE_OPERATION):
        _command(node, application, command)
    application.left_operational()
    assert application.machine.state is after
    assert application.emcy_log[-1][0] == EmcyCode.COMMUNICATION
    assert node.read(Obj.ERROR_CODE) == EmcyCode.COMMUNICATION  # latched even without a fault (0x6007 = 0)


@pytest.mark.parametrize("request_byte", [
    0xA4,  # block upload initiate (ccs 5, CRC supported, cs 0)
    0xC6,  # block download initiate (ccs 6, CRC, size indicated, cs 0)
])
def test_sdo_block_requests_are_aborted_with_0x05040001(node: EmulatedNode, monkeypatch: pytest.MonkeyPatch,
                                                       request_byte: int) -> None:
    guard = SdoGuard(node, threading.RLock())
    node.alive = True  # as a started drive (device.VirtualDrive.start)
    responses: list[bytes] = []
    monkeypatch.setattr(node.sdo, "send_response", lambda data: responses.append(bytes(data)))
    # a raw request for 0x1018 sub 2 (bytes 1..3: index little-endian, subindex), block size 127
    request = bytearray([request_byte, 0x18, 0x10, 0x02, 127, 0, 0, 0])
    guard.on_request(cob_id(FunctionCode.SDO_RX, NODE_ID), request, 0.0)
    # CiA 301 abort: command 0x80, the request's multiplexer, code 0x05040001 (all little-endian)
    assert responses == [bytes([0x80, 0x18, 0x10, 0x02, 0x01, 0x00, 0x04, 0x05])]


def test_a_repeated_controlword_ends_where_the_table_driven_machine_does(node: EmulatedNode) -> None:
    """The application skips a controlword it just applied without effect; over a long seeded mix of repeated
    controlwords (with and without the fault-reset bit), faults, communication aborts under every 0x6007 reaction
    and quick stop option changes, its state must stay the one a bare ``PowerStateMachine`` reaches when it is fed
    every controlword and event in full (the reference skips nothing)."""
    import random

    from plant_emulator.state_machine import MotionKind, PowerStateMachine

    rng = random.Random(9)
    application = _application(node, [])
    reference = PowerStateMachine(quick_stop_option=application.machine.quick_stop_option)
    reference.power_on()
    words = [0x0006, 0x0007, 0x000F, 0x0000, 0x0002, 0x0080, 0x008F, 0x0086]
    word = words[0]
    for step in range(2000):
        event = rng.random()
        if event < 0.75:  # mostly controlwords, half of them the previous one again (what a cyclic master sends)
            word = word if rng.random() < 0.5 else rng.choice(words)
            _command(node, application, word)
            reference.apply_controlword(word)
        elif event < 0.85:
            option = rng.choice([AbortConnectionOption.FAULT, AbortConnectionOption.DISABLE_VOLTAGE,
                                 AbortConnectionOption.QUICK_STOP])
            node.produce(Obj.ABORT_CONNECTION_OPTION, int(option))
            application.detect(FaultKind.HEARTBEAT_LOSS)
            if option is AbortConnectionOption.FAULT:
                reference.fault()
                if reference.motion() is MotionKind.TORQUE_OFF:
                    reference.ramp_finished()
            else:
                voltage_off = option is AbortConnectionOption.DISABLE_VOLTAGE
                reference.apply_controlword(Command402.DISABLE_VOLTAGE if voltage_off else Command402.QUICK_STOP)
        elif event < 0.92:
            application.detect(FaultKind.OVER_CURRENT)
            reference.fault()
            if reference.motion() is MotionKind.TORQUE_OFF:
                reference.ramp_finished()
        else:
            quick_stop = rng.choice([0, 1, 2, 5, 6])
            node.produce(Obj.QUICK_STOP_OPTION, quick_stop)
            application.react(Obj.QUICK_STOP_OPTION)
            reference.quick_stop_option = quick_stop
        assert application.machine.state is reference.state, f"step {step}"
