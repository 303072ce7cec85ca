"""The ``plant:`` section: the PMSM sub-section's defaults and validation errors naming their keys."""

from __future__ import annotations

from typing import Any

import pytest

from foilc_hil.config import load_config
from foilc_hil.errors import ConfigError
from plant_emulator.config import PlantConfig, PmsmConfig


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        ({"plant.pmsm.inertia": 0}, "plant.pmsm.inertia: Input should be greater than 0"),
        ({"plant.pmsm.viscous": -1}, "plant.pmsm.viscous: Input should be greater than or equal to 0"),
        ({"plant.pmsm.resolver_bits": 2}, "plant.pmsm.resolver_bits: Input should be greater than or equal to 4"),
        ({"plant.pmsm.input_kind": "position"}, "plant.pmsm.input_kind: Input should be 'velocity' or 'torque'"),
        ({"plant.pmsm.spread.inertia": 1.5}, "plant.pmsm.spread.inertia: Input should be less than 1"),
        ({"plant.pmsm.torque_limit": 1.0}, "plant.pmsm: torque_limit must be at least rated_torque"),
        ({"plant.pmsm.speed_limit": 100.0}, "plant.pmsm: speed_limit must be at least rated_speed"),
        ({"plant.pmsm.inertai": 1e-3}, "plant.pmsm.inertai: unknown key (did you mean 'inertia'?)"),
        ({"plant.pmsm.internal_step": 0.01}, "plant.pmsm.internal_step: Input should be less than or equal to 0.001"),
        ({"plant.disturbance.kind": "ramp"}, "plant.disturbance.kind: Input should be"),
    ],
)
def test_bad_pmsm_values_name_their_key(overrides: dict[str, Any], expected: str) -> None:
    with pytest.raises(ConfigError) as caught:
        load_config(None, overrides)
    assert str(caught.value).startswith(expected), str(caught.value)


def test_pmsm_section_loads_from_yaml_with_defaults_filled(tmp_path: Any) -> None:
    path = tmp_path / "plant.yaml"
    path.write_text(
        "plant:\n  model: pmsm\n  pmsm:\n    inertia: 8.0e-4\n    input_kind: torque\n    spread: {viscous: 0.2}\n",
        encoding="utf-8",
    )
    plant = load_config(path).plant
    assert plant.model == "pmsm"
    assert plant.pmsm.inertia == 8.0e-4
    assert plant.pmsm.input_kind == "torque"
    assert plant.pmsm.spread.viscous == 0.2
    assert plant.pmsm.spread.inertia == 0.0
    assert plant.pmsm.rated_torque == PmsmConfig().rated_torque


def test_default_pmsm_is_a_400_w_class_axis() -> None:
    pmsm = PlantConfig().pmsm
    assert 1e-4 <= pmsm.inertia <= 1e-3
    rated_power = pmsm.rated_torque * pmsm.rated_speed * 2 * 3.141592653589793 / 60
    assert 300 <= rated_power <= 500
    assert pmsm.torque_limit >= pmsm.rated_torque and pmsm.speed_limit >= pmsm.rated_speed


def test_existing_plant_keys_are_kept() -> None:
    fields = set(PlantConfig.model_fields)
    assert {
        "model",
        "a",
        "b",
        "c",
        "num",
        "den",
        "delay",
        "x0",
        "uncertainty",
        "variation",
        "disturbance",
        "saturation",
        "output_noise",
        "seed",
        "pmsm",
    } <= fields
