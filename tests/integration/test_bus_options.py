"""python-can's bus conventions: ``-i/--interface``, ``-c/--channel``, ``-b/--bitrate`` beside ``--bus``, and
python-can's environment (``CAN_INTERFACE``, ``CAN_CHANNEL``, ``CAN_BITRATE``) and config file (``can.rc``) when the
command line names no bus. The precedence of :func:`drivers.bus.resolve_bus` is checked case by case with env vars
(monkeypatch) and a temporary can.rc; the CLI cases end before any bus opens (unknown interfaces, a real bus refused
by ``replay``) or on python-can's in-process ``virtual`` bus.
"""

from __future__ import annotations

import json
import re
import uuid
from pathlib import Path

import can
import pytest

from drivers.bus import BusOptions, resolve_bus
from drivers.config import BusConfig
from foilc_hil.cli import main
from foilc_hil.errors import InputError

DEFAULT = BusConfig()  # the config without a bus: block (the embedded emulator)


@pytest.fixture(autouse=True)
def isolated(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """No CAN_* variables and a can.rc of our own (absent until a test writes it)."""
    for name in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    rc = tmp_path / "canrc"
    monkeypatch.setattr(can.util, "CONFIG_FILES", [str(rc)])
    return rc


def _env(monkeypatch: pytest.MonkeyPatch, **values: str) -> None:
    for key, value in values.items():
        monkeypatch.setenv(f"CAN_{key.upper()}", value)


def test_without_any_bus_the_config_default_is_kept() -> None:
    assert resolve_bus(BusOptions(), DEFAULT) == DEFAULT


def test_the_environment_names_the_bus_when_nothing_else_does(monkeypatch: pytest.MonkeyPatch) -> None:
    _env(monkeypatch, interface="virtual", channel="envchan", bitrate="250000")
    assert resolve_bus(BusOptions(), DEFAULT) == BusConfig(interface="virtual", channel="envchan", bitrate=250000)


def test_the_environment_wins_over_can_rc(monkeypatch: pytest.MonkeyPatch, isolated: Path) -> None:
    isolated.write_text("[default]\ninterface = udp_multicast\nchannel = 239.74.163.9\nbitrate = 125000\n")
    assert resolve_bus(BusOptions(), DEFAULT) == BusConfig(interface="udp_multicast", channel="239.74.163.9",
                                                           bitrate=125000)
    _env(monkeypatch, interface="virtual")  # interface from the environment, the rest from the file
    assert resolve_bus(BusOptions(), DEFAULT) == BusConfig(interface="virtual", channel="239.74.163.9",
                                                           bitrate=125000)


def test_the_config_files_bus_block_wins_over_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    _env(monkeypatch, interface="virtual", channel="envchan")
    configured = BusConfig.model_validate({"interface": "udp_multicast", "channel": "239.74.163.2"})
    assert resolve_bus(BusOptions(), configured) == configured
    # a bus: block that sets only the bitrate names no bus: the environment does, with the block's bitrate
    assert resolve_bus(BusOptions(), BusConfig.model_validate({"bitrate": 500000})) == BusConfig(
        interface="virtual", channel="envchan", bitrate=500000)


def test_the_command_line_wins_and_completes_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    _env(monkeypatch, interface="virtual", channel="envchan", bitrate="250000")
    configured = BusConfig.model_validate({"interface": "udp_multicast", "channel": "239.74.163.2"})
    assert resolve_bus(BusOptions(interface="socketcan", channel="can1"), configured) == BusConfig(
        interface="socketcan", channel="can1", bitrate=250000)
    assert resolve_bus(BusOptions(channel="other"), configured) == BusConfig(
        interface="virtual", channel="other", bitrate=250000)
    assert resolve_bus(BusOptions(spec="socketcan:can2", bitrate=1000000), configured) == BusConfig(
        interface="socketcan", channel="can2", bitrate=1000000)
    assert resolve_bus(BusOptions(emulator="embedded"), configured).interface == "embedded"
    assert resolve_bus(BusOptions(bitrate=500000), configured) == configured.model_copy(update={"bitrate": 500000})


@pytest.mark.parametrize(("options", "named"), [
    (BusOptions(spec="virtual:a", interface="virtual"), "-i/--interface"),
    (BusOptions(interface="virtual"), "-c/--channel"),
    (BusOptions(channel="can0"), "-i/--interface"),
    (BusOptions(emulator="embedded", channel="can0"), "--emulator"),
])
def test_incomplete_or_conflicting_options_name_the_option(options: BusOptions, named: str) -> None:
    with pytest.raises(InputError) as caught:
        resolve_bus(options, DEFAULT)
    assert str(caught.value).startswith(f"{named}:")


def test_a_bad_bitrate_names_where_it_came_from(monkeypatch: pytest.MonkeyPatch) -> None:
    _env(monkeypatch, interface="virtual", channel="c", bitrate="fast")
    with pytest.raises(InputError, match=r"^CAN_BITRATE: 'fast'"):
        resolve_bus(BusOptions(), DEFAULT)
    with pytest.raises(InputError, match=r"^-b/--bitrate: must be > 0"):
        BusOptions(bitrate=0)


def test_run_honours_can_interface_before_the_design(monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the design started before the bus was checked")

    from foilc_hil.design import pipeline

    monkeypatch.setattr(pipeline, "build_design", refuse)  # where the rig makes a design
    _env(monkeypatch, interface="canbus9000", channel="x")
    assert main(["run", "--out", str(tmp_path / "x.mcap"), "--json"]) == 2
    assert "unknown interface 'canbus9000'" in json.loads(capsys.readouterr().out)["error"]["message"]
    assert main(["run", "-i", "canbus9001", "-c", "y", "--out", str(tmp_path / "x.mcap"), "--json"]) == 2
    assert "unknown interface 'canbus9001'" in json.loads(capsys.readouterr().out)["error"]["message"]


def test_commission_takes_i_and_c(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["commission", "scan", "-i", "canbus9002", "-c", "x", "--json"]) == 2
    assert "canbus9002" in json.loads(capsys.readouterr().out)["error"]["message"]


def test_replay_onto_i_and_c(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from foilc_hil.io.mcap_log import McapLogWriter

    log = tmp_path / "frames.mcap"
    with McapLogWriter(log, config_yaml=None) as writer:
        for n in range(3):
            writer.log_frame(can.Message(arbitration_id=0x201, data=bytes([n]), is_extended_id=False), "tx")
    assert main(["replay", str(log), "-i", "socketcan", "-c", "can0", "--json"]) == 2  # refused before opening
    message = json.loads(capsys.readouterr().out)["error"]["message"]
    assert message.startswith("-i/--interface: socketcan:can0 is a real")
    channel = f"replay-{uuid.uuid4()}"
    assert main(["replay", str(log), "-i", "virtual", "-c", channel, "--rate", "1000", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frames_sent"] == 3


def test_commission_scan_names_the_embedded_bus_without_its_internal_channel(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["commission", "scan", "--timeout", "0.3", "--json"]) == 0
    bus = json.loads(capsys.readouterr().out)["bus"]
    assert bus.startswith("embedded (1 emulated drive(s)")
    assert re.search(r"[0-9a-f]{8}-[0-9a-f]{4}", bus) is None  # no per-process UUID a user cannot join
