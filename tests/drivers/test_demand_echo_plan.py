"""``drive.demand_echo`` in the master's PDO plan and in the bus load (issue 28): the mode's demand object is mapped
when asked and the EDS has it, refused naming the key when it does not, and the plan is today's when not asked."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.cia402 import Obj, OperationMode
from drivers.errors import ConfigError
from drivers.master.plan import PdoPlan, pdo_plan
from drivers.od import load_od
from foilc_hil.cli import main
from foilc_hil.commands.run import check_bus_load
from foilc_hil.config import load_config

NODE = 5
REPO = Path(__file__).resolve().parents[2]


def _tpdos(plan: PdoPlan) -> list[tuple[int, list[int]]]:
    return [(layout.cob_id, [v.index for v in layout.variables]) for layout in plan.tpdos]


#: the plan of today (before the demand echo), the same in every mode on the shipped EDS
TODAY = [(0x180 + NODE, [Obj.STATUSWORD, Obj.VELOCITY_ACTUAL_VALUE]),
         (0x280 + NODE, [Obj.TORQUE_ACTUAL_VALUE, Obj.POSITION_ACTUAL_VALUE])]


@pytest.mark.parametrize("mode", list(OperationMode))
def test_off_the_plan_is_today_s(mode: OperationMode) -> None:
    od = load_od(None, NODE)
    assert _tpdos(pdo_plan(mode, NODE, od)) == TODAY
    assert pdo_plan(mode, NODE, od, demand_echo=False) == pdo_plan(mode, NODE, od)


@pytest.mark.parametrize("mode", [OperationMode.CYCLIC_SYNC_VELOCITY, OperationMode.PROFILE_VELOCITY])
def test_velocity_demand_gets_a_tpdo_of_its_own(mode: OperationMode) -> None:
    plan = pdo_plan(mode, NODE, load_od(None, NODE), demand_echo=True)
    # 0x606B (32 bits) fits in neither 48-bit TPDO: TPDO3, synchronous like the others
    assert _tpdos(plan) == [*TODAY, (0x380 + NODE, [Obj.VELOCITY_DEMAND_VALUE])]
    (demand,) = plan.tpdos[2].variables
    assert (demand.bits, demand.signed) == (32, True)
    assert plan.rpdos == pdo_plan(mode, NODE, load_od(None, NODE)).rpdos


def test_torque_demand_fits_into_tpdo1() -> None:
    plan = pdo_plan(OperationMode.CYCLIC_SYNC_TORQUE, NODE, load_od(None, NODE), demand_echo=True)
    assert _tpdos(plan) == [(0x180 + NODE, [Obj.STATUSWORD, Obj.VELOCITY_ACTUAL_VALUE, Obj.TORQUE_DEMAND]),
                            TODAY[1]]
    assert (plan.tpdos[0].variables[2].bits, plan.tpdos[0].variables[2].signed) == (16, True)


@pytest.mark.parametrize(("mode", "index"), [(OperationMode.CYCLIC_SYNC_VELOCITY, Obj.VELOCITY_DEMAND_VALUE),
                                             (OperationMode.CYCLIC_SYNC_TORQUE, Obj.TORQUE_DEMAND)])
def test_refused_naming_the_key_and_the_object_when_the_eds_lacks_it(mode: OperationMode, index: Obj) -> None:
    od = load_od(None, NODE)
    del od[index]
    with pytest.raises(ConfigError) as caught:
        pdo_plan(mode, NODE, od, demand_echo=True)
    assert caught.value.key == "drive.demand_echo"
    assert f"0x{int(index):04X}" in str(caught.value)
    assert _tpdos(pdo_plan(mode, NODE, od)) == TODAY  # not asked: the drive is fine


def test_refused_when_no_tpdo_is_left() -> None:
    od = load_od(None, NODE)
    for n in (2, 3):  # TPDO1 and TPDO2 only, both full
        del od[Obj.TPDO_COMMUNICATION + n]
    with pytest.raises(ConfigError, match=r"drive\.demand_echo: .*0x606B.*no"):
        pdo_plan(OperationMode.CYCLIC_SYNC_VELOCITY, NODE, od, demand_echo=True)


def test_the_bus_load_counts_the_extra_frame_and_the_scara_still_fits_without_it() -> None:
    scara = load_config(str(REPO / "configs" / "scara_4axis.yaml"))
    off = check_bus_load(scara, scara.bus)  # raises when it does not fit: it must with the key off
    assert off.fits
    one = load_config(None, {"sample_time": 0.001})
    echo = load_config(None, {"sample_time": 0.001, "drive.demand_echo": True})
    names_off = [frame["name"] for frame in check_bus_load(one, one.bus).to_json()["frames"]]
    loads = check_bus_load(echo, echo.bus)
    assert [frame["name"] for frame in loads.to_json()["frames"]] == [*names_off[:4], "TPDO3", *names_off[4:]]
    assert loads.bits_per_cycle > check_bus_load(one, one.bus).bits_per_cycle


@pytest.mark.parametrize("value", ["3", "'yes'", "1", "[true]"])
def test_a_value_that_is_not_a_boolean_exits_2_on_one_line(value: str, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "echo.yaml"
    path.write_text(f"drive:\n  demand_echo: {value}\n", encoding="utf-8")
    code = main(["run", "--config", str(path), "--emulator", "embedded", "--out", str(tmp_path / "x.mcap")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "drive.demand_echo" in err and "Traceback" not in err
    assert not (tmp_path / "x.mcap").exists()
