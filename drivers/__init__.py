"""The CAN side of a servo drive: CiA 301/402 protocol definitions, object dictionary, PDO codecs and the
CiA 402 master (:class:`drivers.drive.Drive`).

The names below are the package's public API for commissioning scripts (``docs/api.md``); every other module and
name is internal. They are imported on first use (PEP 562), so ``import drivers`` (and ``foilc_hil.errors``, which
re-exports ``drivers.errors``) loads neither python-can nor canopen.

>>> import drivers
>>> with drivers.open_bus(bus_config) as bus:                                  # doctest: +SKIP
...     network = drivers.DriveNetwork(bus)
...     print(network.scan(range(1, 5), listen=0.5).nodes)
...     drive = drivers.Cia402Drive.on_network(network, drive_config, sample_time=0.001)
...     drive.connect()
...     print(drive.read_object("Statusword"))
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivers.bus import open_bus
    from drivers.cia402 import OperationMode, State402
    from drivers.cia402_master import Cia402Drive
    from drivers.config import BusConfig, DriveConfig
    from drivers.drive import DeviceInfo, Feedback, StopReport
    from drivers.errors import ConfigError, DriveError, InputError, ProductError, SdoError
    from drivers.network import DriveNetwork
    from drivers.scan import NodeReport, ScanResult, scan_bus

__all__ = [
    "BusConfig",
    "Cia402Drive",
    "ConfigError",
    "DeviceInfo",
    "DriveConfig",
    "DriveError",
    "DriveNetwork",
    "Feedback",
    "InputError",
    "NodeReport",
    "OperationMode",
    "ProductError",
    "ScanResult",
    "SdoError",
    "State402",
    "StopReport",
    "open_bus",
    "scan_bus",
]

#: where each public name is defined
_SOURCES = {
    "open_bus": "drivers.bus",
    "OperationMode": "drivers.cia402",
    "State402": "drivers.cia402",
    "Cia402Drive": "drivers.cia402_master",
    "BusConfig": "drivers.config",
    "DriveConfig": "drivers.config",
    "DeviceInfo": "drivers.drive",
    "Feedback": "drivers.drive",
    "StopReport": "drivers.drive",
    "ConfigError": "drivers.errors",
    "DriveError": "drivers.errors",
    "InputError": "drivers.errors",
    "ProductError": "drivers.errors",
    "SdoError": "drivers.errors",
    "DriveNetwork": "drivers.network",
    "NodeReport": "drivers.scan",
    "ScanResult": "drivers.scan",
    "scan_bus": "drivers.scan",
}


def __getattr__(name: str) -> Any:
    """A public name, imported from its module on first use and kept (PEP 562)."""
    source = _SOURCES.get(name)
    if source is None:
        raise AttributeError(f"module 'drivers' has no attribute {name!r}")
    value = getattr(importlib.import_module(source), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
