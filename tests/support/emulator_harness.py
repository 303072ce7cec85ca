"""Test helper: a virtual drive on a unique ``virtual`` channel and a bare canopen master next to it.

The master side is a plain ``canopen.Network`` with a ``RemoteNode`` for SDO plus a frame recorder, so tests
can send raw SYNC / RPDO / NMT frames and wait for exactly the frames the drive answers with.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import defaultdict
from dataclasses import dataclass, field

import can
import canopen

from drivers.cia301 import SYNC_COB_ID, FunctionCode, NmtCommand, cob_id
from drivers.cia402 import AbortConnectionOption, State402
from drivers.od import load_od
from plant_emulator.config import PlantConfig
from plant_emulator.device import VirtualDrive
from plant_emulator.physics import build_plant
from plant_emulator.settings import EmulatorConfig

NODE_ID = 3

#: the state each abort-connection option (0x6007) leaves an OPERATION ENABLED drive in
#: the state each reaction ends in once its ramp is done: quick stop with the EDS's 0x605A = 2 ramps to standstill
#: and then switches the power stage off (in lockstep after the master is lost, on the drive's own clock)
AFTER_THE_RAMP = {State402.QUICK_STOP_ACTIVE: State402.SWITCH_ON_DISABLED}
#: 0x6007 option -> the state the reaction enters at once
ABORT_REACTIONS = [
    (AbortConnectionOption.NO_ACTION, State402.OPERATION_ENABLED),
    (AbortConnectionOption.FAULT, State402.FAULT),
    (AbortConnectionOption.DISABLE_VOLTAGE, State402.SWITCH_ON_DISABLED),
    (AbortConnectionOption.QUICK_STOP, State402.QUICK_STOP_ACTIVE),
]


@dataclass
class FrameRecorder:
    """Frames seen on the master side, by COB-ID, with a condition to wait on."""

    frames: dict[int, list[bytes]] = field(default_factory=lambda: defaultdict(list))
    condition: threading.Condition = field(default_factory=threading.Condition)

    def __call__(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self.condition:
            self.frames[can_id].append(bytes(data))
            self.condition.notify_all()

    def count(self, can_id: int) -> int:
        with self.condition:
            return len(self.frames[can_id])

    def wait_count(self, can_id: int, count: int, timeout: float = 2.0) -> list[bytes]:
        """Wait until ``count`` frames of ``can_id`` were seen; return them all."""
        with self.condition:
            ok = self.condition.wait_for(lambda: len(self.frames[can_id]) >= count, timeout=timeout)
            if not ok:
                raise TimeoutError(f"only {len(self.frames[can_id])} of {count} frames 0x{can_id:03X}")
            return list(self.frames[can_id])


class Harness:
    """A running drive and a master on one virtual channel. Use as a context manager."""

    def __init__(
        self,
        plant: PlantConfig | None = None,
        *,
        settings: EmulatorConfig | None = None,
        seed: int = 0,
        cycle_period: float = 0.01,
        velocity_scale: float | None = None,
        torque_scale: float | None = None,
    ) -> None:
        self.channel = f"emu-test-{uuid.uuid4()}"
        plant_cfg = plant if plant is not None else PlantConfig(model="pmsm")
        self.drive = VirtualDrive(
            build_plant(plant_cfg, seed=seed),
            node_id=NODE_ID,
            cycle_period=cycle_period,
            settings=settings,
            velocity_scale=velocity_scale,
            torque_scale=torque_scale,
        )
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.1  # quick disconnect
        self.recorder = FrameRecorder()
        self.node = canopen.RemoteNode(NODE_ID, load_od(None, NODE_ID))

    def __enter__(self) -> Harness:
        self.network.connect(interface="virtual", channel=self.channel)
        self.network.add_node(self.node)
        for function in (FunctionCode.TPDO1, FunctionCode.TPDO2, FunctionCode.TPDO3, FunctionCode.TPDO4,
                         FunctionCode.EMCY, FunctionCode.HEARTBEAT):
            self.network.subscribe(cob_id(function, NODE_ID), self.recorder)
        self.drive.start(can.Bus(interface="virtual", channel=self.channel))
        self.recorder.wait_count(cob_id(FunctionCode.HEARTBEAT, NODE_ID), 1)  # the boot-up message
        return self

    def __exit__(self, *exc: object) -> None:
        self.network.disconnect()
        self.drive.stop()

    # --- frames -------------------------------------------------------------------------------------------

    def nmt(self, command: NmtCommand) -> None:
        self.network.send_message(0, bytes([int(command), NODE_ID]))
        time.sleep(0.05)  # NMT has no answer; give the drive's notifier a moment

    def start(self) -> None:
        self.nmt(NmtCommand.START)

    def sync(self, wait_for: int | None = None) -> None:
        """Send one SYNC; with ``wait_for`` (a COB-ID) wait for the drive's next frame on it."""
        before = self.recorder.count(wait_for) if wait_for is not None else 0
        self.network.send_message(SYNC_COB_ID, b"")
        if wait_for is not None:
            self.recorder.wait_count(wait_for, before + 1)
        else:
            self._settle()

    def _settle(self) -> None:
        """Round trip an SDO read so everything sent before has been processed by the drive."""
        self.node.sdo.upload(0x1000, 0)

    def send(self, can_id: int, data: bytes) -> None:
        self.network.send_message(can_id, data)

    @property
    def tpdo1(self) -> int:
        return cob_id(FunctionCode.TPDO1, NODE_ID)

    @property
    def rpdo1(self) -> int:
        return cob_id(FunctionCode.RPDO1, NODE_ID)

    @property
    def emcy(self) -> int:
        return cob_id(FunctionCode.EMCY, NODE_ID)
