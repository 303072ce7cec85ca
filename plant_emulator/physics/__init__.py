"""The one physics code path shared by offline simulation, the virtual drive and identification.

``build_plant(config.plant)`` returns a :class:`~plant_emulator.physics.base.Plant`:

- ``model: first_order`` -- the paper's model (48), ``x' = (a + Da(t)) x + (b + Db(t)) u + d(t)``, ``y = c x``
  (:mod:`plant_emulator.physics.first_order`);
- ``model: pmsm`` -- a PMSM servo axis with its drive's current and velocity loops
  (:mod:`plant_emulator.physics.pmsm`).
"""

from __future__ import annotations

from plant_emulator.config import PlantConfig
from plant_emulator.physics.base import Plant

__all__ = ["Plant", "build_plant"]


def build_plant(plant: PlantConfig, *, seed: int | None = None) -> Plant:
    """Build the plant ``plant`` describes, seeded by ``seed`` (default ``plant.seed``).

    Raises
    ------
    foilc_hil.errors.ConfigError
        If the section is inconsistent (the message names the key).
    """
    run_seed = plant.seed if seed is None else int(seed)
    if plant.model == "pmsm":
        from plant_emulator.physics.pmsm import PmsmPlant

        return PmsmPlant(plant, seed=run_seed)
    from plant_emulator.physics.first_order import FirstOrderPlant

    return FirstOrderPlant(plant, seed=run_seed)
