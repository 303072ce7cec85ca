"""``foilc-hil run``: learning trials over CAN against a CiA 402 drive (or the embedded emulator).

``foilc-hil run --config C [--bus SPEC | -i INTERFACE -c CHANNEL | --emulator embedded] [-b BPS] [--trials N]
[--mode lockstep|realtime] [--law foilc|ioilc|p-type|noilc|gradient] [--inject KIND@WHEN[:KEY=VALUE,...]]...
--out F.mcap [--json] [--quiet] [--live [HOST:]PORT [--live-wait S] [--live-linger S] [--live-can-rate F]
[--live-rows N] [--live-row-rate R]]``

JSON: ``{"law", "trials": [{"trial", "sse", "rmse", "max_abs_error"}, ...], "timing": {"period", "cycles",
"missed_deadlines", "jitter_p99_us", ...}, "log", "design": {"kp", "r", "certificates", ...}, "stopped",
"bus_load": {"bitrate", "period", "limit", "bits_per_cycle", "load", "min_period", "frames"}}``.

Before anything is designed or sent, the worst-case bus load of the run's cyclic schedule (SYNC, the PDOs the
master maps -- :func:`drivers.cia402_master.pdo_plan` --, both heartbeats; stuff bits included, see
:mod:`drivers.busload`) at ``bus.bitrate`` (1 Mbit/s when unset) and a SYNC period of ``sample_time`` is checked
against ``bus.load_limit`` (default 0.7): over it, the run is refused with exit 2 and one line with the figures and
the shortest period that would fit.
Exit 0 when every trial ran; 1 for a drive fault, a bus timeout or learning that diverged and was stopped (the
JSON document and the log are still written for a divergence stop); 2 for bad input; 130 for Ctrl-C / SIGTERM.

``--live`` serves the run to Foxglove while it runs (:mod:`foilc_hil.live`, docs/live-view.md; 127.0.0.1:8765 unless an
address is given); the JSON document then has ``"live"``: the options and what was published and dropped.

``--inject`` (repeatable) adds faults to the config's ``inject:`` list (:mod:`drivers.faults`, docs/reliability.md),
e.g. ``--inject drop-tpdo@2+10:count=3`` or ``--inject emulator-kill@3+25``.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from foilc_hil.commands import CommandResult, add_bus_options, bus_options
from foilc_hil.errors import ExitCode
from foilc_hil.live.options import add_live_options, live_options

if TYPE_CHECKING:
    from drivers.busload import BusLoad
    from drivers.config import BusConfig
    from foilc_hil.config import Config

HELP = "run learning trials over CAN against a drive"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="C", help="config YAML (defaults when omitted)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument(
        "--bus", metavar="SPEC", help="INTERFACE:CHANNEL, e.g. socketcan:vcan0, udp_multicast:239.74.163.2"
    )
    where.add_argument(
        "--emulator",
        choices=["embedded"],
        help="run the plant emulator in this process on a virtual bus (the default when no bus is given)",
    )
    add_bus_options(parser)
    parser.add_argument("--trials", type=int, metavar="N", help="number of trials (default: config 'trials')")
    parser.add_argument("--mode", choices=["lockstep", "realtime"], help="timing mode (default: config bench.mode)")
    parser.add_argument(
        "--law",
        choices=["foilc", "ioilc", "p-type", "noilc", "gradient"],
        help="learning law (default: config law.kind)",
    )
    parser.add_argument(
        "--inject",
        action="append",
        default=[],
        metavar="KIND@WHEN[:K=V,...]",
        help="inject a fault (repeatable): WHEN is TRIAL, TRIAL+CYCLE or cCYCLE (SYNCs from the first), e.g. "
        "drop-tpdo@2+10:count=3, delay@2:frames=tpdo,delay=0.01,count=0, emulator-kill@3+25 (docs/reliability.md)",
    )
    parser.add_argument("--out", required=True, metavar="F.mcap", help="MCAP log to write")
    parser.add_argument("--quiet", action="store_true", help="no progress view on stderr")
    add_live_options(parser, rows=True)


def check_bus(bus: BusConfig) -> None:
    """Find a bad bus before the (possibly minutes-long) design: an interface python-can does not know is an
    :class:`~foilc_hil.errors.InputError` (exit 2); a bus that does not open (e.g. SocketCAN without the kernel
    module or the interface) is the :class:`~foilc_hil.errors.DriveError` of :func:`drivers.bus.open_bus`, with its
    ``ip link`` hint (exit 1). The bus is opened and closed again at once; nothing is sent."""
    from drivers.bus import known_interfaces, open_bus
    from foilc_hil.errors import InputError

    if bus.interface == "embedded":
        return
    if bus.interface not in known_interfaces():
        raise InputError(f"--bus: unknown interface {bus.interface!r}; known: {', '.join(sorted(known_interfaces()))}")
    open_bus(bus).shutdown()


def check_bus_load(config: Config, bus: BusConfig) -> BusLoad:
    """The worst-case :class:`~drivers.busload.BusLoad` of the run's schedule on ``bus``; a
    :class:`~foilc_hil.errors.ConfigError` naming ``bus.load_limit`` with the figures (exit 2) when over the limit.

    The bit rate is the bus's, else the config's ``bus.bitrate``, else 1 Mbit/s (``--emulator embedded`` has none).
    """
    from drivers.busload import DEFAULT_BITRATE, CyclicFrame, drive_schedule, schedule_load
    from drivers.cia402_master import MASTER_HEARTBEATS_PER_CONSUMER_TIME, pdo_plan
    from drivers.od import load_od
    from foilc_hil.config import axis_configs

    frames = [CyclicFrame("SYNC", 0)]
    axes = axis_configs(config)
    for k, axis in enumerate(axes):  # every axis's PDOs and heartbeat; the master's heartbeat once (the first's)
        drive = axis.drive
        plan = pdo_plan(drive.operation_mode, drive.node_id, load_od(drive.eds, drive.node_id),
                        demand_echo=drive.demand_echo)  # one TPDO more per cycle when it has no room
        master = drive.heartbeat_consumer_ms / 1000 / MASTER_HEARTBEATS_PER_CONSUMER_TIME if k == 0 else 0
        frames += drive_schedule(plan, period=config.sample_time, drive_heartbeat=drive.heartbeat_producer_ms / 1000,
                                 master_heartbeat=master, name=f"node {drive.node_id} " if len(axes) > 1 else "")
    bitrate = bus.bitrate or config.bus.bitrate or DEFAULT_BITRATE
    return schedule_load(frames, bitrate=bitrate, period=config.sample_time, limit=config.bus.load_limit).check()


def execute(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.config import load_config
    from foilc_hil.errors import InputError
    from foilc_hil.loop.rig import RunRequest, run_rig
    from plant_emulator.device import TimingMode

    if args.trials is not None and args.trials < 1:
        raise InputError(f"--trials: must be >= 1, got {args.trials}")
    live = live_options(args)  # a bad --live value: exit 2 before anything is designed or opened
    # --law overrides law.kind (also in the logged config, so the log says which law ran); RunRequest.law carries
    # it to each axis of an axes: run, whose own law sections the top-level key does not reach
    config = load_config(args.config, {"law.kind": args.law})
    if args.inject:
        from drivers.faults import parse_injection

        injected = [parse_injection(spec) for spec in args.inject]
        config = config.model_copy(update={"inject": (*config.inject, *injected)})  # logged with the config
    from drivers.bus import resolve_bus

    bus = resolve_bus(bus_options(args), config.bus)  # precedence: drivers.bus.resolve_bus
    check_bus(bus)  # before the design, which may take minutes
    from foilc_hil.references import trial_samples

    trial_samples(config.reference, config.sample_time)  # a trial the run cannot hold names its field first
    load = check_bus_load(config, bus)
    request = RunRequest(
        config=config,
        out=args.out,
        law=args.law,
        trials=args.trials,
        mode=TimingMode(args.mode) if args.mode is not None else None,
        bus=bus,
        quiet=bool(args.quiet or args.json),
    )
    if live is None:
        report = run_rig(request)
        document = {**report.to_json(), "bus_load": load.to_json()}
    else:
        from dataclasses import replace

        from foilc_hil.config import dump_config
        from foilc_hil.live.publisher import live_run

        with live_run(live, name="foilc-hil run", config_yaml=dump_config(config)) as publisher:
            report = run_rig(replace(request, live=publisher))
        document = {**report.to_json(), "bus_load": load.to_json(),
                    "live": {**live.to_json(), **publisher.stats.to_json()}}
    # the confirmed stop ends every run's text, as it ends every failed run's one line
    text = "\n".join([render_text(document), load.describe(), *report.stop_lines])
    if report.outcome.diverged:
        return CommandResult(
            document, text, exit_code=ExitCode.RUNTIME_FAILURE, message=report.outcome.stopped or "learning diverged"
        )
    return CommandResult(document, text)


def render_text(document: dict[str, Any]) -> str:
    """The human-readable summary: one line per trial and the timing."""
    lines = [f"law {document['law']}, log {document['log']}"]
    lines.append(f"{'trial':>5} {'SSE':>14} {'RMSE':>12} {'max |e|':>12}")
    for trial in document["trials"]:
        lines.append(
            f"{trial['trial']:>5} {trial['sse']:>14.6g} {trial['rmse']:>12.6g} {trial['max_abs_error']:>12.6g}"
        )
    timing = document["timing"]
    if timing:
        line = f"{timing['mode']}: {timing['cycles']} cycles of {timing['period'] * 1e3:g} ms"
        if timing.get("cycles_per_second"):
            line += f", {timing['cycles_per_second']:.0f} cycles/s"
        if timing.get("jitter_p99_us") is not None:
            line += (
                f", jitter p50 {timing['jitter_p50_us']:.0f} us p99 {timing['jitter_p99_us']:.0f} us "
                f"max {timing['jitter_max_us']:.0f} us, missed deadlines {timing['missed_deadlines']}"
            )
        lines.append(line)
    if document.get("stopped"):
        lines.append(f"stopped: {document['stopped']}")
    return "\n".join(lines)
