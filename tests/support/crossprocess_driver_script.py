"""Run by ``tests/crossprocess/test_crossprocess_emulator.py`` INSIDE a private network namespace: drives a
``plant-emulator`` process over ``udp_multicast`` with the product's master and prints one JSON document on stdout.

Usage: ``python tests/support/crossprocess_driver_script.py GROUP NODE_ID``. Never run it in the host namespace.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from drivers.bus import open_bus
from drivers.cia402 import OperationMode
from drivers.cia402_master import Cia402Drive
from drivers.config import BusConfig, DriveConfig

TARGET_RPM = 300.0
CYCLES = 200
PERIOD = 0.01


def main(group: str, node_id: int) -> dict[str, object]:
    cfg = DriveConfig(node_id=node_id, velocity_scale=1000.0, heartbeat_producer_ms=100, heartbeat_consumer_ms=500)
    bus = open_bus(BusConfig(interface="udp_multicast", channel=group))
    master = Cia402Drive.open(bus, cfg, sample_time=PERIOD)
    result: dict[str, object] = {}
    try:
        info = master.connect()
        result["vendor_id"] = info.vendor_id
        master.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
        master.enable()
        result["enabled_state"] = master.wait_feedback(1.0).state.name
        velocities = []
        started = time.perf_counter()
        for _ in range(CYCLES):
            master.set_target(TARGET_RPM)
            master.sync()
            velocities.append(master.wait_feedback(1.0).velocity)
        result["cycles_per_second"] = CYCLES / (time.perf_counter() - started)
        result["velocities"] = velocities
        master.quick_stop()
        result["after_quick_stop"] = master.wait_feedback(1.0).state.name
        master.disable()
        final = master.wait_feedback(1.0)
        result["after_disable"] = final.state.name
        result["final_velocity"] = final.velocity
    finally:
        master.safe_stop()
        master.close()
        bus.shutdown()
    return result


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], int(sys.argv[2]))), flush=True)
