"""One error hierarchy for the whole product.

Every exception the product raises on purpose derives from :class:`FoilcHilError`. The root and the errors of the
drive side (input, protocol, drive and bus failures) are defined in :mod:`drivers.errors`, below every package that
raises them (``drivers`` and ``plant_emulator`` import nothing from ``foilc_hil``); they are re-exported here, the
same classes under the same names, and ``FoilcHilError`` *is* their root :class:`drivers.errors.ProductError`, so
``except FoilcHilError`` catches every one of them. This module adds the errors of the control stack.

As in python-can (``CanTimeoutError(CanError, TimeoutError)``), each subclass also inherits the builtin it refines, so
callers that only know the builtin still catch it. Each class carries the process exit code the CLI maps it to
(see ``docs/interface.md``): 1 runtime failure, 2 usage or configuration error, 3 infeasible design.
"""

from __future__ import annotations

from drivers.errors import (
    BadFrameError,
    ConfigError,
    DriveError,
    DriveFaultError,
    DriveNmtStateError,
    DriveTimeoutError,
    EdsError,
    EmergencyError,
    ExitCode,
    FeedbackTimeoutError,
    HeartbeatLostError,
    InputError,
    ProductError,
    ProtocolError,
    SdoError,
    StateTransitionError,
)

__all__ = [
    "BadFrameError",
    "ConfigError",
    "ConvergenceCertificateError",
    "DriveError",
    "DriveFaultError",
    "DriveNmtStateError",
    "DriveNotStoppedError",
    "DriveTimeoutError",
    "EdsError",
    "EmergencyError",
    "ExitCode",
    "FeedbackTimeoutError",
    "FoilcHilError",
    "HeartbeatLostError",
    "InfeasibleDesignError",
    "InputError",
    "LearningDivergedError",
    "LmiInfeasibleError",
    "LogFormatError",
    "ProtocolError",
    "RunInterruptedError",
    "SdoError",
    "StateTransitionError",
    "TuningInfeasibleError",
]

FoilcHilError = ProductError
"""Root of every error the product raises on purpose: :class:`drivers.errors.ProductError` itself (its docstring)."""


# --- usage and input (exit 2) ---------------------------------------------------------------------------------


class LogFormatError(InputError):
    """A log file (MCAP) is unreadable, truncated or does not follow the product's layout."""


# --- infeasible designs (exit 3) ------------------------------------------------------------------------------


class InfeasibleDesignError(FoilcHilError, ArithmeticError):
    """No design meets the specification. The message names the specification that failed."""

    exit_code = ExitCode.INFEASIBLE


class TuningInfeasibleError(InfeasibleDesignError):
    """No ``kp > 0, 0 < r < 2`` meets the loop specification."""


class LmiInfeasibleError(InfeasibleDesignError):
    """The LMI of Theorem 1 has no solution, or its solution fails the independent checks."""


class ConvergenceCertificateError(InfeasibleDesignError):
    """The law as it runs (fractional filter included) is not certified to converge and could not be fixed."""


# --- runtime failures (exit 1) --------------------------------------------------------------------------------


class DriveNotStoppedError(DriveError):
    """The drive's disabled state could not be confirmed by reading it back after the stop."""


class LearningDivergedError(FoilcHilError, ArithmeticError):
    """Learning made the error grow beyond the configured factor, or produced a non-finite value."""


class RunInterruptedError(FoilcHilError):
    """The run was stopped by Ctrl-C or SIGTERM after bringing the drive to a safe state."""

    exit_code = ExitCode.INTERRUPTED
