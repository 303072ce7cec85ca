"""Run by ``tests/crossprocess/test_crossprocess_network.py`` INSIDE a private network namespace: four drives of one
``plant-emulator --node-id 1,2,3,4`` process, driven over ``udp_multicast`` by the product's masters sharing one
:class:`~drivers.network.DriveNetwork` (one receive path, one SYNC); prints one JSON document on stdout.

Usage: ``python tests/support/crossprocess_network_script.py GROUP N[,N...]``. Never run it in the host namespace.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from drivers.bus import open_bus
from drivers.cia402 import OperationMode
from drivers.cia402_master import Cia402Drive
from drivers.config import BusConfig, DriveConfig
from drivers.network import DriveNetwork

CYCLES = 100
PERIOD = 0.01


def target(node_id: int) -> float:
    """A different CSV target per node (rpm), so a frame routed to the wrong node shows."""
    return 100.0 * node_id


def main(group: str, nodes: list[int]) -> dict[str, object]:
    bus = open_bus(BusConfig(interface="udp_multicast", channel=group))
    network = DriveNetwork(bus)
    drives: list[Cia402Drive] = []
    result: dict[str, object] = {}
    try:
        for node in nodes:
            cfg = DriveConfig(node_id=node, velocity_scale=1000.0, heartbeat_producer_ms=100,
                              heartbeat_consumer_ms=500)
            drive = Cia402Drive.on_network(network, cfg, sample_time=PERIOD)
            drives.append(drive)
            drive.connect()
            drive.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
            drive.enable()
        velocities: dict[int, float] = {}
        before = {drive.node_id: drive.cycle for drive in drives}
        for _ in range(CYCLES):
            for drive in drives:
                drive.set_target(target(drive.node_id))
            drives[0].sync()
            velocities = {drive.node_id: drive.wait_feedback(1.0).velocity for drive in drives}
        result["final_velocity"] = velocities
        result["cycles"] = {drive.node_id: drive.cycle - before[drive.node_id] for drive in drives}
    finally:
        reports = [drive.safe_stop() for drive in drives]
        result["stopped"] = {drive.node_id: (report.confirmed, report.state.name if report.state else None)
                             for drive, report in zip(drives, reports, strict=True)}
        for drive in drives:
            drive.close()
        network.close()
        bus.shutdown()
    return result


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], [int(n) for n in sys.argv[2].split(",")])), flush=True)
