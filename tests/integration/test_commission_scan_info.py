"""``commission scan`` finds several emulated drives on one bus; ``commission info`` decodes a drive and exports
its PDO mapping as a DBC that canmatrix loads."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import canmatrix.formats
import pytest

from drivers.bus import open_bus
from drivers.cia301 import NMT_COB_ID, FunctionCode, NmtCommand, NmtState, cob_id
from drivers.cia402 import Obj, State402
from drivers.config import BusConfig
from tests.support.commission_bus import emulated_bus, run_cli, run_json

pytestmark = pytest.mark.timeout(120)

NODES = (3, 17, 99)
EDS_IDENTITY = {"vendor_id": 0x464F494C, "product_code": 0x402, "revision": 0x00010000, "serial": 1}


def test_scan_finds_silent_drives_by_sdo(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus(NODES) as bus:
        # a short listen is below the drives' 1 s heartbeat: the SDO probe has to find them
        code, document, _ = run_json(capsys, "commission", "scan", "--bus", bus.spec, "--timeout", "0.05")
    assert code == 0
    nodes = document["nodes"]
    assert [n["node_id"] for n in nodes] == list(NODES)
    for node in nodes:
        assert "sdo" in node["found_by"]
        assert node["profile"] == 402
        assert node["identity"] == EDS_IDENTITY


@pytest.mark.slow
def test_scan_reads_nmt_states_from_heartbeats(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus(NODES) as bus:
        # node 17 operational, 99 stopped (no SDO answers in stopped: only its heartbeat can reveal it)
        with open_bus(BusConfig(interface="inprocess", channel=bus.channel)) as sender:
            for command, node in ((NmtCommand.START, 17), (NmtCommand.STOP, 99)):
                sender.send(can.Message(arbitration_id=NMT_COB_ID, data=[int(command), node], is_extended_id=False))
        code, document, _ = run_json(capsys, "commission", "scan", "--bus", bus.spec, "--timeout", "1.3",
                                     "--node-range", "1-100")
        assert bus.drives[99].nmt_state is NmtState.STOPPED
    assert code == 0
    states = {n["node_id"]: n["nmt_state"] for n in document["nodes"]}
    assert states == {3: "PRE_OPERATIONAL", 17: "OPERATIONAL", 99: "STOPPED"}
    stopped = next(n for n in document["nodes"] if n["node_id"] == 99)
    assert stopped["found_by"] == ["heartbeat"] and stopped["errors"]  # identity unreadable in stopped


def test_scan_with_nmt_reset_sees_boot_ups(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus(NODES) as bus:
        code, out, _ = run_cli(capsys, "commission", "scan", "--bus", bus.spec, "--timeout", "0.3", "--nmt-reset")
    assert code == 0
    rows = [line.split() for line in out.splitlines() if line.strip()[:1].isdigit()]
    assert [int(r[0]) for r in rows] == list(NODES)
    assert all("boot-up," in r or "boot-up" in r for r in rows)


def test_scan_range_excludes_other_nodes(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus(NODES) as bus:
        code, document, _ = run_json(capsys, "commission", "scan", "--bus", bus.spec, "--timeout", "0.05",
                                     "--node-range", "10-20")
    assert code == 0
    assert [n["node_id"] for n in document["nodes"]] == [17]


@pytest.mark.parametrize("bad", ["0-5", "5-2", "x", "1-200"])
def test_scan_bad_range_exits_2(bad: str, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_cli(capsys, "commission", "scan", "--node-range", bad)
    assert code == 2 and "--node-range" in err and len(err.strip().splitlines()) == 1


def test_info_decodes_the_drive(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus([5]) as bus:
        drive = bus.drives[5]
        drive.inject_fault("over-current")
        code, document, _ = run_json(capsys, "commission", "info", "--bus", bus.spec, "--node-id", "5")
        statusword = int(drive.node.read(Obj.STATUSWORD))
    assert code == 0
    assert document["identity"] == EDS_IDENTITY
    assert document["nmt_state"] == "PRE_OPERATIONAL"
    modes = {m["mode"] for m in document["supported_modes"]["modes"]}
    assert modes == {3, 9, 10}  # 0x6502 = 0x304: bits 2, 8, 9
    assert document["mode"] == {"value": 9, "name": "cyclic synchronous velocity (csv)"}
    assert document["statusword"]["value"] == statusword
    assert document["statusword"]["state"] == State402.FAULT.name
    assert "FAULT" in document["statusword"]["flags"]
    assert document["error_code"]["value"] == 0x2310
    assert "over-current" in document["error_code"]["text"]
    assert set(document["error_register"]["bits"]) == {"generic", "current"}
    tpdo1 = next(p for p in document["pdos"] if p["direction"] == "TPDO" and p["number"] == 1)
    assert tpdo1["cob_id"] == 0x185 and tpdo1["valid"]
    assert [(m["index"], m["bits"]) for m in tpdo1["mapped"]] == [(0x6041, 16), (0x606C, 32)]


def test_info_dbc_loads_in_canmatrix_with_the_mapping_run_installs(capsys: pytest.CaptureFixture[str],
                                                                   tmp_path: Path) -> None:
    dbc = tmp_path / "drive.dbc"
    with emulated_bus([6]) as bus:
        code, document, _ = run_json(capsys, "commission", "info", "--bus", bus.spec, "--node-id", "6",
                                     "--dbc", str(dbc))
    assert code == 0
    db = canmatrix.formats.loadp_flat(str(dbc))
    assert db is not None
    loaded: list[Any] = list(db.frames)  # canmatrix's Frame is not typed for mypy
    frames = {frame.arbitration_id.id: frame for frame in loaded}
    # the EDS defaults (info's "pdos") map RPDO2 too; run installs RPDO1, TPDO1 and TPDO2 only (velocity mode)
    assert any(p["direction"] == "RPDO" and p["number"] == 2 and p["valid"] for p in document["pdos"])
    rpdo1, tpdo1_id, tpdo2 = (cob_id(code, 6) for code in (FunctionCode.RPDO1, FunctionCode.TPDO1, FunctionCode.TPDO2))
    assert set(frames) == {rpdo1, tpdo1_id, tpdo2}
    for frame in loaded:
        assert frame.size == max(s.start_bit + s.size for s in frame.signals) // 8
    tpdo1 = frames[tpdo1_id]
    assert [s.name for s in sorted(tpdo1.signals, key=lambda s: s.start_bit)] == [
        "statusword_state", "statusword_flags", "velocity_actual_value",
    ]
    velocity = next(s for s in tpdo1.signals if s.name == "velocity_actual_value")
    assert velocity.is_signed and velocity.start_bit == 16 and velocity.unit == "rpm"


@pytest.mark.slow
def test_info_text_and_bad_dbc_suffix(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, out, _ = run_cli(capsys, "commission", "info")
    assert code == 0 and "supported modes" in out and "TPDO1" in out and "SWITCH_ON_DISABLED" in out
    code, _, err = run_cli(capsys, "commission", "info", "--dbc", str(tmp_path / "x.txt"))
    assert code == 2 and "--dbc" in err
