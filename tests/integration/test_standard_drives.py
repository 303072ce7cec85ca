"""The bench on standard CiA 402 drives that lack optional objects (issue 12).

0x1006 (cycle period) and 0x1016 (consumer heartbeat) are optional in CiA 301, 0x6077 (torque actual) in CiA 402,
and a velocity loop needs no second TPDO. Each is removed, one at a time, from the EDS that both the emulated drive
(``emulator.eds``) and the master (``drive.eds``) load; ``foilc-hil run`` must then finish its trials, map only what
the EDS has, and ``commission enable`` must agree. A drive lacking what the mode truly needs (0x606C) is refused by
both, naming the object.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.cia301 import TPDO_BASES, cob_id
from drivers.cia402 import Obj, OperationMode
from drivers.cia402_master import pdo_plan
from drivers.od import DEFAULT_EDS, load_od
from foilc_hil.io.mcap_log import read_log
from tests.support.standard_drives import NODE, cli, config_file, mutated_eds


@pytest.mark.slow
def test_the_mutation_removes_only_the_named_objects(tmp_path: Path) -> None:
    full = load_od(DEFAULT_EDS, NODE)
    od = load_od(mutated_eds(tmp_path, Obj.TORQUE_ACTUAL_VALUE, 0x1801, 0x1A01), NODE)
    assert {Obj.TORQUE_ACTUAL_VALUE, 0x1801, 0x1A01} <= set(full.indices) - set(od.indices)
    assert set(full.indices) - set(od.indices) == {Obj.TORQUE_ACTUAL_VALUE, 0x1801, 0x1A01}


@pytest.mark.slow
@pytest.mark.parametrize(
    "removed",
    [(Obj.COMMUNICATION_CYCLE_PERIOD,), (Obj.CONSUMER_HEARTBEAT_TIME,), (Obj.TORQUE_ACTUAL_VALUE,), (0x1801, 0x1A01)],
    ids=["no-0x1006", "no-0x1016", "no-0x6077", "no-TPDO2"],
)
def test_run_and_enable_work_on_a_drive_without_an_optional_object(tmp_path: Path, removed: tuple[int, ...]) -> None:
    eds = mutated_eds(tmp_path, *removed)
    config = config_file(tmp_path, eds, eds)
    out = tmp_path / "run.mcap"
    code, document = cli("run", "--config", str(config), "--emulator", "embedded", "--out", str(out))
    assert code == 0, document
    assert [trial["trial"] for trial in document["trials"]] == [1, 2]

    # the master mapped only what the EDS has: no TPDO or setting names a removed object
    plan = pdo_plan(OperationMode.CYCLIC_SYNC_VELOCITY, NODE, load_od(eds, NODE))
    mapped = {variable.index for layout in plan.tpdos for variable in layout.variables}
    assert {Obj.STATUSWORD, Obj.VELOCITY_ACTUAL_VALUE} <= mapped
    assert not mapped & set(removed)
    assert all(layout.number != 2 for layout in plan.tpdos) or 0x1801 not in removed
    contents = read_log(out)
    assert len(contents.samples) == 2 * 20
    # the drive answered on the TPDOs of the plan and on no other
    tpdo_ids = {layout.cob_id for layout in plan.tpdos}
    every_tpdo = {cob_id(base, NODE) for base in TPDO_BASES}
    received = {frame["id"] for frame in contents.frames if frame["dir"] == "rx" and frame["id"] in every_tpdo}
    assert received == tpdo_ids

    code, enabled = cli("commission", "enable", "--config", str(config))
    assert code == 0, enabled
    assert enabled["final_state"] == "OPERATION_ENABLED"
    assert any(note.startswith("run can configure CYCLIC_SYNC_VELOCITY") for note in enabled["notes"])


def test_with_one_tpdo_the_torque_shares_tpdo1_and_the_position_is_left_out(tmp_path: Path) -> None:
    one_tpdo = mutated_eds(tmp_path, 0x1801, 0x1802, 0x1803, 0x1A01, 0x1A02, 0x1A03)
    plan = pdo_plan(OperationMode.CYCLIC_SYNC_VELOCITY, NODE, load_od(one_tpdo, NODE))
    (tpdo,) = plan.tpdos
    assert [variable.index for variable in tpdo.variables] == [
        Obj.STATUSWORD, Obj.VELOCITY_ACTUAL_VALUE, Obj.TORQUE_ACTUAL_VALUE,
    ]
    assert sum(variable.bits for variable in tpdo.variables) <= 64
    assert any("0x6064" in note for note in plan.notes)


def test_run_and_enable_both_refuse_a_drive_without_velocity_feedback(tmp_path: Path) -> None:
    lacking = mutated_eds(tmp_path, Obj.VELOCITY_ACTUAL_VALUE)
    config = config_file(tmp_path, lacking, DEFAULT_EDS)  # the emulator has it; the master reads the drive's EDS
    code_run, run = cli("run", "--config", str(config), "--emulator", "embedded", "--out", str(tmp_path / "r.mcap"))
    code_enable, enable = cli("commission", "enable", "--config", str(config))
    assert code_run == code_enable == 1
    for document in (run, enable):
        assert "0x606C" in document["error"]["message"]
