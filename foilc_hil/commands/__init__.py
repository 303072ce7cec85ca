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

from dataclasses import dataclass
from typing import Any

from foilc_hil.errors import ExitCode


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
