"""``foilc-hil run`` checks its bus before the design (which may take minutes): an unknown interface is exit 2,
a SocketCAN bus that does not open is exit 1 with the ``ip link`` hint, both before any synthesis."""

from __future__ import annotations

import json
import uuid
from pathlib import Path
from typing import Any

import pytest

from drivers.config import BusConfig
from foilc_hil.cli import main
from foilc_hil.commands.run import check_bus


@pytest.fixture
def no_design(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any design step fails the test: the bus check must come first."""

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the design started before the bus was checked")

    from foilc_hil.design import pipeline

    monkeypatch.setattr(pipeline, "build_design", refuse)  # where the rig makes a design


@pytest.mark.usefixtures("no_design")
def test_an_unknown_interface_is_exit_2_before_the_design(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code = main(["run", "--bus", "canbus9000:x", "--out", str(tmp_path / "x.mcap"), "--json"])
    captured = capsys.readouterr()
    assert code == 2
    message = json.loads(captured.out)["error"]["message"]
    assert message.startswith("--bus: unknown interface 'canbus9000'") and "socketcan" in message


@pytest.mark.usefixtures("no_design")
def test_socketcan_that_does_not_open_is_exit_1_with_the_hint(capsys: pytest.CaptureFixture[str],
                                                              tmp_path: Path) -> None:
    # no such interface here (or no SocketCAN at all): either way the open fails at once
    channel = f"nocan{uuid.uuid4().hex[:6]}"
    code = main(["run", "--bus", f"socketcan:{channel}", "--out", str(tmp_path / "x.mcap"), "--json"])
    captured = capsys.readouterr()
    assert code == 1
    message = json.loads(captured.out)["error"]["message"]
    assert f"cannot open CAN bus socketcan:{channel}" in message and "ip link" in message
    assert "Traceback" not in captured.err


def test_a_bus_that_opens_passes_and_is_closed_again() -> None:
    check_bus(BusConfig(interface="virtual", channel=f"check-{uuid.uuid4()}"))  # the leak guard sees no open bus
    check_bus(BusConfig(interface="embedded"))  # the emulator opens its own bus later
