"""An independent CiA 402 master -- canopen's own ``BaseNode402`` -- drives the emulator.

Two ``canopen.Network`` objects share a ``virtual`` bus (a unique channel per test): one hosts the emulated
drive, the other the master. The master uses only standard services, as its documentation describes: it reads
the PDO configuration over SDO (``setup_402_state_machine``), starts NMT, produces SYNC, transmits its
synchronous RPDO periodically (``PdoMap.start``), walks the state machine, sets the mode and commands a velocity.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Iterator
from typing import Any

import can
import canopen
import pytest
from canopen.profiles.p402 import BaseNode402

from drivers.od import load_od
from plant_emulator.config import PlantConfig
from plant_emulator.device import VirtualDrive
from plant_emulator.physics import build_plant

pytestmark = pytest.mark.slow

NODE_ID = 5
PERIOD = 0.01  # s
COUNTS_PER_RPM = 1000  # 0x2000 of the shipped EDS


@pytest.fixture
def master_and_drive() -> Iterator[tuple[BaseNode402, canopen.Network, VirtualDrive]]:
    channel = f"interop-{uuid.uuid4()}"
    drive = VirtualDrive(build_plant(PlantConfig(model="pmsm"), seed=1), node_id=NODE_ID, cycle_period=PERIOD)
    drive.start(can.Bus(interface="virtual", channel=channel))
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    node = BaseNode402(NODE_ID, load_od(None, NODE_ID))
    network.add_node(node)
    try:
        yield node, network, drive
    finally:
        network.sync.stop()
        for pdo_map in node.rpdo.values():
            pdo_map.stop()
        network.disconnect()
        drive.stop()


def _wait_tpdo_value(node: BaseNode402, index: int, accept: float, timeout: float) -> int:
    """Latest TPDO value of ``index`` once within ``accept`` counts of settling (by reading it repeatedly)."""
    deadline = time.monotonic() + timeout
    value = node.tpdo_values[index]
    while time.monotonic() < deadline:
        node.tpdo[1].wait_for_reception(timeout=0.5)
        value = node.tpdo_values[index]
        if abs(value) >= accept:
            break
    return int(value)


@pytest.mark.timeout(60)
def test_base_node_402_enables_and_runs_csv(
    master_and_drive: tuple[BaseNode402, canopen.Network, VirtualDrive],
) -> None:
    node, network, drive = master_and_drive
    booted = threading.Event()
    node.nmt.add_heartbeat_callback(lambda state: booted.set() if state == 0 else None)
    # A master's start-up: reset node, wait for the boot-up message. (canopen's wait_for_bootup() only sees a
    # boot-up that arrives after it is called, which races with a fast device; the callback does not.)
    node.nmt.state = "RESET"
    assert booted.wait(timeout=2.0), "no boot-up message after reset node"
    node.nmt.state = "PRE-OPERATIONAL"
    node.sdo[0x1006].raw = int(PERIOD * 1e6)  # communication cycle period, as a master sets it up
    node.setup_402_state_machine()  # reads the PDO mapping over SDO (pre-operational)
    assert 0x6041 in node.tpdo_values and 0x6040 in node.rpdo_pointers
    node.nmt.state = "OPERATIONAL"
    network.sync.start(PERIOD)
    node.rpdo[1].start(PERIOD)  # synchronous RPDO: the master keeps sending it, the drive applies it on SYNC
    node.tpdo[1].wait_for_reception(timeout=1.0)
    assert node.state == "SWITCH ON DISABLED"

    node.sdo[0x6060].raw = 3  # profile velocity first, to see 0x6061 follow a mode change
    assert node.sdo[0x6061].raw == 3
    node.op_mode = "CYCLIC SYNCHRONOUS VELOCITY"  # canopen checks 0x6502 and waits for 0x6061
    assert node.sdo[0x6061].raw == 9
    assert node.op_mode == "CYCLIC SYNCHRONOUS VELOCITY"

    node.state = "OPERATION ENABLED"  # blocking: 2 shutdown, 3 switch on, 4 enable operation
    assert node.state == "OPERATION ENABLED"
    assert drive.state.name == "OPERATION_ENABLED"
    assert node.statusword & (1 << 12)  # CSV: target value followed

    target_rpm = 300.0
    target_velocity: Any = node.rpdo_pointers[0x60FF]  # canopen annotates these as PdoMap; they are variables
    target_velocity.raw = int(target_rpm * COUNTS_PER_RPM)
    velocity = _wait_tpdo_value(node, 0x606C, accept=0.98 * target_rpm * COUNTS_PER_RPM, timeout=10.0)
    assert velocity == pytest.approx(target_rpm * COUNTS_PER_RPM, rel=0.03)
    assert node.sdo[0x606C].raw == pytest.approx(target_rpm * COUNTS_PER_RPM, rel=0.03)  # SDO agrees with PDO

    node.state = "QUICK STOP ACTIVE"  # 11, then the ramp of 0x6085 and, with 0x605A = 2, switch on disabled
    deadline = time.monotonic() + 5.0
    while node.state != "SWITCH ON DISABLED" and time.monotonic() < deadline:
        node.check_statusword(timeout=0.5)
    assert node.state == "SWITCH ON DISABLED"
    assert abs(node.tpdo_values[0x606C]) <= 2 * COUNTS_PER_RPM  # disabled only once the axis is at rest
