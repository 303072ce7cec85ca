"""``foilc-hil run`` computes the worst-case bus load before anything is designed or sent, and refuses a schedule
over ``bus.load_limit`` (exit 2, one line with the figures).

The expected figures are counted here by hand from ISO 11898-1 (a standard-ID data frame with ``s`` bytes: 34 + 8s
stuffable bits, at most ``(34 + 8s - 1) // 4`` stuff bits, 13 unstuffed bits incl. the interframe space), for the
master's default CSV mapping: RPDO1 = controlword (2) + target velocity (4), TPDO1 = statusword (2) + velocity (4),
TPDO2 = torque (2) + position (4), a SYNC with no data, the drive's heartbeat every 0.1 s and the master's every
0.5 s / 4.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from foilc_hil.cli import main
from foilc_hil.commands.run import check_bus_load
from foilc_hil.config import load_config
from foilc_hil.errors import ConfigError

SYNC_BITS = 34 + 13 + 33 // 4  # 55
PDO6_BITS = 82 + 13 + 81 // 4  # 115: a 6-byte PDO
HEARTBEAT_BITS = 42 + 13 + 41 // 4  # 65


def _expected_bits(period: float) -> float:
    return SYNC_BITS + 3 * PDO6_BITS + HEARTBEAT_BITS * (period / 0.1 + period / 0.125)


def _config(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bench.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture
def no_design(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any design step fails the test: the bus-load check must come first."""

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the design started before the bus load was checked")

    from foilc_hil.design import pipeline

    monkeypatch.setattr(pipeline, "build_design", refuse)  # where the rig makes a design


@pytest.mark.usefixtures("no_design")
def test_a_slow_bus_is_refused_with_the_figures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = _config(tmp_path, "sample_time: 0.01\nbus: {bitrate: 50000}\n")
    code = main(["run", "--config", str(config), "--emulator", "embedded", "--out", str(tmp_path / "x.mcap"),
                 "--json"])
    captured = capsys.readouterr()
    assert code == 2
    message = json.loads(captured.out)["error"]["message"]
    load = _expected_bits(0.01) / (50_000 * 0.01)  # 82.3 %
    assert "bus.load_limit" in message and f"bus load {load:.1%} of 50 kbit/s at a 10 ms period" in message
    assert "(limit 70%)" in message and "Traceback" not in captured.err


@pytest.mark.usefixtures("no_design")
def test_a_short_period_is_refused_in_text_mode_on_one_line(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    config = _config(tmp_path, "sample_time: 0.0005\n")  # 1 Mbit/s by default: about 80 % at 0.5 ms
    code = main(["run", "--config", str(config), "--emulator", "embedded", "--out", str(tmp_path / "x.mcap")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert f"bus load {_expected_bits(0.0005) / 500:.1%} of 1000 kbit/s at a 0.5 ms period" in err


def test_the_default_schedule_fits_and_its_figures_are_counted_by_hand(tmp_path: Path) -> None:
    config = load_config(str(_config(tmp_path, "sample_time: 0.001\n")))
    load = check_bus_load(config, config.bus)
    assert load.bits_per_cycle == pytest.approx(_expected_bits(0.001))
    assert load.to_json()["load"] == pytest.approx(_expected_bits(0.001) / 1000)  # 40 % at 1 kHz, 1 Mbit/s
    assert [frame["name"] for frame in load.to_json()["frames"]] == [
        "SYNC", "RPDO1", "TPDO1", "TPDO2", "heartbeat", "master heartbeat"]


def test_the_limit_is_the_config_s(tmp_path: Path) -> None:
    config = load_config(str(_config(tmp_path, "sample_time: 0.001\nbus: {load_limit: 0.3}\n")))
    with pytest.raises(ConfigError, match=r"bus\.load_limit.*limit 30%"):
        check_bus_load(config, config.bus)


def test_four_axes_at_1_khz_do_not_fit_on_1_mbit() -> None:
    from drivers.busload import CyclicFrame, drive_schedule, schedule_load
    from drivers.cia402 import OperationMode
    from drivers.cia402_master import pdo_plan
    from drivers.od import load_od

    frames = [CyclicFrame("SYNC", 0)]
    for node in (1, 2, 3, 4):  # one master heartbeat on the bus, each drive its own
        plan = pdo_plan(OperationMode.CYCLIC_SYNC_VELOCITY, node, load_od(None, node))
        frames += drive_schedule(plan, period=0.001, drive_heartbeat=0.1, master_heartbeat=0.125 if node == 1 else 0,
                                 name=f"node {node} ")
    load = schedule_load(frames, bitrate=1_000_000, period=0.001)
    by_hand = SYNC_BITS + 4 * 3 * PDO6_BITS + HEARTBEAT_BITS * (4 * 0.001 / 0.1 + 0.001 / 0.125)  # 1438.12
    assert load.bits_per_cycle == pytest.approx(by_hand)
    assert not load.fits and load.min_period == pytest.approx(by_hand / 700_000)
    with pytest.raises(ConfigError, match=r"bus load 143\.8% of 1000 kbit/s at a 1 ms period"):
        load.check()
