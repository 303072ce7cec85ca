"""The demand echo of the virtual drive (issue 28): at every SYNC, 0x606B (CSV) / 0x6074 (CST) is the target the
drive latched at that SYNC -- not the one before it, not the axis's actual value."""

from __future__ import annotations

import math
import struct

import pytest

from drivers.cia301 import FunctionCode, cob_id
from drivers.cia402 import Obj, OperationMode, State402
from plant_emulator.config import PlantConfig
from tests.support.emulator_harness import NODE_ID, Harness

pytestmark = pytest.mark.timeout(120)


def _enable(h: Harness, rpdo: int, layout: str) -> None:
    h.start()
    for controlword in (0x06, 0x07, 0x0F):
        h.send(rpdo, struct.pack(layout, controlword, 0))
        h.sync(wait_for=h.tpdo1)
    assert h.drive.state is State402.OPERATION_ENABLED


def test_velocity_demand_is_the_target_latched_at_each_sync() -> None:
    with Harness(PlantConfig(model="first_order", a=-2.0, b=3.0, c=1.0), velocity_scale=1000.0) as h:
        _enable(h, h.rpdo1, "<Hi")
        echoed, sent = [], []
        for k in range(30):
            target = round(50_000 * math.sin(2 * math.pi * k / 11))  # a new target every cycle
            h.send(h.rpdo1, struct.pack("<Hi", 0x0F, target))
            h.sync(wait_for=h.tpdo1)  # the TPDOs of this SYNC are out: the store holds this cycle's echo
            sent.append(target)
            echoed.append(h.drive.node.read(Obj.VELOCITY_DEMAND_VALUE))
        assert echoed == sent
        assert len(set(sent)) > 10  # the targets changed, so an echo of the previous one would differ


def test_torque_demand_is_the_target_latched_at_each_sync() -> None:
    with Harness(PlantConfig(model="pmsm")) as h:
        h.node.sdo[Obj.MODES_OF_OPERATION].raw = OperationMode.CYCLIC_SYNC_TORQUE
        rpdo2 = cob_id(FunctionCode.RPDO2, NODE_ID)  # default RPDO2: controlword + target torque
        _enable(h, rpdo2, "<Hh")
        echoed, sent = [], []
        for k in range(30):
            target = (-1) ** k * (10 + k)  # small, alternating: the axis stays slow
            h.send(rpdo2, struct.pack("<Hh", 0x0F, target))
            h.sync(wait_for=h.tpdo1)
            sent.append(target)
            echoed.append(h.drive.node.read(Obj.TORQUE_DEMAND))
        assert echoed == sent
