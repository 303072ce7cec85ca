"""A minimal CiA 402 slave built ONLY from canopen's ``LocalNode`` and the EDS (no emulator code), for the master's
tests (``tests/drivers/test_master_localnode.py``, ``test_master_faults.py``, ``test_master_startup_trace.py``).

:class:`MiniServo` is canopen's SDO server and NMT slave, plus what ``LocalNode`` leaves to the application: the
boot-up after an NMT reset, RPDO reception applied at SYNC, the 402 state machine (statusword follows controlword per
the CiA 402-2 transition table), TPDOs sent on SYNC from whatever mapping the master wrote, and the PDO-configuration
rules of CiA 301 (mapping only while the PDO is disabled, only PDO-mappable objects, EDS limits); and fault hooks.
"""

from __future__ import annotations

import struct
import threading
from pathlib import Path

import can
import canopen
from canopen.objectdictionary import ODVariable, datatypes
from canopen.sdo import SdoAbortedError

from drivers.cia301 import (
    RPDO_BASES,
    SYNC_COB_ID,
    EmcyCode,
    ErrorRegister,
    NmtCommand,
    SdoAbortCode,
    cob_id,
)
from drivers.cia402 import (
    STATE_STATUSWORD,
    Command402,
    Controlword,
    Obj,
    State402,
    Statusword,
    decode_command,
)
from drivers.config import DriveConfig
from drivers.od import DEFAULT_EDS
from drivers.pdo import PDO_DISABLED, MappingEntry

NODE_ID = 5
VELOCITY_SCALE = 1000.0  # plant unit rpm -> 0.001 rpm counts, as the EDS documents

_FORMATS = {
    datatypes.INTEGER8: "b",
    datatypes.INTEGER16: "h",
    datatypes.INTEGER32: "i",
    datatypes.UNSIGNED8: "B",
    datatypes.UNSIGNED16: "H",
    datatypes.UNSIGNED32: "I",
}


def transition(state: State402, controlword: int, previous_controlword: int) -> State402:
    """CiA 402-2 device control: the state after ``controlword`` (quick stop option 5..8: stays in QSA)."""
    command = decode_command(controlword)
    if state is State402.FAULT:
        rising = controlword & Controlword.FAULT_RESET and not previous_controlword & Controlword.FAULT_RESET
        return State402.SWITCH_ON_DISABLED if rising else state
    if command is Command402.FAULT_RESET or command is None:
        return state
    if command is Command402.DISABLE_VOLTAGE:
        return State402.SWITCH_ON_DISABLED
    if command is Command402.QUICK_STOP:
        if state is State402.OPERATION_ENABLED:
            return State402.QUICK_STOP_ACTIVE
        return State402.SWITCH_ON_DISABLED if state is not State402.QUICK_STOP_ACTIVE else state
    if state is State402.QUICK_STOP_ACTIVE:
        return State402.OPERATION_ENABLED if command is Command402.ENABLE_OPERATION else state
    table = {
        (State402.SWITCH_ON_DISABLED, Command402.SHUTDOWN): State402.READY_TO_SWITCH_ON,
        (State402.READY_TO_SWITCH_ON, Command402.SWITCH_ON): State402.SWITCHED_ON,
        (State402.SWITCHED_ON, Command402.ENABLE_OPERATION): State402.OPERATION_ENABLED,
        (State402.SWITCHED_ON, Command402.SHUTDOWN): State402.READY_TO_SWITCH_ON,
        (State402.OPERATION_ENABLED, Command402.SWITCH_ON): State402.SWITCHED_ON,  # disable operation
        (State402.OPERATION_ENABLED, Command402.SHUTDOWN): State402.READY_TO_SWITCH_ON,
    }
    return table.get((state, command), state)


