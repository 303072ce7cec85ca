"""Lockstep timing: the SYNC-cycle order (one-cycle transport delay) against the closed-form response of a
first-order plant, and bit-identical feedback for identical seeds."""

from __future__ import annotations

import math
import struct

import pytest

from drivers.cia301 import FunctionCode, cob_id
from drivers.cia402 import Obj, OperationMode, State402
from plant_emulator.config import PlantConfig
from plant_emulator.settings import EmulatorConfig
from tests.support.emulator_harness import NODE_ID, Harness

pytestmark = pytest.mark.timeout(120)

A, B, PERIOD = -2.0, 3.0, 0.01
SCALE = 1000.0  # counts of 0x60FF/0x606C per plant unit


def _enable(h: Harness) -> None:
    h.start()
    for controlword in (0x06, 0x07, 0x0F):
        h.send(h.rpdo1, struct.pack("<Hi", controlword, 0))
        h.sync(wait_for=h.tpdo1)
    assert h.drive.state is State402.OPERATION_ENABLED


def _velocity(frame: bytes) -> int:
    return int(struct.unpack_from("<Hi", frame)[1])


def test_cycle_order_is_the_one_cycle_transport_delay() -> None:
    """A target sent before SYNC n moves the axis during cycle n and is first reported at SYNC n+1."""
    plant = PlantConfig(model="first_order", a=A, b=B, c=1.0)
    u = 2.0
    with Harness(plant, cycle_period=PERIOD, velocity_scale=SCALE) as h:
        _enable(h)
        h.send(h.rpdo1, struct.pack("<Hi", 0x0F, round(u * SCALE)))
        reported = []
        for _ in range(4):
            h.sync(wait_for=h.tpdo1)
            reported.append(_velocity(h.recorder.frames[h.tpdo1][-1]))
    # closed form of x' = a x + b u under a zero-order hold, from rest
    decay = math.exp(A * PERIOD)
    gain = (decay - 1.0) / A * B
    expected, y = [0.0], 0.0  # SYNC n: the physics ran cycle n-1 with the old (zero) command
    for _ in range(3):
        y = decay * y + gain * u
        expected.append(y)
    assert reported == [round(v * SCALE) for v in expected]
    assert reported[0] == 0 and reported[1] > 0


def _run(seed: int, cycles: int = 120) -> list[bytes]:
    plant = PlantConfig(model="pmsm", output_noise=0.5, seed=seed)
    frames: list[bytes] = []
    with Harness(plant, seed=seed) as h:
        _enable(h)
        for k in range(cycles):
            target = round(200_000 * math.sin(2 * math.pi * k / 60))  # +-200 rpm in 0.001 rpm counts
            h.send(h.rpdo1, struct.pack("<Hi", 0x0F, target))
            h.sync(wait_for=h.tpdo1)
            frames.append(h.recorder.frames[h.tpdo1][-1])
        tpdo2 = cob_id(FunctionCode.TPDO2, NODE_ID)  # torque + position, sent right after TPDO1
        frames.extend(h.recorder.wait_count(tpdo2, h.recorder.count(h.tpdo1)))
    return frames


@pytest.mark.slow
def test_same_seed_gives_identical_feedback() -> None:
    first, second, other = _run(seed=7), _run(seed=7), _run(seed=8)
    assert len(first) == len(second) > 0
    assert first == second
    assert first != other  # the noise is seeded: a different seed changes the feedback
    velocities = [_velocity(frame) for frame in first[:120]]
    assert max(velocities) > 100_000  # the axis really moved (> 100 rpm)


