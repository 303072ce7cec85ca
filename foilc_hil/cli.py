"""``foilc-hil``: the command line. Subcommands are fixed in ``docs/interface.md``.

The CLI does the shared work -- argument parsing, ``--json`` output, mapping errors to exit codes -- and
each subcommand module in :mod:`foilc_hil.commands` does its own (python-can's ``BusABC.recv`` /
``_recv_internal`` split). Command modules are imported lazily, so ``foilc-hil tune`` never imports the CAN
stack and ``foilc-hil run`` never imports cvxpy unless it must.
"""

from __future__ import annotations

import argparse
import enum
import importlib
import json
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from enum import StrEnum
from types import ModuleType
from typing import Any, NoReturn

from foilc_hil import __version__
from foilc_hil.errors import ConfigError, ExitCode, FoilcHilError, RunInterruptedError
from foilc_hil.progress import steps

#: subcommand name -> (module implementing it, one-line help). Modules are imported only when chosen.
COMMANDS: dict[str, tuple[str, str]] = {
    "tune": ("foilc_hil.commands.tune", "tune the fractional PD function's kp and r from loop specifications"),
    "synthesize": ("foilc_hil.commands.synthesize", "solve the LMI of Theorem 1 for the learning gain P"),
    "simulate": ("foilc_hil.commands.simulate", "run learning trials offline, with no bus"),
    "robustness": (
        "foilc_hil.commands.robustness",
        "certify a designed law on plants drawn from the uncertainty set (Monte Carlo on Dask)",
    ),
    "run": ("foilc_hil.commands.run", "run learning trials over CAN against a drive"),
    "demo": ("foilc_hil.commands.demo", "FOILC and IOILC side by side on the embedded emulator"),
    "replay": ("foilc_hil.commands.replay", "play a log back onto a bus, or verify it bit for bit"),
    "report": ("foilc_hil.commands.report", "plots and a summary of a log"),
    "export": ("foilc_hil.commands.export", "write a log's CAN frames as ASC, BLF or CSV, or the DBC of its mapping"),
    "config": ("foilc_hil.commands.config", "print the JSON Schema of the config file (for editors)"),
    "commission": ("foilc_hil.commands.commission", "scan, inspect, enable, parameterise and identify a drive"),
}