class MiniServo:
    """A CiA 402 slave on canopen's LocalNode, answering in lockstep (TPDOs on every SYNC)."""

    def __init__(self, channel: str, node_id: int = NODE_ID, eds: Path = DEFAULT_EDS) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.network = canopen.Network(self.bus)
        self.network.NOTIFIER_CYCLE = 0.1  # quick teardown
        self.node: canopen.LocalNode = self.network.create_node(node_id, str(eds))
        self.node_id = node_id
        self.lock = threading.Lock()
        self.state = State402.SWITCH_ON_DISABLED
        self.controlword = 0
        self.pending_rpdo: dict[int, bytes] = {}
        self.received_controlwords: list[int] = []
        self.syncs = 0
        # fault hooks used by tests/drivers/test_master_faults.py
        self.freeze = False  # the state machine ignores every command
        self.mute_tpdo = False  # no TPDO answers SYNC
        self.short_tpdo = False  # TPDO1 goes out one byte short
        self.boot_up = True  # answer NMT reset with a boot-up message
        self.node.add_write_callback(self._check_write)
        self.network.subscribe(0, self._on_nmt)
        self.network.subscribe(SYNC_COB_ID, self._on_sync)
        for base in RPDO_BASES:
            self.network.subscribe(cob_id(base, node_id), self._on_rpdo)
        self.network.connect()
        self._store_status()

    # --- object dictionary helpers ----------------------------------------------------------------------------

    def _variable(self, index: int, subindex: int) -> ODVariable:
        obj = self.node.object_dictionary[index]
        variable = obj if isinstance(obj, ODVariable) else obj[subindex]
        assert isinstance(variable, ODVariable)
        return variable

    def _format(self, index: int, subindex: int) -> str:
        data_type = self._variable(index, subindex).data_type
        assert data_type is not None
        return "<" + _FORMATS[data_type]

    def value(self, index: int, subindex: int = 0) -> int:
        (value,) = struct.unpack(self._format(index, subindex), self.node.get_data(index, subindex))
        return int(value)

    def put(self, index: int, subindex: int, value: int) -> None:
        self.node.set_data(index, subindex, struct.pack(self._format(index, subindex), value))

    def _store_status(self) -> None:
        statusword = STATE_STATUSWORD[self.state] | Statusword.REMOTE
        if self.state in (State402.READY_TO_SWITCH_ON, State402.SWITCHED_ON, State402.OPERATION_ENABLED,
                          State402.QUICK_STOP_ACTIVE, State402.FAULT_REACTION_ACTIVE):
            statusword |= Statusword.VOLTAGE_ENABLED
        self.put(Obj.STATUSWORD, 0, statusword)

    # --- SDO rules of CiA 301 that LocalNode leaves to the application -----------------------------------------

    def _check_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        if od.data_type is not None and od.data_type in _FORMATS:
            (value,) = struct.unpack("<" + _FORMATS[od.data_type], data)
            if od.min is not None and value < od.min:
                raise SdoAbortedError(SdoAbortCode.VALUE_TOO_LOW)
            if od.max is not None and value > od.max:
                raise SdoAbortedError(SdoAbortCode.VALUE_TOO_HIGH)
        is_mapping = 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03
        if is_mapping:
            if self.value(index - 0x200, 1) & PDO_DISABLED == 0:
                raise SdoAbortedError(SdoAbortCode.GENERAL_PARAMETER)  # map only a disabled PDO
            if subindex > 0:
                (value,) = struct.unpack("<I", data)
                entry = MappingEntry.decode(value)
                mapped = self.node.object_dictionary.get_variable(entry.index, entry.subindex)
                if value and (mapped is None or not mapped.pdo_mappable):
                    raise SdoAbortedError(SdoAbortCode.CANNOT_MAP)
        if index == Obj.MODES_OF_OPERATION:
            self.node.set_data(Obj.MODES_OF_OPERATION_DISPLAY, 0, data)

    # --- NMT: LocalNode tracks the state but sends no boot-up after a reset -----------------------------------

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        command, node = data[0], data[1]
        if node not in (0, self.node_id):
            return
        if command in (NmtCommand.RESET_COMMUNICATION, NmtCommand.RESET_NODE):
            for index in [i for i in self.node.data_store if 0x1000 <= i <= 0x1FFF]:
                del self.node.data_store[index]  # back to the EDS defaults
            if self.boot_up:
                self.node.nmt.send_command(NmtCommand.RESET_COMMUNICATION)  # sends the boot-up frame
                self.node.nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)  # starts the heartbeat (0x1017)

    # --- PDOs: RPDOs applied at SYNC, TPDOs sent on SYNC ------------------------------------------------------

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self.lock:
            self.pending_rpdo[can_id] = bytes(data)

    def _mapping(self, mapping_index: int) -> list[tuple[int, int, str]]:
        entries = []
        for sub in range(1, self.value(mapping_index, 0) + 1):
            entry = MappingEntry.decode(self.value(mapping_index, sub))
            entries.append((entry.index, entry.subindex, self._format(entry.index, entry.subindex)[1:]))
        return entries

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        with self.lock:
            pending, self.pending_rpdo = self.pending_rpdo, {}
            self.syncs += 1
        for number in range(1, 5):
            cob = self.value(0x1400 + number - 1, 1)
            if cob & PDO_DISABLED or cob not in pending:
                continue
            layout = self._mapping(0x1600 + number - 1)
            values = struct.unpack("<" + "".join(f for _, _, f in layout), pending[cob])
            for (index, subindex, _), value in zip(layout, values, strict=True):
                self.put(index, subindex, value)
        controlword = self.value(Obj.CONTROLWORD)
        self.received_controlwords.append(controlword)
        if not self.freeze:
            self.state = transition(self.state, controlword, self.controlword)
        self.controlword = controlword
        self._store_status()
        enabled = self.state is State402.OPERATION_ENABLED
        velocity = self.value(Obj.TARGET_VELOCITY) if enabled else 0
        torque = self.value(Obj.TARGET_TORQUE) if enabled else 0
        self.put(Obj.VELOCITY_ACTUAL_VALUE, 0, velocity)
        self.put(Obj.TORQUE_ACTUAL_VALUE, 0, torque)
        self.put(Obj.POSITION_ACTUAL_VALUE, 0, self.value(Obj.POSITION_ACTUAL_VALUE) + velocity // 1000)
        if self.mute_tpdo:
            return
        for number in range(1, 5):
            cob = self.value(0x1800 + number - 1, 1)
            if cob & PDO_DISABLED:
                continue
            payload = b"".join(self.node.get_data(i, s) for i, s, _ in self._mapping(0x1A00 + number - 1))
            if self.short_tpdo and number == 1:
                payload = payload[:-1]
            self.network.send_message(cob, payload)

    # --- fault hooks ------------------------------------------------------------------------------------------

    def fault(self, code: int = EmcyCode.OVER_CURRENT, *, emcy: bool = True) -> None:
        """Enter FAULT (statusword bit 3) and, optionally, announce it with an EMCY."""
        self.state = State402.FAULT
        self._store_status()
        if emcy:
            self.node.emcy.send(code, ErrorRegister.GENERIC | ErrorRegister.CURRENT)

    def stop_heartbeat(self) -> None:
        self.node.nmt.stop_heartbeat()

    def close(self) -> None:
        self.node.nmt.stop_heartbeat()
        self.network.disconnect()


def drive_config(**overrides: object) -> DriveConfig:
    base: dict[str, object] = {
        "node_id": NODE_ID,
        "velocity_scale": VELOCITY_SCALE,
        "velocity_limit": 3000.0,
        "heartbeat_producer_ms": 100,  # loss declared after 0.3 s: robust on a loaded machine
        "heartbeat_consumer_ms": 200,
        "state_timeout": 1.0,
        "sdo_timeout": 0.3,
    }
    base.update(overrides)
    return DriveConfig.model_validate(base)
