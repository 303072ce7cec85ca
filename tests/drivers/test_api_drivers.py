"""The commissioning API at ``drivers``' top (``docs/api.md``) on the embedded emulator: scan, connect, SDO by
object name or index, enable, and the confirmed stop; the emulated drive's own state is the independent truth."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

import drivers
from plant_emulator.config import PlantConfig
from plant_emulator.embedded import EmbeddedEmulator
from plant_emulator.settings import EmulatorConfig

NODE = 5
SAMPLE_TIME = 0.005
PLANT = PlantConfig(model="first_order", a=-1.23, b=1.68)


@pytest.fixture
def emulated() -> Iterator[tuple[EmbeddedEmulator, Any, Any]]:
    """One emulated drive, and the master's end of its bus with a network on it (not listening yet)."""
    drive_cfg = drivers.DriveConfig(node_id=NODE, heartbeat_timeout_factor=10.0)
    with EmbeddedEmulator.for_drive(PLANT, EmulatorConfig(), drive_cfg, sample_time=SAMPLE_TIME) as emulator:
        bus = drivers.open_bus(emulator.bus_config)
        network = drivers.DriveNetwork(bus)
        try:
            yield emulator, network, drive_cfg
        finally:
            network.close()
            bus.shutdown()


def test_scan_connect_sdo_by_name_enable_and_the_confirmed_stop(emulated: tuple[EmbeddedEmulator, Any, Any]) -> None:
    emulator, network, drive_cfg = emulated
    found = network.scan(range(1, 8), listen=0.05)
    assert [node.node_id for node in found.nodes] == [NODE] and found.nodes[0].profile == 402
    drive = drivers.Cia402Drive.on_network(network, drive_cfg, sample_time=SAMPLE_TIME)
    try:
        info = drive.connect()
        assert info is not None
        with pytest.raises(drivers.DriveError, match="scan before listen"):
            network.scan(range(1, 8), listen=0.05)
        # by name and by index: the same objects
        assert drive.read_object("Statusword") == drive.read_object(0x6041)
        vendor = drive.read_object("Identity object", "Vendor-ID")
        assert vendor == drive.read_object(0x1018, 1) == found.nodes[0].vendor_id
        drive.write_object("Producer heartbeat time", 0, 700)
        assert drive.read_object(0x1017) == 700
        with pytest.raises(drivers.InputError, match="no object"):
            drive.read_object("No such object")
        with pytest.raises(drivers.InputError, match="Vendor"):
            drive.read_object("Identity object", "Vendor")
        drive.configure(drive_cfg.operation_mode)
        drive.enable()
        assert emulator.drive.state is drivers.State402.OPERATION_ENABLED
        report = drive.safe_stop()
        assert report.confirmed and report.state is drivers.State402.SWITCH_ON_DISABLED
        assert emulator.drive.state is drivers.State402.SWITCH_ON_DISABLED
    finally:
        drive.close()


def test_an_sdo_abort_is_a_typed_error(emulated: tuple[EmbeddedEmulator, Any, Any]) -> None:
    _, network, drive_cfg = emulated
    drive = drivers.Cia402Drive.on_network(network, drive_cfg, sample_time=SAMPLE_TIME)
    try:
        drive.connect()
        with pytest.raises(drivers.SdoError, match="read-only"):
            drive.write_object("Statusword", 0, 0)  # the drive refuses: a read-only object
        with pytest.raises(drivers.ConfigError, match="neither in the EDS"):
            drive.read_object(0x2FFF, 0)  # an index nothing types: refused before anything is sent
    finally:
        drive.close()


def test_import_drivers_loads_neither_can_nor_canopen() -> None:
    import json
    import subprocess
    import sys

    probe = ("import json, sys, drivers\n"
             "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in ('can', 'canopen', 'drivers'))))")
    child = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    assert json.loads(child.stdout.splitlines()[-1]) == ["drivers"]