class _Parser(argparse.ArgumentParser):
    """argparse that reports usage errors as one line and exit 2 (never a multi-line usage dump)."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(ExitCode.USAGE)


def _load(name: str) -> ModuleType:
    return importlib.import_module(COMMANDS[name][0])


def build_parser(chosen: str | None = None) -> argparse.ArgumentParser:
    """The parser; only the ``chosen`` subcommand's module is imported, to add its options."""
    parser = _Parser(prog="foilc-hil", description="Hardware-in-the-loop bench for 2D fractional-order ILC.")
    parser.add_argument("--version", action="version", version=f"foilc-hil {__version__}")
    parser.add_argument(
        "--log-level", choices=[level.value for level in LogLevel], default=LogLevel.WARNING.value,
        help="diagnostics on stderr before the command's one-line result (default warning; canopen's and "
        "python-can's own messages only at debug)",
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name, (_, help_text) in COMMANDS.items():
        command_parser = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            _load(name).add_arguments(command_parser)
            if not any(action.dest == "json" for action in command_parser._actions):
                command_parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")
            if not any(action.dest in ("quiet", "action") for action in command_parser._actions):
                # commission's actions add their own where they have slow steps
                command_parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return parser


def main(argv: Sequence[str] | None = None, *, restore_signals: bool = True) -> int:
    """Entry point of the ``foilc-hil`` console script. Returns the process exit code.

    Once the command is done, SIGINT and SIGTERM are ignored while it reports; ``restore_signals`` puts the handlers
    found back on return (a caller in the same process); the console script does not, so a signal between the report
    and the process's exit cannot cut it short either."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    try:
        chosen = next((token for token in args_list if token in COMMANDS), None)
        parser = build_parser(chosen if chosen in COMMANDS else None)
        args = parser.parse_args(args_list)
    except SystemExit as exc:  # --help, --version, usage errors
        code = int(exc.code) if isinstance(exc.code, int) else ExitCode.USAGE
        if code != ExitCode.OK and "--json" in args_list:  # the one-line message went to stderr; a document too
            _write_json({"error": _error_detail("UsageError", "invalid command line (see stderr)", code)})
        return code
    _configure_logging(LogLevel(args.log_level))
    previous = _handlers()
    try:
        return _execute(args)
    finally:
        if restore_signals:
            _restore(previous)


def _execute(args: argparse.Namespace) -> int:
    """Run the parsed command and report it (one JSON document under ``--json``); its exit code."""
    module = _load(args.command)
    want_json = bool(getattr(args, "json", False))
    try:
        with steps(quiet=want_json or bool(getattr(args, "quiet", False))):  # progress.step of the slow work
            result = module.execute(args)
        _shield_signals()
    except KeyboardInterrupt:
        error: FoilcHilError = RunInterruptedError("interrupted")
        return _fail(args.command, error, want_json)
    except ConfigError as exc:
        return _fail(args.command, _with_source(exc, getattr(args, "config", None)), want_json)
    except FoilcHilError as exc:
        _shield_signals()
        return _fail(args.command, exc, want_json)
    if want_json:
        document = result.document
        if result.exit_code != ExitCode.OK:  # a command that finished but failed: its document plus the error
            detail = _error_detail(f"{args.command.capitalize()}Failed", result.message or "failed", result.exit_code)
            document = {**document, "error": detail}
        sys.stdout.write(json.dumps(document, indent=2, allow_nan=False) + "\n")
    elif result.text:
        sys.stdout.write(result.text.rstrip("\n") + "\n")
    if result.exit_code != ExitCode.OK and result.message:
        sys.stderr.write(f"foilc-hil {args.command}: {result.message}\n")
    sys.stdout.flush()
    return int(result.exit_code)


_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _handlers() -> list[Any]:
    return [signal.getsignal(signum) for signum in _SIGNALS]


def _restore(previous: list[Any]) -> None:
    """The handlers ``main`` found (a caller in the same process, pytest, gets its own back)."""
    if threading.current_thread() is threading.main_thread():
        for signum, handler in zip(_SIGNALS, previous, strict=True):
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


def _shield_signals() -> None:
    """The command is done (its drive stopped, its log closed): a SIGINT or SIGTERM from now on would only cut the
    report short (a SIGTERM 30 ms after a Ctrl-C killed the process after its stop, exit -15 instead of 130), so the
    rest (the report, the exit code) runs with both ignored. Outside the main thread nothing can be changed."""
    if threading.current_thread() is threading.main_thread():
        for signum in _SIGNALS:
            signal.signal(signum, signal.SIG_IGN)


@enum.unique
class LogLevel(StrEnum):
    """``--log-level``: how much the product logs on stderr besides its one-line result."""

    DEBUG = "debug"
    INFO = "info"
    WARNING = "warning"
    ERROR = "error"


PRODUCT_LOGGERS = ("foilc_hil", "drivers", "plant_emulator")


def _configure_logging(level: LogLevel) -> None:
    """Product diagnostics at ``level``; canopen's and python-can's only at ``debug``: below that they repeat what
    the product's one line already says (e.g. canopen's "Transfer aborted" for each SDO the confirmed stop tried);
    any other library's only when they are errors."""
    numeric = getattr(logging, level.name)
    debug = level is LogLevel.DEBUG
    root = logging.getLogger()
    if not root.handlers:  # an application embedding main() (or pytest) keeps its own logging set-up
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("foilc-hil: %(name)s: %(message)s"))
        # other libraries (matplotlib's font warnings, dask's cluster chatter, ...) only when they report errors;
        # a filter on the handler, because some of them (distributed) set their own loggers' levels
        threshold = numeric if debug else logging.ERROR
        handler.addFilter(lambda record: record.name.split(".")[0] in PRODUCT_LOGGERS or record.levelno >= threshold)
        root.addHandler(handler)
        root.setLevel(numeric)
    for product in PRODUCT_LOGGERS:
        logging.getLogger(product).setLevel(numeric)
    for library in ("canopen", "can"):
        logging.getLogger(library).setLevel(numeric if debug else logging.CRITICAL)


def _with_source(error: ConfigError, config_path: object) -> ConfigError:
    """A config error found after loading (by the tuner, the synthesis ...) names the file it came from too."""
    if error.source or not error.key or not isinstance(config_path, str):
        return error
    return type(error)(error.message, key=error.key, source=config_path)


def _fail(command: str, error: FoilcHilError, want_json: bool) -> int:
    """One line on stderr; under ``--json`` also one JSON document on stdout, so a script always gets a document."""
    message = str(error).splitlines()[0] if str(error) else type(error).__name__
    # PEP 678 notes carry what happened on the way out, e.g. whether the drive was confirmed disabled
    notes = [note for note in getattr(error, "__notes__", ()) if isinstance(note, str)]
    if notes:
        message = "; ".join([message, *notes])
    sys.stderr.write(f"foilc-hil {command}: {message}\n")
    if want_json:
        detail = _error_detail(type(error).__name__, message, error.exit_code)
        if isinstance(error, ConfigError):
            detail.update(key=error.key, source=error.source)
        detail.update(error.facts or {})
        _write_json({**(error.partial or {}), "error": detail})  # with what the command had done, if anything
    return int(error.exit_code)


def _error_detail(type_name: str, message: str, exit_code: int) -> dict[str, object]:
    """The ``"error"`` member of a ``--json`` failure document; ``kind`` names the exit code's class."""
    try:
        kind = ExitCode(exit_code).name.lower()
    except ValueError:
        kind = "unknown"
    return {"type": type_name, "message": message, "exit_code": int(exit_code), "kind": kind}


def _write_json(document: dict[str, object]) -> None:
    sys.stdout.write(json.dumps(document, allow_nan=False, default=str) + "\n")
    sys.stdout.flush()


def run() -> NoReturn:
    """Console-script wrapper."""
    raise SystemExit(main(restore_signals=False))


if __name__ == "__main__":
    run()
