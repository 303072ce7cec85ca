"""The one error tree across the packages: ``drivers.errors`` defines the root and the drive side's errors (so
``drivers`` and ``plant_emulator`` stand alone), ``foilc_hil.errors`` re-exports them as the same classes and adds
the control stack's; ``except FoilcHilError`` catches all of them, each with the exit code of the interface."""

from __future__ import annotations

import inspect

import pytest

import drivers.errors
import foilc_hil.errors as errors
from drivers.errors import ExitCode

DRIVER_ERRORS = sorted((cls for cls in vars(drivers.errors).values()
                        if inspect.isclass(cls) and issubclass(cls, BaseException)
                        and cls.__module__ == drivers.errors.__name__), key=lambda cls: cls.__name__)

#: docs/interface.md: 1 runtime failure, 2 usage or configuration error, 3 infeasible design, 130 interrupted
EXIT_CODES = {
    "ConfigError": ExitCode.USAGE, "EdsError": ExitCode.USAGE, "InputError": ExitCode.USAGE,
    "ProtocolError": ExitCode.USAGE, "LogFormatError": ExitCode.USAGE,
    "DriveError": ExitCode.RUNTIME_FAILURE, "SdoError": ExitCode.RUNTIME_FAILURE,
    "HeartbeatLostError": ExitCode.RUNTIME_FAILURE, "BadFrameError": ExitCode.RUNTIME_FAILURE,
    "EmergencyError": ExitCode.RUNTIME_FAILURE, "DriveNotStoppedError": ExitCode.RUNTIME_FAILURE,
    "LmiInfeasibleError": ExitCode.INFEASIBLE, "RunInterruptedError": ExitCode.INTERRUPTED,
}
FIELDS: dict[type[BaseException], tuple[object, ...]] = {
    drivers.errors.EmergencyError: (0x2310, 0x03, "over-current"),
    drivers.errors.SdoError: (0x6060, 0, 0x06090030, "value range exceeded"),
}


def test_the_drive_side_defines_the_errors_it_raises() -> None:
    names = {cls.__name__ for cls in DRIVER_ERRORS}
    assert {"ProductError", "DriveError", "SdoError", "EmergencyError", "ConfigError", "ProtocolError"} <= names


@pytest.mark.parametrize("cls", DRIVER_ERRORS, ids=lambda cls: cls.__name__)
def test_foilc_hil_re_exports_the_same_class(cls: type[BaseException]) -> None:
    alias = "FoilcHilError" if cls is drivers.errors.ProductError else cls.__name__
    assert getattr(errors, alias) is cls


@pytest.mark.parametrize("cls", DRIVER_ERRORS, ids=lambda cls: cls.__name__)
def test_except_foilc_hil_error_catches_every_driver_error(cls: type[BaseException]) -> None:
    error = cls(*FIELDS.get(cls, ("the message",)))
    try:
        raise error
    except errors.FoilcHilError as caught:
        assert caught is error
    except BaseException:  # the case under test: an error that escapes the root
        pytest.fail(f"{cls.__name__} escapes `except FoilcHilError`")


@pytest.mark.parametrize(("name", "code"), sorted(EXIT_CODES.items()))
def test_exit_codes_are_the_interface_s(name: str, code: ExitCode) -> None:
    assert getattr(errors, name).exit_code is code


def test_each_error_still_is_the_builtin_it_refines() -> None:
    assert issubclass(errors.ConfigError, ValueError) and issubclass(errors.DriveTimeoutError, TimeoutError)
    assert issubclass(errors.SdoError, RuntimeError) and issubclass(errors.LmiInfeasibleError, ArithmeticError)
