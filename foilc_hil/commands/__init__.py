"""One module per ``foilc-hil`` subcommand, registered lazily in :mod:`foilc_hil.cli`.

Each module defines:

``HELP: str``
    one line for ``foilc-hil --help``;
``add_arguments(parser: argparse.ArgumentParser) -> None``
    its options (``--json`` is added by the CLI);
``execute(args: argparse.Namespace) -> CommandResult``
    the work. Errors are raised as :class:`foilc_hil.errors.FoilcHilError` subclasses; the CLI maps them to
    exit codes and one-line messages.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from foilc_hil.errors import ExitCode

if TYPE_CHECKING:
    from drivers.bus import BusOptions


@dataclass(frozen=True)
class CommandResult:
    """What a command hands back to the CLI.

    Attributes
    ----------
    document
        The ``--json`` document (exactly one per run).
    text
        The human-readable rendering printed without ``--json``.
    exit_code
        Usually OK; a command that finished but must report failure (e.g. learning diverged and was stopped,
        after writing its outputs) returns RUNTIME_FAILURE here with ``document`` still filled in.
    message
        A one-line explanation printed on stderr when ``exit_code`` is not OK.
    """

    document: dict[str, Any]
    text: str = ""
    exit_code: ExitCode = ExitCode.OK
    message: str = ""


def add_bus_options(parser: argparse.ArgumentParser) -> None:
    """python-can's bus options beside ``--bus`` (as its ``can.logger``/``can.player`` spell them)."""
    parser.add_argument("-i", "--interface", metavar="NAME",
                        help="python-can interface, e.g. socketcan (with -c; instead of --bus; default: "
                        "python-can's CAN_INTERFACE / can.rc)")
    parser.add_argument("-c", "--channel", metavar="CHANNEL",
                        help="python-can channel, e.g. can0 (default: python-can's CAN_CHANNEL / can.rc)")
    parser.add_argument("-b", "--bitrate", type=int, metavar="BPS", help="bitrate in bit/s (overrides bus.bitrate)")


def bus_options(args: argparse.Namespace) -> BusOptions:
    """The bus options of ``args`` (:func:`add_bus_options` and ``--bus``/``--emulator``)."""
    from drivers.bus import BusOptions

    return BusOptions(spec=args.bus, interface=args.interface, channel=args.channel, bitrate=args.bitrate,
                      emulator=getattr(args, "emulator", None))
