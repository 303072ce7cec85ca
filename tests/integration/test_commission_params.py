"""``commission params read|write``: round trip, EDS refusal, drive aborts with rollback, exit codes.

The CLI runs in-process against emulated drives on a shared ``virtual`` channel, so what one command wrote is
checked by the next command and directly in the drive's object dictionary.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from plant_emulator.device import VirtualDrive
from tests.support.commission_bus import emulated_bus, run_cli, run_json

pytestmark = pytest.mark.timeout(120)

NODE = 4
SHIPPED = Path(__file__).resolve().parents[2] / "configs" / "params_example.yaml"


def _set(path: Path, entries: list[dict[str, object]]) -> str:
    path.write_text(yaml.safe_dump({"parameters": entries}), encoding="utf-8")
    return str(path)


def _value(drive: VirtualDrive, index: int, subindex: int = 0) -> int:
    return int(drive.node.read(index, subindex))  # the emulator's own store


def test_write_then_read_round_trips_the_shipped_set(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    wanted = yaml.safe_load(SHIPPED.read_text())["parameters"]
    with emulated_bus([NODE]) as bus:
        before = {e["index"]: _value(bus.drives[NODE], e["index"]) for e in wanted}
        assert all(before[e["index"]] != e["value"] for e in wanted)  # the set really changes something
        code, document, _ = run_json(capsys, "commission", "params", "write", str(SHIPPED), "--bus", bus.spec,
                                     "--node-id", str(NODE))
        assert code == 0 and document["ok"] is True
        for change, entry in zip(document["changes"], wanted, strict=True):
            assert (change["old"], change["new"], change["status"]) == (before[entry["index"]], entry["value"],
                                                                         "changed")
        # read with the same file: the YAML has the same entries with the new values
        out = tmp_path / "now.yaml"
        code, _, _ = run_cli(capsys, "commission", "params", "read", str(SHIPPED), "--bus", bus.spec,
                             "--node-id", str(NODE), "--out", str(out))
        assert code == 0
        read = yaml.safe_load(out.read_text())["parameters"]
        assert [(r["name"], int(r["index"], 0), r["subindex"], r["value"]) for r in read] == [
            (e["name"], e["index"], e["subindex"], e["value"]) for e in wanted
        ]
        # and the drive itself holds them
        assert all(_value(bus.drives[NODE], e["index"]) == e["value"] for e in wanted)
        # writing the read-back file again changes nothing
        code, document, _ = run_json(capsys, "commission", "params", "write", str(out), "--bus", bus.spec,
                                     "--node-id", str(NODE))
        assert code == 0 and {c["status"] for c in document["changes"]} == {"unchanged"}


def test_read_only_object_is_refused_before_anything_is_written(capsys: pytest.CaptureFixture[str],
                                                                tmp_path: Path) -> None:
    path = _set(tmp_path / "ro.yaml", [
        {"name": "max_torque", "index": 0x6072, "value": 1800},
        {"name": "statusword", "index": 0x6041, "value": 1},
    ])
    with emulated_bus([NODE]) as bus:
        before = _value(bus.drives[NODE], 0x6072)
        code, out, err = run_cli(capsys, "commission", "params", "write", path, "--bus", bus.spec,
                                 "--node-id", str(NODE))
        assert code == 1
        assert "0x06010002" in out and "attempt to write a read-only object" in out
        assert "nothing was written" in err
        assert _value(bus.drives[NODE], 0x6072) == before


def test_read_only_write_sent_anyway_gets_the_drives_abort_and_is_rolled_back(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    path = _set(tmp_path / "ro.yaml", [
        {"name": "max_torque", "index": 0x6072, "value": 1800},
        {"name": "statusword", "index": 0x6041, "value": 1},
    ])
    with emulated_bus([NODE]) as bus:
        before = _value(bus.drives[NODE], 0x6072)
        code, document, err = run_json(capsys, "commission", "params", "write", path, "--bus", bus.spec,
                                       "--node-id", str(NODE), "--skip-eds-check")
        assert code == 1
        assert "aborted with 0x06010002: attempt to write a read-only object" in err
        assert document["rolled_back"] == ["max_torque"] and not document["not_restored"]
        assert _value(bus.drives[NODE], 0x6072) == before  # max_torque was written, then restored


def test_out_of_range_value_is_refused_with_the_decoded_abort(capsys: pytest.CaptureFixture[str],
                                                               tmp_path: Path) -> None:
    path = _set(tmp_path / "range.yaml", [
        {"name": "quick_stop_option", "index": 0x605A, "value": 5},
        {"name": "max_torque", "index": 0x6072, "value": 5000},  # EDS HighLimit 3000
    ])
    with emulated_bus([NODE]) as bus:
        before = _value(bus.drives[NODE], 0x605A)
        code, document, _ = run_json(capsys, "commission", "params", "write", path, "--bus", bus.spec,
                                     "--node-id", str(NODE))
        assert code == 1
        assert document["ok"] is False
        assert any("0x06090031" in r and "written too high" in r for r in document["refused"])
        assert _value(bus.drives[NODE], 0x605A) == before


def test_abort_mid_set_rolls_back_the_entries_already_written(capsys: pytest.CaptureFixture[str],
                                                              tmp_path: Path) -> None:
    # mode 4 (profile torque) is inside the EDS range 3..10 but the drive does not support it: the drive aborts
    path = _set(tmp_path / "mid.yaml", [
        {"name": "max_torque", "index": 0x6072, "value": 1200},
        {"name": "velocity_loop_gain", "index": 0x2001, "value": 250},
        {"name": "mode", "index": 0x6060, "value": 4},
        {"name": "quick_stop_option", "index": 0x605A, "value": 5},
    ])
    with emulated_bus([NODE]) as bus:
        drive = bus.drives[NODE]
        before = {index: _value(drive, index) for index in (0x6072, 0x2001, 0x6060, 0x605A)}
        code, document, err = run_json(capsys, "commission", "params", "write", path, "--bus", bus.spec,
                                       "--node-id", str(NODE))
        assert code == 1
        assert "0x06090030" in err and "invalid value for parameter" in err
        assert document["rolled_back"] == ["velocity_loop_gain", "max_torque"]  # newest first
        statuses = [c["status"] for c in document["changes"]]
        assert statuses == ["rolled back", "rolled back", "failed", "pending"]
        assert {index: _value(drive, index) for index in before} == before


def test_read_without_a_file_dumps_the_eds_parameters(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus([NODE]) as bus:
        code, document, _ = run_json(capsys, "commission", "params", "read", "--bus", bus.spec,
                                     "--node-id", str(NODE))
    assert code == 0
    names = {p["name"]: p for p in document["parameters"]}
    assert names["max_torque"]["value"] == 1000 and names["velocity_loop_gain"]["value"] == 100
    assert "controlword" not in names and "target_velocity" not in names  # process data are not parameters


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["params", "write"], "give the parameter set"),
        (["params", "write", "{missing}"], "no such file"),
        (["params", "write", "{bad}"], "parameters.0.index"),
        (["params", "write", "{novalue}"], "needs a value"),
        (["params", "bogus"], "invalid choice"),
    ],
)
def test_bad_parameter_files_exit_2(argv: list[str], needle: str, capsys: pytest.CaptureFixture[str],
                                    tmp_path: Path) -> None:
    files = {
        "missing": str(tmp_path / "nope.yaml"),
        "bad": _set(tmp_path / "bad.yaml", [{"name": "x", "index": "sixty", "value": 1}]),
        "novalue": _set(tmp_path / "novalue.yaml", [{"name": "x", "index": 0x6072}]),
    }
    code, _out, err = run_cli(capsys, "commission", *[a.format(**files) for a in argv])
    assert code == 2
    assert needle in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
