"""Plant physics (shared by offline simulation and the emulator) and a virtual CiA 402 servo drive.

The public name is :class:`EmbeddedEmulator` (``docs/api.md``): emulated drives on an in-process CAN channel, for
commissioning scripts without hardware; it is imported on first use (PEP 562). Every other module is internal.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from plant_emulator.embedded import EmbeddedEmulator

__all__ = ["EmbeddedEmulator"]


def __getattr__(name: str) -> Any:
    """A public name, imported from its module on first use and kept (PEP 562)."""
    if name != "EmbeddedEmulator":
        raise AttributeError(f"module 'plant_emulator' has no attribute {name!r}")
    value = importlib.import_module("plant_emulator.embedded").EmbeddedEmulator
    globals()[name] = value
    return value
