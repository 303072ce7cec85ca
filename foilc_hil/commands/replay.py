"""``foilc-hil replay F.mcap [--bus SPEC | -i INTERFACE -c CHANNEL] [-b BPS] [--rate X] [--verify]
[--allow-real-bus] [--live [HOST:]PORT [--live-wait S] [--live-linger S] [--live-can-rate F]] [--json]``.

``--live`` streams the whole log to a Foxglove live view (:mod:`foilc_hil.live.replay`, docs/live-view.md) at
``--rate`` times its recorded pace, on the channels of ``run --live``; the JSON document then has ``"live"``: the
options and what was streamed. It replays onto no bus (``--bus`` with it is exit 2).

JSON: ``{"log", "frames_selected", "frames_sent", "duration", "verified", "first_divergence", "samples_checked",
"trials_checked", "truncated", "damage"}``; ``verified`` is ``null`` without ``--verify``. A divergence exits 1
(after printing the document); a non-MCAP or missing file, a bad option, or a real bus without
``--allow-real-bus`` exits 2 before anything is sent. Frames are replayed only onto a bus the command line names
(``-i``/``-c`` complete each other from python-can's ``CAN_INTERFACE``/``CAN_CHANNEL``/``can.rc``, which alone never
start a replay).
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from foilc_hil.commands import CommandResult, add_bus_options, bus_options
from foilc_hil.errors import ExitCode, InputError
from foilc_hil.live.options import add_live_options, live_options

if TYPE_CHECKING:
    from foilc_hil.live.options import LiveOptions
    from foilc_hil.live.replay import StreamReport

HELP = "play a log back onto a bus, or verify it bit for bit"


def _id(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an arbitration id (e.g. 0x201 or 513)") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="F.mcap", help="the log to play back")
    parser.add_argument("--bus", metavar="SPEC", help="re-emit the logged frames here (INTERFACE:CHANNEL)")
    add_bus_options(parser)
    parser.add_argument("--rate", type=float, default=1.0, metavar="X", help="playback speed factor (default 1)")
    parser.add_argument("--start", type=float, default=0.0, metavar="S", help="skip the first S seconds of the log")
    parser.add_argument("--duration", type=float, metavar="D", help="replay only D seconds from --start")
    parser.add_argument(
        "--direction",
        choices=("tx", "rx", "both"),
        default="tx",
        help="which logged frames to re-emit: sent by the bench (tx, default), received (rx), or both",
    )
    parser.add_argument("--ids", type=_id, nargs="+", metavar="ID", help="re-emit only these arbitration ids")
    parser.add_argument("--verify", action="store_true", help="re-run the learning law and check every command")
    add_live_options(parser, rows=False)
    parser.add_argument(
        "--allow-real-bus",
        action="store_true",
        help="allow a bus other than virtual/udp_multicast: a replayed log moves real hardware",
    )


def _check_bus(args: argparse.Namespace) -> Any:
    """The bus the command line names (``None``: none) -- hardware refused unless allowed, before anything opens."""
    from drivers.bus import command_line_bus, is_simulated_bus

    cfg = command_line_bus(bus_options(args))
    if cfg is not None and not is_simulated_bus(cfg.interface) and not args.allow_real_bus:
        option = "--bus" if args.bus else "-i/--interface"
        raise InputError(
            f"{option}: {cfg.interface}:{cfg.channel} is a real bus and a replayed log moves real hardware; use "
            "virtual or udp_multicast, or pass --allow-real-bus"
        )
    return cfg


def _frame_lines(args: argparse.Namespace, selected: int, sent: int, *, replayed: bool) -> list[str]:
    """What happened to the frames; nothing under ``--verify`` without a bus (the frames are not its subject, and
    "N selected, 0 sent" read like a failed replay)."""
    if replayed:
        return [f"{args.log}: replayed {sent} of {selected} selected frames"]
    if args.verify:
        return []
    return [f"{args.log}: {selected} frames selected (no bus given: nothing replayed)"]


def _verify(contents: Any, document: dict[str, Any]) -> None:
    """``--verify``: re-run the law(s) on the log and put the result into ``document``."""
    from foilc_hil.logtools.axes import log_axes, verify_axes
    from foilc_hil.logtools.replay import verify_log

    if log_axes(contents):  # several axes (axes: runs): each on its own law, one entry per axis
        verification, axes = verify_axes(contents)
        document["axes"] = [axis.to_json() for axis in axes]
    else:
        verification = verify_log(contents)
    document["verified"] = verification.verified
    document["samples_checked"] = verification.samples_checked
    document["trials_checked"] = verification.trials_checked
    if verification.first_divergence is not None:
        document["first_divergence"] = verification.first_divergence.to_json()


def _stream(log: str, live: LiveOptions, rate: float, document: dict[str, Any]) -> str:
    """``--live``: the log streamed to a live view at ``rate`` times its pace (:mod:`foilc_hil.live.replay`), what
    was sent put into ``document``; returns the line that says it."""
    report = _streamed(log, live, rate)
    options = {key: value for key, value in live.to_json().items() if key not in ("rows", "row_rate")}  # run's
    document["live"] = {**options, **report.to_json()}
    return f"{log}: streamed {sum(report.published.values())} messages to the live view in {report.duration:.1f} s"


def _streamed(log: str, live: LiveOptions, rate: float) -> StreamReport:
    from foilc_hil.live.replay import stream_log
    from foilc_hil.live.server import LiveServer

    with LiveServer(live.address, name=f"foilc-hil replay {log}") as server:
        sys.stderr.write(f"foilc-hil replay: live view on {live.address.host}:{server.port}\n")
        if live.wait > 0 and not server.wait_for_viewer(live.wait):
            sys.stderr.write(f"foilc-hil replay: no viewer subscribed within {live.wait:g} s; streaming anyway\n")
        try:
            return stream_log(log, server, rate=rate, can_rate=live.can_rate)
        finally:
            server.close(live.linger)


def execute(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.io.mcap_log import read_log
    from foilc_hil.logtools.replay import play_frames, select_frames

    if not args.rate > 0:
        raise InputError(f"--rate: must be > 0, got {args.rate}")
    live = live_options(args)
    bus_cfg = _check_bus(args)
    if live is not None and bus_cfg is not None:
        raise InputError("--live: streams the log to a viewer; replay it onto a bus in another run (without --live)")
    contents = read_log(args.log)
    if contents.truncated and not args.verify:
        sys.stderr.write(f"foilc-hil replay: {args.log}: {contents.damage}; using what was read before it\n")
    directions = ("tx", "rx") if args.direction == "both" else (args.direction,)
    frames = select_frames(
        contents.frames, directions=directions, start=args.start, duration=args.duration, ids=args.ids
    )
    document: dict[str, Any] = {
        "log": str(args.log),
        "frames_selected": len(frames),
        "frames_sent": 0,
        "duration": 0.0,
        "verified": None,
        "first_divergence": None,
        "truncated": contents.truncated,
        "damage": contents.damage or None,
        "partial": bool(args.verify and contents.truncated),
    }
    if args.verify:
        _verify(contents, document)
    if bus_cfg is not None:
        from drivers.bus import open_bus

        bus = open_bus(bus_cfg)
        try:
            playback = play_frames(bus, frames, rate=args.rate)
        finally:
            bus.shutdown()
        document["frames_sent"] = playback.frames_sent
        document["duration"] = playback.duration
        document["max_lateness"] = playback.max_lateness
    lines = _frame_lines(args, len(frames), document["frames_sent"], replayed=bus_cfg is not None)
    if live is not None:
        lines.append(_stream(args.log, live, args.rate, document))
    if contents.truncated:
        lines.append(f"truncated: {contents.damage}")
    if args.verify:
        divergence = document["first_divergence"]
        if divergence is None:
            lines.append(
                f"verified: {document['samples_checked']} commands in {document['trials_checked']} trials "
                "are bit-identical to the log"
            )
        else:
            lines.append(
                f"NOT verified: {divergence['topic']}, trial {divergence['trial']} sample {divergence['sample']}: "
                f"{divergence['reason']} (logged {divergence['logged']}, recomputed {divergence['recomputed']})"
            )
    text = "\n".join(lines)
    if document["verified"] is False:
        divergence = document["first_divergence"]
        return CommandResult(
            document,
            text,
            exit_code=ExitCode.RUNTIME_FAILURE,
            message=f"the log does not hold up at {divergence['topic']}, trial {divergence['trial']}, sample "
            f"{divergence['sample']}: {divergence['reason']}",
        )
    if document["partial"]:
        # Why exit 1: "verified" must mean the whole log was checked; a damaged log was only checked up to the damage
        return CommandResult(
            document,
            text,
            exit_code=ExitCode.RUNTIME_FAILURE,
            message=f"partial: {args.log}: {contents.damage}; checked {document['samples_checked']} commands in "
            f"{document['trials_checked']} trials before it, the rest is unchecked",
        )
    return CommandResult(document, text)
