"""``commission info --dbc``: cantools (an independent DBC reader) decodes a run log's frames to the logged values.

The run and the DBC use the same config; the DBC describes the mapping ``run`` installs. cantools loads it in
strict mode (no overlapping signals), decodes every TPDO the drive sent during the run, and the scaled velocity
must be the ``/ilc/sample`` output the bench logged (in rpm, not in 0.001 rpm counts); every RPDO decodes to a
402 command and a target within one count of the law's command.

``export F.mcap --format dbc`` writes the same DBC from the log alone (the mapping the run installed is in its
metadata): on a drive with one TPDO, with the EDS gone after the run, cantools still decodes the log with it.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
from pathlib import Path
from typing import Any, cast

import cantools
import pytest
import yaml

from drivers.cia301 import FunctionCode, cob_id
from drivers.cia402 import STATE_STATUSWORD, Command402, State402
from foilc_hil.cli import main
from foilc_hil.io.mcap_log import read_log
from tests.support.standard_drives import mutated_eds

NODE = 4
SCALE = 1000.0


def _config(tmp_path: Path, **drive: Any) -> Path:
    document = {
        "plant": {"model": "first_order", "a": -1.23, "b": 1.68, "c": 1.0},
        "reference": {"profile": "piecewise", "segments": [{"duration": 0.1, "start": 0.0, "end": 20.0}]},
        "sample_time": 0.005,
        "trials": 2,
        "law": {"kind": "p-type"},
        "drive": {"node_id": NODE, "velocity_scale": SCALE, "velocity_limit": 500.0, "heartbeat_timeout_factor": 10.0,
                  "heartbeat_consumer_ms": 2000, **drive},
        "bench": {"settle_time": 0.01, "settle_tolerance": 0.5},
    }
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def _cli(*argv: str) -> dict[str, Any]:
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert main([*argv, "--json"]) == 0
    document: dict[str, Any] = json.loads(stdout.getvalue())
    return document


def test_cantools_decodes_a_run_log_to_the_logged_values(tmp_path: Path) -> None:
    config = _config(tmp_path)
    log = tmp_path / "run.mcap"
    _cli("run", "--config", str(config), "--emulator", "embedded", "--out", str(log))
    dbc = tmp_path / "drive.dbc"
    _cli("commission", "info", "--config", str(config), "--dbc", str(dbc))
    db = cantools.database.load_file(str(dbc), strict=True)
    assert isinstance(db, cantools.database.can.Database)
    assert [node.name for node in db.nodes] == ["foilc_hil_master", f"drive_{NODE}"]
    tpdo1 = db.get_message_by_frame_id(cob_id(FunctionCode.TPDO1, NODE))
    assert tpdo1.senders == [f"drive_{NODE}"]
    assert tpdo1.get_signal_by_name("velocity_actual_value").unit == "rpm"

    _assert_decodes_to_the_logged_values(db, log)


def _assert_decodes_to_the_logged_values(db: cantools.database.can.Database, log: Path) -> None:
    """Every ``/ilc/sample`` output is a decoded TPDO velocity; every command a decoded RPDO target."""
    contents = read_log(log)
    decoded: list[dict[str, Any]] = [
        {"id": frame["id"], **cast(dict[str, Any], db.decode_message(frame["id"], base64.b64decode(frame["data"])))}
        for frame in contents.frames if frame["id"] in {message.frame_id for message in db.messages}
    ]
    velocities = [d["velocity_actual_value"] for d in decoded if "velocity_actual_value" in d]
    outputs = [row["output"] for row in contents.samples]
    assert max(abs(y) for y in outputs) > 1.0  # the axis moved: the check below is not about zeros
    for y in outputs:  # every logged output is a decoded frame's velocity, in plant units (not counts)
        assert min(abs(v - y) for v in velocities) <= 1e-9 * max(1.0, abs(y))
    states = {str(d["statusword_state"]) for d in decoded if "statusword_state" in d}
    assert State402.OPERATION_ENABLED.name in states
    commands = [d for d in decoded if "controlword_command" in d]
    assert {str(d["controlword_command"]) for d in commands} >= {Command402.ENABLE_OPERATION.name,
                                                                 Command402.SHUTDOWN.name}
    controls = [row["control"] for row in contents.samples]
    targets = [d["target_velocity"] for d in commands]
    for u in controls:  # quantised to one count (0.001 rpm) on the way to the drive
        assert min(abs(t - u) for t in targets) <= 0.5 / SCALE + 1e-12


def _offline_dbc(tmp_path: Path, eds: Path | None = None, **drive: Any) -> cantools.database.can.Database:
    """The DBC of the plan ``run`` computes from an EDS, written without a bus (what ``info --dbc`` writes)."""
    from drivers.cia402_master import pdo_plan
    from drivers.config import DriveConfig
    from drivers.od import load_od
    from foilc_hil.commission.dbc import write_dbc

    cfg = DriveConfig.model_validate({"node_id": NODE, "velocity_scale": SCALE, **drive})
    plan = pdo_plan(cfg.operation_mode, NODE, load_od(eds, NODE))
    path = tmp_path / "offline.dbc"
    write_dbc([(plan, cfg)], path)
    db = cantools.database.load_file(str(path))
    assert isinstance(db, cantools.database.can.Database)
    return db


def test_the_state_value_table_names_every_402_state(tmp_path: Path) -> None:
    db = _offline_dbc(tmp_path, velocity_unit="rad/s")
    tpdo1 = db.get_message_by_frame_id(cob_id(FunctionCode.TPDO1, NODE))
    assert tpdo1.get_signal_by_name("velocity_actual_value").unit == "rad/s"
    for state, pattern in STATE_STATUSWORD.items():  # CiA 402-2's coding, from drivers.cia402
        payload = pattern.to_bytes(2, "little") + bytes(4)
        assert str(cast(dict[str, Any], tpdo1.decode(payload))["statusword_state"]) == state.name


def test_the_dbc_has_the_mapping_run_installs_on_a_drive_with_one_tpdo(tmp_path: Path) -> None:
    db = _offline_dbc(tmp_path, mutated_eds(tmp_path, 0x1801, 0x1802, 0x1803, 0x1A01, 0x1A02, 0x1A03))
    tpdos = [m for m in db.messages if m.senders == [f"drive_{NODE}"]]
    assert [m.frame_id for m in tpdos] == [cob_id(FunctionCode.TPDO1, NODE)]
    assert [s.name for s in tpdos[0].signals] == [
        "statusword_state", "statusword_flags", "velocity_actual_value", "torque_actual_value",
    ]


def test_info_writes_other_canmatrix_formats(tmp_path: Path) -> None:
    out = tmp_path / "drive.sym"
    document = _cli("commission", "info", "--config", str(_config(tmp_path)), "--dbc", str(out))
    assert out.stat().st_size > 0
    assert [frame["arbitration_id"] for frame in document["dbc"]["frames"]] == [
        cob_id(FunctionCode.RPDO1, NODE), cob_id(FunctionCode.TPDO1, NODE), cob_id(FunctionCode.TPDO2, NODE),
    ]


def test_export_writes_the_dbc_of_the_mapping_the_run_installed(tmp_path: Path) -> None:
    one_tpdo = mutated_eds(tmp_path, 0x1801, 0x1802, 0x1803, 0x1A01, 0x1A02, 0x1A03)
    config = _config(tmp_path, eds=str(one_tpdo))
    document = yaml.safe_load(config.read_text(encoding="utf-8"))
    config.write_text(yaml.safe_dump({**document, "emulator": {"eds": str(one_tpdo)}}), encoding="utf-8")
    log = tmp_path / "run.mcap"
    _cli("run", "--config", str(config), "--emulator", "embedded", "--out", str(log))
    one_tpdo.unlink()  # the DBC must come from the log's metadata, not from the drive's EDS
    dbc = tmp_path / "from_log.dbc"
    exported = _cli("export", str(log), "--format", "dbc", "--out", str(dbc))
    assert exported["dbc"]["file"] == str(dbc)
    db = cantools.database.load_file(str(dbc), strict=True)
    assert isinstance(db, cantools.database.can.Database)
    tpdos = [m for m in db.messages if m.senders == [f"drive_{NODE}"]]
    assert [m.frame_id for m in tpdos] == [cob_id(FunctionCode.TPDO1, NODE)]  # not the shipped EDS's TPDO1 + TPDO2
    assert "torque_actual_value" in [s.name for s in tpdos[0].signals]
    _assert_decodes_to_the_logged_values(db, log)


def test_export_dbc_of_a_log_without_the_mapping_record_uses_the_logged_drive_section(tmp_path: Path) -> None:
    from foilc_hil.config import dump_config, load_config
    from foilc_hil.io.mcap_log import McapLogWriter

    log = tmp_path / "old.mcap"
    McapLogWriter(log, config_yaml=dump_config(load_config(_config(tmp_path, velocity_unit="rad/s")))).close()
    _cli("export", str(log), "--format", "dbc", "--out", str(tmp_path / "old.dbc"))
    db = cantools.database.load_file(str(tmp_path / "old.dbc"))
    assert isinstance(db, cantools.database.can.Database)
    offline = _offline_dbc(tmp_path, velocity_unit="rad/s")
    assert [(m.frame_id, [s.name for s in m.signals]) for m in db.messages] == [
        (m.frame_id, [s.name for s in m.signals]) for m in offline.messages]
    tpdo1 = db.get_message_by_frame_id(cob_id(FunctionCode.TPDO1, NODE))
    assert tpdo1.get_signal_by_name("velocity_actual_value").unit == "rad/s"
    assert tpdo1.get_signal_by_name("velocity_actual_value").scale == 1 / SCALE


def test_export_dbc_of_a_log_without_a_config_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from foilc_hil.io.mcap_log import McapLogWriter

    log = tmp_path / "bare.mcap"
    McapLogWriter(log, config_yaml=None).close()
    assert main(["export", str(log), "--format", "dbc", "--out", str(tmp_path / "x.dbc")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "foilc_hil.config" in err
