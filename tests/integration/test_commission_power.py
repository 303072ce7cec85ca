"""``commission enable|disable|fault-reset``: the 402 walk with its transitions, the heartbeat-fault path (NMT
reset communication before the fault reset), a stuck drive, and the exit codes."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import pytest
import yaml

from drivers.bus import open_bus
from drivers.cia301 import NMT_COB_ID, EmcyCode, FunctionCode, NmtCommand, NmtState, cob_id
from drivers.cia402 import Obj, State402
from drivers.config import BusConfig
from tests.support.commission_bus import emulated_bus, run_cli, run_json

pytestmark = pytest.mark.timeout(120)

NODE = 7


@contextmanager
def sniffer(channel: str) -> Iterator[list[can.Message]]:
    """Every frame sent on ``channel`` while the block runs (read afterwards)."""
    frames: list[can.Message] = []
    with open_bus(BusConfig(interface="inprocess", channel=channel)) as bus:
        yield frames
        while (message := bus.recv(timeout=0.05)) is not None:
            frames.append(message)


def test_enable_then_disable_reports_each_transition(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus([NODE]) as bus:
        code, document, _ = run_json(capsys, "commission", "enable", "--bus", bus.spec, "--node-id", str(NODE))
        assert code == 0
        assert bus.drives[NODE].state is State402.OPERATION_ENABLED
        states = [t["state"] for t in document["transitions"]]
        assert states == ["SWITCH_ON_DISABLED", "READY_TO_SWITCH_ON", "SWITCHED_ON", "OPERATION_ENABLED"]
        assert [t["controlword"] for t in document["transitions"]] == [None, "0x06", "0x07", "0x0F"]
        times = [t["t"] for t in document["transitions"]]
        assert times == sorted(times)
        assert document["final_state"] == "OPERATION_ENABLED"

        code, out, _ = run_cli(capsys, "commission", "disable", "--bus", bus.spec, "--node-id", str(NODE))
        assert code == 0
        assert bus.drives[NODE].state is State402.SWITCH_ON_DISABLED
        assert "OPERATION_ENABLED" in out and "-> SWITCH_ON_DISABLED" in out


def test_heartbeat_fault_resets_communication_before_the_fault_reset(capsys: pytest.CaptureFixture[str],
                                                                     tmp_path: Path) -> None:
    option = tmp_path / "fault_on_loss.yaml"
    option.write_text(yaml.safe_dump({"parameters": [
        {"name": "abort_connection_option", "index": int(Obj.ABORT_CONNECTION_OPTION), "value": 1},  # fault
    ]}))
    with emulated_bus([NODE]) as bus:
        drive = bus.drives[NODE]
        assert run_cli(capsys, "commission", "params", "write", str(option), "--bus", bus.spec,
                       "--node-id", str(NODE))[0] == 0
        assert run_cli(capsys, "commission", "enable", "--bus", bus.spec, "--node-id", str(NODE))[0] == 0
        drive.inject_fault("heartbeat-loss")
        assert drive.state is State402.FAULT and int(drive.node.read(Obj.ERROR_CODE)) == EmcyCode.HEARTBEAT_LOSS

        # enable refuses a faulted drive: exit 1, naming the fault and the way out
        code, _, err = run_cli(capsys, "commission", "enable", "--bus", bus.spec, "--node-id", str(NODE))
        assert code == 1 and "FAULT" in err and "0x8130" in err and "fault-reset" in err

        with sniffer(bus.channel) as frames:
            code, document, _ = run_json(capsys, "commission", "fault-reset", "--bus", bus.spec,
                                         "--node-id", str(NODE))
        assert code == 0
        assert drive.state is State402.SWITCH_ON_DISABLED and int(drive.node.read(Obj.ERROR_CODE)) == 0
        assert any("NMT reset communication" in note for note in document["notes"])
        assert [t["state"] for t in document["transitions"]] == ["FAULT", "SWITCH_ON_DISABLED"]
        # on the wire: NMT reset communication to the node, its boot-up, and only then the fault-reset command
        reset = next(i for i, m in enumerate(frames)
                     if m.arbitration_id == NMT_COB_ID and list(m.data) == [NmtCommand.RESET_COMMUNICATION, NODE])
        boot = next(i for i, m in enumerate(frames)
                    if m.arbitration_id == cob_id(FunctionCode.HEARTBEAT, NODE) and m.data[0] == NmtState.INITIALISING)
        sdo_rx = cob_id(FunctionCode.SDO_RX, NODE)
        fault_reset_write = next(i for i, m in enumerate(frames)
                                 if m.arbitration_id == sdo_rx and m.data[1:3] == b"\x40\x60" and m.data[4] == 0x80)
        assert reset < boot < fault_reset_write


def test_ordinary_fault_is_reset_without_touching_communication(capsys: pytest.CaptureFixture[str]) -> None:
    with emulated_bus([NODE]) as bus:
        drive = bus.drives[NODE]
        drive.inject_fault("over-current")
        with sniffer(bus.channel) as frames:
            code, document, _ = run_json(capsys, "commission", "fault-reset", "--bus", bus.spec,
                                         "--node-id", str(NODE))
        assert code == 0 and drive.state is State402.SWITCH_ON_DISABLED
        assert not any(m.arbitration_id == NMT_COB_ID for m in frames)
        assert not document["notes"]


def test_a_stuck_drive_names_the_state_and_exits_1(capsys: pytest.CaptureFixture[str],
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    with emulated_bus([NODE]) as bus:
        drive = bus.drives[NODE]
        monkeypatch.setattr(drive.application, "_apply_controlword", lambda controlword: None)  # deaf to it
        code, _, err = run_cli(capsys, "commission", "enable", "--bus", bus.spec, "--node-id", str(NODE),
                               "--state-timeout", "0.2")
        assert code == 1
        assert "stuck in SWITCH_ON_DISABLED" in err and "0x06 (SHUTDOWN)" in err
        assert len(err.strip().splitlines()) == 1


def test_fault_reset_of_a_healthy_drive_says_so(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli(capsys, "commission", "fault-reset")
    assert code == 0 and "no fault to reset" in out


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["enable", "--state-timeout", "-1"], "--state-timeout"),
        (["disable", "--node-id", "0"], "--node-id"),
        (["enable", "--bus", "nonsense"], "--bus"),
        (["enable", "--bus", "virtual:x", "--emulator", "embedded"], "not allowed with"),
        (["reboot"], "invalid choice"),
    ],
)
def test_bad_arguments_exit_2(argv: list[str], needle: str, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_cli(capsys, "commission", *argv)
    assert code == 2
    assert needle in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
