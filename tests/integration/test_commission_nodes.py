"""``commission enable|disable|fault-reset|info --node-id 1,2,3,4``: each node acted on over one shared network,
one document per node in ``--json``; a failed multi-node enable leaves no node enabled."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.cia301 import FunctionCode, cob_id
from drivers.cia402 import State402
from tests.support.commission_bus import emulated_bus, run_cli, run_json

pytestmark = pytest.mark.timeout(120)

NODES = (1, 2, 3, 4)


def test_enable_and_disable_several_nodes(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus([*NODES, 9]) as bus:  # node 9 is on the bus but not named: left alone
        code, document, _ = run_json(capsys, "commission", "enable", "--bus", bus.spec, "--node-id", "1-4")
        assert code == 0 and document["action"] == "enable"
        assert [node["node_id"] for node in document["nodes"]] == list(NODES)
        assert [node["final_state"] for node in document["nodes"]] == ["OPERATION_ENABLED"] * 4
        assert [bus.drives[n].state for n in (*NODES, 9)] == [State402.OPERATION_ENABLED] * 4 + [
            State402.SWITCH_ON_DISABLED]
        code, out, _ = run_cli(capsys, "commission", "disable", "--bus", bus.spec, "--node-id", "2,4")
        assert code == 0 and "node 2 disable:" in out and "node 4 disable:" in out
        assert [bus.drives[n].state for n in NODES] == [State402.OPERATION_ENABLED, State402.SWITCH_ON_DISABLED,
                                                        State402.OPERATION_ENABLED, State402.SWITCH_ON_DISABLED]


def test_a_failed_enable_disables_the_nodes_it_enabled(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus(NODES) as bus:
        bus.drives[3].inject_fault("over-current")
        code, _, err = run_cli(capsys, "commission", "enable", "--bus", bus.spec, "--node-id", "1,2,3,4")
        assert code == 1 and "node 3 is in FAULT" in err
        assert [bus.drives[n].state for n in NODES] == [State402.SWITCH_ON_DISABLED, State402.SWITCH_ON_DISABLED,
                                                        State402.FAULT, State402.SWITCH_ON_DISABLED]
        code, document, _ = run_json(capsys, "commission", "fault-reset", "--bus", bus.spec, "--node-id", "3,4")
        assert code == 0
        assert [node["final_state"] for node in document["nodes"]] == ["SWITCH_ON_DISABLED"] * 2
        assert "no fault to reset (drive in SWITCH_ON_DISABLED)" in document["nodes"][1]["notes"]
        assert bus.drives[3].state is State402.SWITCH_ON_DISABLED


def test_info_on_the_embedded_emulator_for_several_nodes(capsys: pytest.CaptureFixture[str]) -> None:
    code, document, _ = run_json(capsys, "commission", "info", "--node-id", "5,6")
    assert code == 0 and document["action"] == "info"
    assert [node["node_id"] for node in document["nodes"]] == [5, 6]
    assert all(node["identity"] == document["nodes"][0]["identity"] for node in document["nodes"])


def test_info_dbc_for_several_nodes_holds_every_node_mapping(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    cantools = pytest.importorskip("cantools")  # the oracle: an independent DBC reader
    dbc = tmp_path / "bus.dbc"
    code, document, _ = run_json(capsys, "commission", "info", "--node-id", "5,6", "--dbc", str(dbc))
    assert code == 0 and [node["node_id"] for node in document["nodes"]] == [5, 6]
    db = cantools.database.load_file(str(dbc), strict=True)
    assert {node.name for node in db.nodes} == {"foilc_hil_master", "drive_5", "drive_6"}
    for node in (5, 6):  # each node's RPDO1 from the master and TPDO1 from the drive, at its own COB-ID
        assert db.get_message_by_frame_id(cob_id(FunctionCode.RPDO1, node)).senders == ["foilc_hil_master"]
        assert db.get_message_by_frame_id(cob_id(FunctionCode.TPDO1, node)).senders == [f"drive_{node}"]


@pytest.mark.parametrize("argv", [("params", "read"), ("identify",), ("info", "--dcf", "x.dcf")])
def test_one_node_actions_refuse_a_list(argv: tuple[str, ...], capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_cli(capsys, "commission", *argv, "--node-id", "1,2")
    assert code == 2 and "--node-id" in err + out and len(err.strip().splitlines()) == 1
