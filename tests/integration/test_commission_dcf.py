"""``commission info --dcf``: the configured drive as a CiA 306 DCF that canopen loads back (issue 12).

The truth the DCF is held against is the drive itself after ``run``'s start-up: the master connects to an emulated
drive and configures it exactly as ``run`` does, then every object is read back over SDO. canopen's ``import_od``
(an independent CiA 306 reader) must load the DCF with the node id and bit rate of its ``[DeviceComissioning]``,
and each ``ParameterValue`` must be what the configured drive holds -- for the objects the bench writes (PDO
communication and mapping, mode, cycle, heartbeats), on the shipped drive and on one with a single TPDO and no
0x1006/0x1016.
"""

from __future__ import annotations

from pathlib import Path

import canopen
import pytest
from canopen.objectdictionary import ODVariable

from drivers.bus import open_bus, parse_bus_spec
from drivers.cia402 import Obj
from drivers.cia402_master import Cia402Drive
from drivers.od import DEFAULT_EDS
from drivers.pdo import MappingEntry
from foilc_hil.config import load_config
from tests.support.commission_bus import emulated_bus, run_json
from tests.support.standard_drives import NODE, config_file, mutated_eds

BITRATE = 500_000
#: (index, sub-index) of objects run's start-up writes on every drive that has them
_WRITTEN_BY_STARTUP = {(Obj.MODES_OF_OPERATION, 0), (Obj.PRODUCER_HEARTBEAT_TIME, 0), (Obj.CONSUMER_HEARTBEAT_TIME, 1),
                       (Obj.COMMUNICATION_CYCLE_PERIOD, 0), (Obj.RPDO_COMMUNICATION, 1), (Obj.RPDO_MAPPING, 0),
                       (Obj.TPDO_COMMUNICATION, 1), (Obj.TPDO_MAPPING, 0)}


def _parameter_values(od: canopen.ObjectDictionary) -> dict[tuple[int, int], int]:
    """Every object of ``od`` that has a ``ParameterValue`` (canopen's ``value``)."""
    values: dict[tuple[int, int], int] = {}
    for index in od.indices:
        obj = od[index]
        members = [obj] if isinstance(obj, ODVariable) else [obj[sub] for sub in obj.subindices]
        for variable in members:
            value = getattr(variable, "value", None)
            if value is not None:
                values[index, variable.subindex] = int(value)
    return values


@pytest.mark.parametrize("removed", [(), (0x1006, 0x1016, 0x1801, 0x1802, 0x1803, 0x1A01, 0x1A02, 0x1A03)],
                         ids=["shipped-drive", "one-tpdo-no-0x1006-0x1016"])
def test_canopen_loads_the_dcf_with_the_values_the_configured_drive_holds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], removed: tuple[int, ...]
) -> None:
    eds = mutated_eds(tmp_path, *removed) if removed else DEFAULT_EDS
    config_path = config_file(tmp_path, eds, eds)
    config = load_config(config_path)
    dcf = tmp_path / "drive.dcf"
    with emulated_bus([NODE], config) as bus:
        code, document, _ = run_json(capsys, "commission", "info", "--bus", bus.spec, "-b", str(BITRATE),
                                     "--config", str(config_path), "--dcf", str(dcf))
        assert code == 0, document
        # the truth: the drive as run's start-up leaves it, read back over SDO
        with open_bus(parse_bus_spec(bus.spec)) as master_bus:
            drive = Cia402Drive.open(master_bus, config.drive, sample_time=config.sample_time)
            with drive:
                drive.connect()
                drive.configure(config.drive.operation_mode)
                od = canopen.import_od(str(dcf))
                values = _parameter_values(od)
                held = {key: drive.read_object(*key) for key in values}
                drive.disable()
    assert od.node_id == NODE and od.bitrate == BITRATE
    assert values == held
    expected = {key for key in _WRITTEN_BY_STARTUP if key[0] not in removed}
    assert expected <= set(values)
    assert values[Obj.MODES_OF_OPERATION, 0] == 9
    assert values[Obj.PRODUCER_HEARTBEAT_TIME, 0] == config.drive.heartbeat_producer_ms
    # TPDO1's mapping as run installs it: statusword and velocity first (plus the torque when it is alone)
    tpdo1 = [MappingEntry.decode(values[Obj.TPDO_MAPPING, sub]).index
             for sub in range(1, values[Obj.TPDO_MAPPING, 0] + 1)]
    assert tpdo1[:2] == [Obj.STATUSWORD, Obj.VELOCITY_ACTUAL_VALUE]
    assert (Obj.TORQUE_ACTUAL_VALUE in tpdo1) == bool(removed)
    assert document["dcf"]["file"] == str(dcf) and len(document["dcf"]["parameters"]) == len(values)


def test_a_dcf_that_cannot_be_written_is_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, document, err = run_json(capsys, "commission", "info", "--dcf", str(tmp_path / "no" / "such" / "d.dcf"))
    assert code == 2
    assert "--dcf" in document["error"]["message"] and len(err.strip().splitlines()) == 1
