"""``commission check``: before any motion, whether ``run`` will work on a drive and why (issue 12).

Each verdict is held against what ``run`` then does on the same config: a drive the check passes (with warnings
for the optional objects it lacks) runs its trials; one it fails is refused by ``run`` too, for the object the
check named. The drives are the emulator on canopen's ``LocalNode`` with the EDS of
``tests.support.standard_drives`` (objects removed from what the drive has, from what the master's EDS says, or
both). The check itself only reads: a tap on the drive's channel sees no SDO download, NMT command or PDO.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import pytest

from drivers.bus import open_bus, parse_bus_spec
from drivers.cia301 import NMT_COB_ID, FunctionCode, cob_id
from drivers.cia402 import Obj, State402
from drivers.od import DEFAULT_EDS
from foilc_hil.config import load_config
from tests.support.commission_bus import emulated_bus, run_json
from tests.support.standard_drives import NODE, cli, config_file, mutated_eds

_SDO_DOWNLOAD_REQUESTS = range(0x20, 0x30)  # client command specifier 1 (initiate download), CiA 301


def _verdicts(document: dict[str, Any], verdict: str) -> set[str]:
    return {check["object"] for check in document["checks"] if check["verdict"] == verdict}


def _run(tmp_path: Path, config: Path) -> tuple[int, dict[str, Any]]:
    return cli("run", "--config", str(config), "--emulator", "embedded", "--out", str(tmp_path / "run.mcap"))


def test_the_emulated_drive_passes_and_the_check_changes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = load_config(config_file(tmp_path, DEFAULT_EDS, DEFAULT_EDS))
    with emulated_bus([NODE], config) as bus:
        drive = bus.drives[NODE]
        before = (drive.state, drive.nmt_state)
        with open_bus(parse_bus_spec(bus.spec)) as tap:  # a third end of the channel: every frame the check sends
            code, document, _ = run_json(capsys, "commission", "check", "--bus", bus.spec,
                                         "--config", str(tmp_path / "standard.yaml"))
            frames: list[can.Message] = []
            while (message := tap.recv(0)) is not None:
                frames.append(message)
        assert (drive.state, drive.nmt_state) == before
    assert code == 0, document
    assert document["runnable"] is True and document["counts"]["fail"] == 0
    assert document["node_id"] == NODE and document["mode"] == "CYCLIC_SYNC_VELOCITY"
    # every object the velocity loop needs was read from the drive itself
    assert {"0x6040:00", "0x60FF:00", "0x6041:00", "0x606C:00", "0x6060:00", "0x1017:00"} <= _verdicts(document,
                                                                                                        "pass")
    assert "bus.load_limit" in _verdicts(document, "pass")
    sdo_requests = [m for m in frames if m.arbitration_id == cob_id(FunctionCode.SDO_RX, NODE)]
    assert sdo_requests, "the check must have asked the drive"
    assert not [m for m in sdo_requests if m.data[0] in _SDO_DOWNLOAD_REQUESTS]
    assert not [m for m in frames if m.arbitration_id in (NMT_COB_ID, cob_id(FunctionCode.RPDO1, NODE))]
    assert before[0] is State402.SWITCH_ON_DISABLED


def test_a_drive_without_optional_objects_passes_with_warnings_and_runs(tmp_path: Path) -> None:
    removed = (Obj.COMMUNICATION_CYCLE_PERIOD, Obj.CONSUMER_HEARTBEAT_TIME, Obj.TORQUE_ACTUAL_VALUE, 0x1801, 0x1A01)
    eds = mutated_eds(tmp_path, *removed)
    config = config_file(tmp_path, eds, eds)
    code, document = cli("commission", "check", "--config", str(config))
    assert code == 0, document
    assert document["runnable"] is True
    assert {"0x1006", "0x1016", "0x6077"} <= _verdicts(document, "warn")
    assert not any(check["object"].startswith("0x6077") for check in document["checks"]
                   if check["verdict"] == "pass")
    code_run, ran = _run(tmp_path, config)
    assert code_run == 0, ran


def test_a_drive_lacking_velocity_feedback_is_refused_naming_0x606c(tmp_path: Path) -> None:
    config = config_file(tmp_path, mutated_eds(tmp_path, Obj.VELOCITY_ACTUAL_VALUE), DEFAULT_EDS)
    code, document = cli("commission", "check", "--config", str(config))
    assert code == 1
    assert document["runnable"] is False
    assert _verdicts(document, "fail") == {"0x606C"}
    assert "0x606C" in document["error"]["message"] and document["error"]["kind"] == "runtime_failure"


def test_an_object_the_eds_promises_and_the_drive_lacks_is_found_over_sdo(tmp_path: Path) -> None:
    # the master's EDS has 0x6077, so run maps it; the drive itself has no such object
    config = config_file(tmp_path, DEFAULT_EDS, mutated_eds(tmp_path, Obj.TORQUE_ACTUAL_VALUE))
    code, document = cli("commission", "check", "--config", str(config))
    assert code == 1
    (failed,) = [check for check in document["checks"] if check["verdict"] == "fail"]
    assert failed["object"] == "0x6077:00" and "TPDO2" in failed["detail"]
    code_run, ran = _run(tmp_path, config)
    # run fails where it writes that object into TPDO2's mapping (0x1A01), after the check said so before
    assert code_run == 1 and "0x1A01" in ran["error"]["message"]


def test_a_bus_too_slow_for_the_schedule_fails_as_run_refuses_it(tmp_path: Path) -> None:
    config = config_file(tmp_path, DEFAULT_EDS, DEFAULT_EDS)
    code, document = cli("commission", "check", "--config", str(config), "-b", "20000")
    assert code == 1
    assert _verdicts(document, "fail") == {"bus.load_limit"}
    code_run, ran = cli("run", "--config", str(config), "-b", "20000", "--out", str(tmp_path / "r.mcap"))
    assert code_run == 2 and "bus.load_limit" in ran["error"]["message"]


def test_a_drive_in_fault_is_refused_as_run_s_enable_would(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = load_config(config_file(tmp_path, DEFAULT_EDS, DEFAULT_EDS))
    with emulated_bus([NODE], config) as bus:
        bus.drives[NODE].inject_fault("over-current")
        code, document, err = run_json(capsys, "commission", "check", "--bus", bus.spec,
                                       "--config", str(tmp_path / "standard.yaml"))
        assert bus.drives[NODE].state is State402.FAULT  # still: the check reset nothing
    assert code == 1
    (failed,) = [check for check in document["checks"] if check["verdict"] == "fail"]
    assert failed["object"] == "0x6041" and "FAULT" in failed["detail"] and "0x603F" in failed["detail"]
    assert err.startswith(f"foilc-hil commission: run would refuse node {NODE}: 0x6041")
