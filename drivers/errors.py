"""The errors ``drivers`` and ``plant_emulator`` raise, and the root of the product's one error tree.

The tree is rooted here, at the bottom of the import ranks, so that ``drivers`` (and ``plant_emulator``, which
builds on it) stand alone: a commissioning script imports the master without the control stack, and still gets
typed errors with their exit codes. :mod:`foilc_hil.errors` re-exports every class of this module under the same
name (``foilc_hil.errors.DriveError is drivers.errors.DriveError``) and names the root :class:`ProductError`
``FoilcHilError``, so ``except FoilcHilError`` catches every error raised on purpose, whichever package raised it,
and the CLI maps each to its ``exit_code``. (The root has to be a base class, not a registered virtual one: an
``except`` clause does not consult ``ABC.register``.)

As in python-can (``CanTimeoutError(CanError, TimeoutError)``), each class also inherits the builtin it refines, so
callers that only know the builtin still catch it. Exit codes (``docs/interface.md``): 1 runtime failure, 2 usage
or configuration error, 3 infeasible design.
"""

from __future__ import annotations

from enum import IntEnum, unique
from typing import Any

__all__ = [
    "BadFrameError",
    "ConfigError",
    "DriveError",
    "DriveFaultError",
    "DriveNmtStateError",
    "DriveTimeoutError",
    "EdsError",
    "EmergencyError",
    "ExitCode",
    "FeedbackTimeoutError",
    "HeartbeatLostError",
    "InputError",
    "ProductError",
    "ProtocolError",
    "SdoError",
    "StateTransitionError",
]


@unique
class ExitCode(IntEnum):
    """Process exit codes fixed by the interface."""

    OK = 0
    RUNTIME_FAILURE = 1
    USAGE = 2
    INFEASIBLE = 3
    INTERRUPTED = 130  # Ctrl-C / SIGTERM: the shell convention 128 + SIGINT


class ProductError(Exception):
    """Root of every error the product raises on purpose (``foilc_hil.errors.FoilcHilError`` is this class).

    ``partial`` is what the failing command had done so far, as its JSON document (e.g. the trials a run
    completed, its log path): the CLI's ``--json`` error document includes it.
    """

    exit_code: ExitCode = ExitCode.RUNTIME_FAILURE
    partial: dict[str, Any] | None = None
    #: JSON-ready facts an outer layer learnt on the way out (``run``: the confirmed stop, ``drive_stop``); the
    #: ``--json`` error document carries them next to the message
    facts: dict[str, object] | None = None


# --- usage and input (exit 2) ---------------------------------------------------------------------------------


class InputError(ProductError, ValueError):
    """Bad input from the user: a config, an argument, a file. Exit 2, one line naming the field or file."""

    exit_code = ExitCode.USAGE


class ConfigError(InputError):
    """A configuration value is invalid.

    Parameters
    ----------
    message
        What is wrong, e.g. ``"must be non-zero"``.
    key
        Dotted key path inside the document, e.g. ``"plant.b"``; empty for the document as a whole.
    source
        The file (or other origin) the value came from, if any.
    """

    def __init__(self, message: str, key: str = "", source: str = "") -> None:
        self.message = message
        self.key = key
        self.source = source
        where = ": ".join(part for part in (source, key) if part)
        super().__init__(f"{where}: {message}" if where else message)


class EdsError(ConfigError):
    """An EDS / object dictionary file is missing, malformed or lacks a required object."""


class ProtocolError(InputError):
    """A CAN frame that does not fit the protocol: wrong DLC, unknown COB-ID, bad payload."""


# --- runtime failures of the drive or the bus (exit 1) --------------------------------------------------------


class DriveError(ProductError, RuntimeError):
    """The drive or the bus failed at run time."""


class DriveTimeoutError(DriveError, TimeoutError):
    """The drive did not answer in time."""


class HeartbeatLostError(DriveTimeoutError):
    """The drive's heartbeat stopped arriving."""


class FeedbackTimeoutError(DriveTimeoutError):
    """No TPDO feedback arrived for the configured number of cycles (the bench watchdog)."""


class StateTransitionError(DriveTimeoutError):
    """The CiA 402 state machine did not reach the requested state; the message names where it stuck."""


class DriveFaultError(DriveError):
    """The drive reports a fault (statusword fault bit)."""


class DriveNmtStateError(DriveError):
    """The drive's heartbeat reported that it left NMT OPERATIONAL while the bench ran its cyclic path."""


class BadFrameError(DriveError):
    """A frame received from the drive at run time does not decode (wrong DLC, malformed EMCY or heartbeat,
    impossible statusword), under ``bench.faults.bad_frame: abort``.

    A run-time failure of the link (exit 1), not bad input: :class:`ProtocolError` (exit 2) is for frames a user
    handed the product (e.g. a trace to decode)."""


class EmergencyError(DriveFaultError):
    """The drive sent an EMCY message.

    Parameters
    ----------
    code
        The 16-bit emergency error code (CiA 301 / CiA 402).
    register
        The error register (0x1001).
    text
        Decoded meaning of ``code``.
    """

    def __init__(self, code: int, register: int, text: str) -> None:
        self.code = code
        self.register = register
        self.text = text
        super().__init__(f"EMCY 0x{code:04X} ({text}), error register 0x{register:02X}")

    def __reduce__(self) -> tuple[Any, ...]:
        # pickled across processes (the demo's runs): rebuilt from its fields, with what was added (``partial``)
        return type(self), (self.code, self.register, self.text), self.__dict__


class SdoError(DriveError):
    """An SDO transfer failed.

    Parameters
    ----------
    index, subindex
        The object addressed.
    abort_code
        The CiA 301 abort code, 0 when the transfer failed without one (e.g. a timeout).
    text
        Decoded meaning of the abort code.
    """

    def __init__(self, index: int, subindex: int, abort_code: int, text: str) -> None:
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code
        self.text = text
        super().__init__(f"SDO 0x{index:04X}:{subindex:02X} aborted with 0x{abort_code:08X}: {text}")

    def __reduce__(self) -> tuple[Any, ...]:
        return type(self), (self.index, self.subindex, self.abort_code, self.text), self.__dict__
