"""Wire codes are enums without aliases: an alias silently hides a member (as EMCY once hid behind SYNC's 0x080)."""

from __future__ import annotations

import enum
import importlib
import pkgutil

import pytest

import drivers

ALLOWED_ALIASES = {"drivers.cia402.Command402": {"DISABLE_OPERATION"}}  # CiA 402 defines 0x07 twice


def wire_enums() -> list[type[enum.IntEnum]]:
    found: list[type[enum.IntEnum]] = []
    for info in pkgutil.iter_modules(drivers.__path__, "drivers."):
        module = importlib.import_module(info.name)
        for value in vars(module).values():
            if isinstance(value, type) and issubclass(value, enum.IntEnum) and value.__module__ == module.__name__:
                found.append(value)
    return found


def aliases(cls: type[enum.Enum]) -> set[str]:
    return {name for name, member in cls.__members__.items() if member.name != name}


@pytest.mark.parametrize("cls", wire_enums(), ids=lambda cls: cls.__qualname__)
def test_wire_enum_has_no_alias(cls: type[enum.Enum]) -> None:
    assert aliases(cls) == ALLOWED_ALIASES.get(f"{cls.__module__}.{cls.__qualname__}", set())


def test_the_check_can_fail() -> None:
    class Planted(enum.IntEnum):
        SYNC = 0x080
        EMCY = 0x080

    assert aliases(Planted) == {"EMCY"}
    assert len(wire_enums()) >= 10
