"""``python -m plant_emulator``: the same as the ``plant-emulator`` console script."""

from __future__ import annotations

from plant_emulator.cli import run

if __name__ == "__main__":
    run()