def test_profile_velocity_ramps_with_0x6083_and_reports_target_reached() -> None:
    """PV: the set-point ramps linearly at 0x6083; a fast first-order plant (tau 1 ms) follows it; bit 10 is set
    once the velocity is within the window of the target."""
    a, b = -1000.0, 1000.0  # unit DC gain, 1 ms time constant
    accel_counts, target_counts = 50_000, 2_000  # 0.5 plant units per 10 ms cycle, target 2 plant units
    plant = PlantConfig(model="first_order", a=a, b=b, c=1.0)
    settings = EmulatorConfig(velocity_window=0.01)
    with Harness(plant, settings=settings, cycle_period=PERIOD, velocity_scale=SCALE) as h:
        h.node.sdo[Obj.MODES_OF_OPERATION].raw = OperationMode.PROFILE_VELOCITY
        h.node.sdo[Obj.PROFILE_ACCELERATION].raw = accel_counts
        _enable(h)
        h.send(h.rpdo1, struct.pack("<Hi", 0x0F, target_counts))
        frames = []
        for _ in range(9):
            h.sync(wait_for=h.tpdo1)
            frames.append(struct.unpack_from("<Hi", h.recorder.frames[h.tpdo1][-1]))
    decay = math.exp(a * PERIOD)
    y, expected = 0.0, [0.0]
    for j in range(1, 9):
        u = min(j * accel_counts * PERIOD, target_counts) / SCALE  # the linear ramp of CiA 402 PV
        y = decay * y + (1.0 - decay) * u
        expected.append(y)
    assert [v for _, v in frames] == [round(v * SCALE) for v in expected]
    reached = [bool(sw & (1 << 10)) for sw, _ in frames]
    assert reached[:4] == [False] * 4 and reached[-1]


@pytest.mark.parametrize(("option", "after_ramp"), [(2, State402.SWITCH_ON_DISABLED), (6, State402.QUICK_STOP_ACTIVE)])
def test_quick_stop_ramps_at_0x6085(option: int, after_ramp: State402) -> None:
    """Quick stop ramps the set-point linearly to zero at 0x6085, then disables (option 2) or holds (option 6,
    which allows transition 16 back to operation enabled)."""
    a, b = -1000.0, 1000.0
    decel_counts = 50_000  # 0.5 plant units per 10 ms cycle
    plant = PlantConfig(model="first_order", a=a, b=b, c=1.0)
    settings = EmulatorConfig(standstill_velocity=0.001)
    with Harness(plant, settings=settings, cycle_period=PERIOD, velocity_scale=SCALE) as h:
        h.node.sdo[Obj.QUICK_STOP_OPTION].raw = option
        h.node.sdo[Obj.QUICK_STOP_DECELERATION].raw = decel_counts
        _enable(h)
        for _ in range(20):
            h.send(h.rpdo1, struct.pack("<Hi", 0x0F, 2000))
            h.sync(wait_for=h.tpdo1)
        h.send(h.rpdo1, struct.pack("<Hi", 0x02, 2000))  # quick stop (target left at 2000: ignored)
        h.sync(wait_for=h.tpdo1)
        assert h.drive.state is State402.QUICK_STOP_ACTIVE
        velocities = []
        for _ in range(6):
            h.sync(wait_for=h.tpdo1)
            velocities.append(struct.unpack_from("<Hi", h.recorder.frames[h.tpdo1][-1])[1])
        assert h.drive.state is after_ramp
        if option == 6:
            statusword = struct.unpack_from("<H", h.recorder.frames[h.tpdo1][-1])[0]
            assert statusword & 0x6F == 0x07 and statusword & (1 << 10)  # quick stop active, target reached
            h.send(h.rpdo1, struct.pack("<Hi", 0x0F, 0))
            h.sync(wait_for=h.tpdo1)
            assert h.drive.state is State402.OPERATION_ENABLED  # transition 16
    decay = math.exp(a * PERIOD)
    y = 2.0  # at rest at 2 units (20 cycles of a 1 ms lag: exact to 1e-80)
    expected = []
    for step in range(1, 7):
        u = max(2.0 - step * decel_counts * PERIOD / SCALE, 0.0)  # the linear ramp to zero
        y = decay * y + (1.0 - decay) * u
        expected.append(round(y * SCALE))
    assert velocities == expected
