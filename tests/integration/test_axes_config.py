"""``axes:``: several axes in one document; the single-axis form stays valid and means one axis.

Each axis's config (:func:`foilc_hil.config.axis_configs`) is the whole document with the axis's sections in place of
the top-level ones; bad entries exit 2 naming the field (``axes.K.node_id``), before anything is designed or sent.
The bus-load check counts every axis's PDOs and heartbeat (figures counted by hand, as in test_run_bus_load).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from foilc_hil.cli import main
from foilc_hil.commands.run import check_bus_load
from foilc_hil.config import axis_configs, load_config
from tests.integration.test_run_bus_load import HEARTBEAT_BITS, PDO6_BITS, SYNC_BITS

ROOT = Path(__file__).resolve().parents[2]
SCARA = ROOT / "configs" / "scara_4axis.yaml"

TWO_AXES = """
plant: {model: first_order, a: -2.0, b: 2.0}
drive: {velocity_limit: 500.0}
axes:
  - node_id: 3
  - node_id: 5
    plant: {model: first_order, a: -7.0, b: 3.5}
    drive: {velocity_limit: 250.0, mode: cst}
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "axes.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_the_single_axis_form_is_one_axis(tmp_path: Path) -> None:
    config = load_config(_write(tmp_path, "plant: {model: first_order, a: -2.0, b: 2.0}\ndrive: {node_id: 9}\n"))
    assert config.axes == ()
    assert axis_configs(config) == (config,)


def test_each_axis_takes_its_own_sections_and_inherits_the_rest(tmp_path: Path) -> None:
    config = load_config(_write(tmp_path, TWO_AXES))
    first, second = axis_configs(config)
    assert (first.drive.node_id, second.drive.node_id) == (3, 5)
    assert first.plant == config.plant and first.drive.velocity_limit == 500.0  # inherited whole
    assert second.plant.a == [[-7.0]] and second.plant.b == [[3.5]]
    # a section given replaces the top-level one whole: velocity_scale is the section's default, mode its own
    assert (second.drive.velocity_limit, second.drive.mode) == (250.0, "cst")
    assert first.axes == () and second.axes == ()  # each is a single-axis document again
    assert first.sample_time == second.sample_time == config.sample_time  # shared: one SYNC clock


def test_the_shipped_scara_config_has_four_different_pmsm_axes() -> None:
    axes = axis_configs(load_config(SCARA))
    assert [axis.drive.node_id for axis in axes] == [1, 2, 3, 4]
    assert all(axis.plant.model == "pmsm" for axis in axes)
    assert len({axis.plant.pmsm.inertia for axis in axes}) == 4
    assert len({axis.plant.disturbance.amplitude for axis in axes}) == 4


@pytest.mark.parametrize(
    ("axes", "expected"),
    [
        ("[{node_id: 1}, {node_id: 2}, {node_id: 0}]", "axes.2.node_id: Input should be greater than or equal to 1"),
        ("[{node_id: 1}, {node_id: 2}, {node_id: 1}]", "axes.2.node_id: 1 is already the node id of axes.0"),
        ("[{node_id: 1}, {plant: {}}]", "axes.1.node_id: is required"),
        ("[{node_id: 1, plantt: {}}]", "axes.0.plantt: unknown key (did you mean 'plant'?)"),
        ("[{node_id: 1, drive: {node_id: 2}}]", "axes.0: drive.node_id 2 differs from node_id 1"),
        ("[{node_id: 1, drive: {master_node_id: 100}}, {node_id: 2}]", "drive.master_node_id must be the same"),
    ],
)
def test_bad_axis_entries_exit_2_naming_the_field(tmp_path: Path, capsys: pytest.CaptureFixture[str], axes: str,
                                                  expected: str, monkeypatch: pytest.MonkeyPatch) -> None:
    from foilc_hil.design import pipeline

    monkeypatch.setattr(pipeline, "build_design", _refuse)  # where the rig makes a design
    config = _write(tmp_path, f"axes: {axes}\n")
    code = main(["run", "--config", str(config), "--out", str(tmp_path / "x.mcap"), "--json"])
    captured = capsys.readouterr()
    assert code == 2
    message = json.loads(captured.out)["error"]["message"]
    assert expected in message and "Traceback" not in captured.err


def _refuse(*args: Any, **kwargs: Any) -> None:
    raise AssertionError("a bad config reached the design")


def _four_axis_bits(period: float) -> float:
    """SYNC, three 6-byte PDOs and a heartbeat (every 0.1 s) per axis, the master's heartbeat (0.125 s) once."""
    return SYNC_BITS + 4 * 3 * PDO6_BITS + HEARTBEAT_BITS * (4 * period / 0.1 + period / 0.125)


def test_the_bus_load_counts_every_axis_and_refuses_four_axes_at_1_khz(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    config = load_config(SCARA)
    load = check_bus_load(config, config.bus)
    assert load.bits_per_cycle == pytest.approx(_four_axis_bits(config.sample_time))
    assert load.to_json()["load"] < 0.7
    names = [frame["name"] for frame in load.to_json()["frames"]]
    assert names.count("SYNC") == 1 and sum("master heartbeat" in name for name in names) == 1
    assert {f"node {node} TPDO2" for node in (1, 2, 3, 4)} <= set(names)
    from foilc_hil.design import pipeline

    monkeypatch.setattr(pipeline, "build_design", _refuse)  # where the rig makes a design
    fast = tmp_path / "fast.yaml"
    fast.write_text(SCARA.read_text(encoding="utf-8").replace("sample_time: 0.0025", "sample_time: 0.001"),
                    encoding="utf-8")
    code = main(["run", "--config", str(fast), "--out", str(tmp_path / "x.mcap"), "--json"])
    message = json.loads(capsys.readouterr().out)["error"]["message"]
    assert code == 2 and "bus.load_limit" in message
    assert f"bus load {_four_axis_bits(0.001) / 1000:.1%} of 1000 kbit/s at a 1 ms period" in message  # 143.8 %
