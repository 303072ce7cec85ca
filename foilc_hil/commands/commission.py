"""``foilc-hil commission scan|info|enable|disable|fault-reset|params|identify``: drive commissioning.

Every action takes ``--bus INTERFACE:CHANNEL`` (default: ``--emulator embedded``, the in-process emulator),
``--node-id N`` (default: ``drive.node_id`` of ``--config``; ``info``, ``enable``, ``disable`` and ``fault-reset`` also
take several, ``--node-id 1,2,3,4`` or ``1-4``, and act on each node in turn over one shared
:class:`~drivers.network.DriveNetwork`), ``--config C`` (drive settings, ``sample_time``; and
for the embedded emulator its ``plant:``/``emulator:``) and ``--json``. ``--emulator-config C`` makes the embedded
emulator emulate the plant of another config (e.g. a known first-order plant); ``--emulated-nodes 1,5,9`` puts
several emulated drives on its bus. See :mod:`foilc_hil.commission` for what each action does.

JSON documents:

- ``scan``: ``{"bus", "nodes": [{"node_id", "found_by", "nmt_state", "device_type", "profile", "identity": {...}}],
  "node_range", "listen_seconds", "nmt_reset"}``
- ``info``: ``{"node_id", "device_type", "identity", "nmt_state", "supported_modes", "mode", "statusword",
  "error_register", "error_code", "pdos": [...], "dbc"?}``
- ``enable``/``disable``/``fault-reset``: ``{"action", "node_id", "final_state", "transitions": [{"t", "state",
  "statusword", "controlword"}], "notes"}``
- ``info``/``enable``/``disable``/``fault-reset`` with several node ids: ``{"action", "nodes": [one document above
  per node, in node order]}``; ``enable`` on several nodes that fails on one disables the nodes it enabled before
  (then exit 1 with the error).
- ``params read``: ``{"parameters": [{"name", "index", "subindex", "value", "unit"}]}``; ``params write``:
  ``{"ok", "changes": [{"name", "index", "subindex", "old", "new", "status"}], "error", "refused", "rolled_back",
  "not_restored"}`` (exit 1 when not ok)
- ``identify``: ``{"plant": {"a", "b", "c", "num", "den", "delay"}, "uncertainty": {"G1", "H1", "G2", "H2", ...},
  "fit": {...}, "campaign": {...}, "out", "plot"}``
"""

from __future__ import annotations

import argparse
import contextlib
import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from foilc_hil.commands import CommandResult, add_bus_options, bus_options
from foilc_hil.errors import ExitCode, InputError

if TYPE_CHECKING:
    from drivers.cia402_master import Cia402Drive
    from drivers.config import DriveConfig
    from foilc_hil.commission.identify import CampaignSpec
    from foilc_hil.commission.target import CommissionTarget
    from foilc_hil.config import Config

HELP = "scan, inspect, enable, parameterise and identify a drive"

def _common(parser: argparse.ArgumentParser) -> None:
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--bus", metavar="SPEC", help="INTERFACE:CHANNEL, e.g. socketcan:vcan0 (default: embedded)")
    where.add_argument("--emulator", choices=["embedded"], help="the in-process emulator (the default)")
    add_bus_options(parser)
    parser.add_argument("--node-id", metavar="N", help="the drive's node id (default: drive.node_id); info, enable, "
                        "disable and fault-reset take several, e.g. 1,2,3,4 or 1-4")
    parser.add_argument("--config", metavar="C", help="config YAML: drive settings, sample_time, emulated plant")
    parser.add_argument("--emulator-config", metavar="C",
                        help="config whose plant:/emulator: the embedded emulator runs (default: --config)")
    parser.add_argument("--emulated-nodes", metavar="LIST",
                        help="node ids of the embedded emulator's drives, e.g. 1,5,9 (default: --node-id)")
    parser.add_argument("--json", action="store_true", default=argparse.SUPPRESS,
                        help="print one JSON document on stdout")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``commission`` actions and their options."""
    parser.add_argument("--json", action="store_true", default=False, help="print one JSON document on stdout")
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")

    scan = actions.add_parser("scan", help="find the nodes on the bus (heartbeat, boot-up, SDO probe)")
    _common(scan)
    scan.add_argument("--timeout", type=float, default=1.2, metavar="S", help="seconds to listen (default 1.2)")
    scan.add_argument("--node-range", default="1-127", metavar="LO-HI", help="node ids to look for (default 1-127)")
    scan.add_argument("--nmt-reset", action="store_true",
                      help="broadcast NMT reset communication first (resets every node's PDO/heartbeat settings)")

    info = actions.add_parser("info", help="identity, modes, 402 state, errors and PDO mapping of a drive")
    _common(info)
    info.add_argument("--dbc", metavar="FILE",
                      help="also write the DBC of the PDO mapping run installs (scaled signals, units, "
                      "402 value tables, node names; any canmatrix format by suffix; several --node-id: every "
                      "node in one file)")
    info.add_argument("--dcf", metavar="FILE.dcf",
                      help="also write the configured drive as a CiA 306 DCF: its EDS plus node id, bit rate and "
                      "the values run writes (PDO mapping, mode, heartbeats)")

    check = actions.add_parser("check", help="before any motion: will run work on this drive, and why")
    _common(check)

    for name, text in (
        ("enable", "walk the 402 state machine to OPERATION ENABLED"),
        ("disable", "disable voltage (to SWITCH ON DISABLED)"),
        ("fault-reset", "clear a fault (NMT reset communication first after a heartbeat/SYNC fault)"),
    ):
        power = actions.add_parser(name, help=text)
        _common(power)
        power.add_argument("--state-timeout", type=float, metavar="S",
                           help="seconds per transition (default: drive.state_timeout)")

    params = actions.add_parser("params", help="read or write a parameter set over SDO")
    params.add_argument("operation", choices=["read", "write"])
    params.add_argument("file", nargs="?", metavar="FILE.yaml",
                        help="parameter set (write: required; read: the entries to read, default all EDS parameters)")
    _common(params)
    params.add_argument("--out", metavar="FILE.yaml", help="read: write the values there (default: stdout)")
    params.add_argument("--skip-eds-check", action="store_true",
                        help="write: send the set even where the EDS says the drive will refuse it")

    identify = actions.add_parser("identify", help="step tests and a fitted plant model with uncertainty bounds")
    _common(identify)
    identify.add_argument("--mode", choices=["csv", "cst"], help="csv: velocity steps, cst: torque steps "
                          "(default: drive.mode, pv -> csv)")
    identify.add_argument("--model", choices=["first-order", "first-order-delay", "second-order"],
                          default="first-order", help="model structure (default first-order b/(s - a))")
    identify.add_argument("--amplitudes", metavar="LIST",
                          help="step sizes in plant units, e.g. 300,600 (default: 10/20/30 %% of the velocity "
                          "limit in csv, 2/4 %% of the torque limit in cst)")
    identify.add_argument("--hold", type=float, metavar="S", help="seconds each step is held (csv 1.0, cst 0.2)")
    identify.add_argument("--rest", type=float, metavar="S", help="seconds of rest between steps (default 1.0)")
    identify.add_argument("--repetitions", type=int, default=2, metavar="N", help="campaign repetitions (default 2)")
    identify.add_argument("--output-limit", type=float, metavar="Y",
                          help="abort (safe stop) when |velocity| exceeds this (default: drive.velocity_limit)")
    identify.add_argument("--uncertainty-margin", type=float, default=1.25, metavar="M",
                          help="factor on the observed parameter spread (default 1.25)")
    identify.add_argument("--out", metavar="FILE.yaml", help="write the plant: section (plus --config's other "
                          "sections) for tune/synthesize/run")
    identify.add_argument("--plot", metavar="FILE.png", help="plot measured steps against the fitted model")
    identify.add_argument("--quiet", action="store_true", help="no progress on stderr")


# --- shared plumbing ----------------------------------------------------------------------------------------------


def _positive(value: float | None, option: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"{option}: must be a positive number, got {value}")


def _load_nodes(args: argparse.Namespace) -> tuple[Config, Config | None, tuple[DriveConfig, ...]]:
    """The configs and one ``drive:`` section per ``--node-id`` (one or several)."""
    from foilc_hil.commission.target import parse_node_list
    from foilc_hil.config import load_config

    config = load_config(args.config)
    emulator_config = load_config(args.emulator_config) if args.emulator_config else None
    nodes = parse_node_list(args.node_id, option="--node-id") if args.node_id is not None else (config.drive.node_id,)
    return config, emulator_config, tuple(config.drive.model_copy(update={"node_id": node}) for node in nodes)


def _load(args: argparse.Namespace) -> tuple[Config, Config | None, DriveConfig]:
    """As :func:`_load_nodes`, for the actions that act on one node."""
    config, emulator_config, drives = _load_nodes(args)
    if len(drives) > 1:
        raise InputError(f"--node-id: commission {args.action} acts on one node, got {len(drives)}")
    return config, emulator_config, drives[0]


def _target(args: argparse.Namespace, config: Config, emulator_config: Config | None,
            *node_ids: int) -> CommissionTarget:
    from drivers.bus import resolve_bus
    from foilc_hil.commission.target import CommissionTarget, parse_node_list

    resolved = resolve_bus(bus_options(args), config.bus)  # precedence: drivers.bus.resolve_bus
    bus = None if resolved.interface == "embedded" else resolved  # None: the target's embedded emulator
    nodes = parse_node_list(args.emulated_nodes, option="--emulated-nodes") if args.emulated_nodes else node_ids
    return CommissionTarget(config, bus, emulated_nodes=nodes, emulator_config=emulator_config)


def _open_drive(target: CommissionTarget, drive_cfg: DriveConfig, sample_time: float) -> Cia402Drive:
    from drivers.cia402_master import Cia402Drive

    drive = Cia402Drive.open(target.bus, drive_cfg, sample_time=sample_time)
    drive.listen()  # the actions talk SDO/NMT to the drive as it is: no connect() (that resets its communication)
    return drive


@contextlib.contextmanager
def _shared_drives(target: CommissionTarget, drive_cfgs: tuple[DriveConfig, ...],
                   sample_time: float) -> Iterator[list[Cia402Drive]]:
    """Masters for several nodes on one :class:`~drivers.network.DriveNetwork`, listening (no connect()), all
    closed with the network on exit."""
    from drivers.cia402_master import Cia402Drive
    from drivers.network import DriveNetwork

    network = DriveNetwork(target.bus)
    drives: list[Cia402Drive] = []
    try:
        for drive_cfg in drive_cfgs:
            drives.append(Cia402Drive.on_network(network, drive_cfg, sample_time=sample_time))
            drives[-1].listen()
        yield drives
    finally:
        for drive in drives:
            drive.close()
        network.close()


def execute(args: argparse.Namespace) -> CommandResult:
    """Dispatch to the action."""
    handlers = {
        "scan": _scan,
        "info": _info,
        "check": _check,
        "enable": _power,
        "disable": _power,
        "fault-reset": _power,
        "params": _params,
        "identify": _identify,
    }
    return handlers[args.action](args)


# --- actions ------------------------------------------------------------------------------------------------------


def _scan(args: argparse.Namespace) -> CommandResult:
    from drivers.scan import render_scan, scan_bus
    from foilc_hil.commission.target import parse_node_list

    _positive(args.timeout, "--timeout")
    nodes = parse_node_list(args.node_range, option="--node-range")
    config, emulator_config, drive_cfg = _load(args)
    with _target(args, config, emulator_config, drive_cfg.node_id) as target:
        result = scan_bus(target.bus, nodes=nodes, listen=args.timeout, nmt_reset=args.nmt_reset,
                          sdo_timeout=min(config.drive.sdo_timeout, 0.5))
        document = {"bus": target.description, **result.to_json()}
    return CommandResult(document, f"bus {document['bus']}\n{render_scan(result)}")


def _info(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.commission.dbc import write_dbc
    from foilc_hil.commission.dcf import write_dcf
    from foilc_hil.commission.info import read_info, render_info

    config, emulator_config, drive_cfgs = _load_nodes(args)
    if args.dbc and Path(args.dbc).suffix.lower() not in (".dbc", ".dbf", ".kcd", ".arxml", ".sym", ".json",
                                                          ".xls", ".xlsx", ".yaml"):
        raise InputError(f"--dbc: {args.dbc!r} needs a suffix canmatrix writes (.dbc, .kcd, .arxml, .sym, ...)")
    if len(drive_cfgs) > 1:
        if args.dcf:
            raise InputError("--dcf: give one --node-id (the file describes one drive's configuration)")
        with _target(args, config, emulator_config, *(cfg.node_id for cfg in drive_cfgs)) as target, \
                _shared_drives(target, drive_cfgs, config.sample_time) as drives:
            documents = tuple(read_info(drive).to_json() for drive in drives)
            # one DBC for the bus: every node's mapping as run will install it (each drive's preflight)
            plans = [(drive.preflight(cfg.operation_mode), cfg)
                     for drive, cfg in zip(drives, drive_cfgs, strict=True)] if args.dbc else []
        result = _per_node("info", documents, "\n".join(render_info(document) for document in documents))
        if args.dbc:
            result.document["dbc"] = write_dbc(plans, args.dbc).to_json()
        return result
    drive_cfg = drive_cfgs[0]
    with _target(args, config, emulator_config, drive_cfg.node_id) as target:
        drive = _open_drive(target, drive_cfg, config.sample_time)
        try:
            document = read_info(drive).to_json()
            if args.dbc or args.dcf:  # the mapping run will install on this drive (its preflight), not today's
                plan = drive.preflight(drive_cfg.operation_mode)
                if args.dbc:
                    document["dbc"] = write_dbc([(plan, drive_cfg)], args.dbc).to_json()
                if args.dcf:
                    document["dcf"] = write_dcf(drive, plan, bitrate=_bitrate(args, config),
                                                path=args.dcf).to_json()
        finally:
            drive.close()
    return CommandResult(document, render_info(document))


def _check(args: argparse.Namespace) -> CommandResult:
    from drivers.bus import resolve_bus
    from foilc_hil.commands.run import check_bus_load
    from foilc_hil.commission.check import Verdict, bus_load_check, check_drive
    from foilc_hil.errors import ConfigError, DriveError

    config, emulator_config, drive_cfg = _load(args)
    config = config.model_copy(update={"drive": drive_cfg})
    try:  # run's own check, on the bus run would use
        load = check_bus_load(config, resolve_bus(bus_options(args), config.bus))
        bus_load = bus_load_check(load.describe(), Verdict.PASS)
    except ConfigError as exc:
        bus_load = bus_load_check(str(exc), Verdict.FAIL)
    except DriveError as exc:  # no PDO plan to load the bus with: the plan's own check names the object
        bus_load = bus_load_check(f"not computed: {exc}", Verdict.WARN)
    with _target(args, config, emulator_config, drive_cfg.node_id) as target:
        drive = _open_drive(target, drive_cfg, config.sample_time)
        try:
            report = check_drive(drive, config, bus_load)
        finally:
            drive.close()
    if not report.runnable:
        first = report.failures[0]
        message = f"run would refuse node {report.node_id}: {first.subject}: {first.detail}"
        return CommandResult(report.to_json(), report.render(), exit_code=ExitCode.RUNTIME_FAILURE, message=message)
    return CommandResult(report.to_json(), report.render())


def _bitrate(args: argparse.Namespace, config: Config) -> int:
    """The bit rate of the bus the command talks on: ``-b``, the bus's, ``bus.bitrate``, else 1 Mbit/s."""
    from drivers.bus import resolve_bus
    from drivers.busload import DEFAULT_BITRATE

    return resolve_bus(bus_options(args), config.bus).bitrate or config.bus.bitrate or DEFAULT_BITRATE


def _power(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.commission import power

    _positive(args.state_timeout, "--state-timeout")
    config, emulator_config, drive_cfgs = _load_nodes(args)
    if len(drive_cfgs) > 1:
        return _power_nodes(args, config, emulator_config, drive_cfgs)
    drive_cfg = drive_cfgs[0]
    timeout = args.state_timeout if args.state_timeout is not None else drive_cfg.state_timeout
    with _target(args, config, emulator_config, drive_cfg.node_id) as target:
        drive = _open_drive(target, drive_cfg, config.sample_time)
        try:
            if args.action == "enable":  # run's own checks first: enable and run agree on what a drive must have
                report = power.enable(drive, state_timeout=timeout, mode=drive_cfg.operation_mode)
            else:
                walk = power.disable if args.action == "disable" else power.fault_reset
                report = walk(drive, state_timeout=timeout)
        finally:
            drive.close()
    return CommandResult(report.to_json(), report.render())


def _power_nodes(args: argparse.Namespace, config: Config, emulator_config: Config | None,
                 drive_cfgs: tuple[DriveConfig, ...]) -> CommandResult:
    """``enable``/``disable``/``fault-reset`` on each node in turn; a failed ``enable`` disables the nodes it had
    enabled before the error propagates (no drive is left enabled by a command that failed)."""
    from foilc_hil.commission import power

    reports: list[power.PowerReport] = []
    with _target(args, config, emulator_config, *(cfg.node_id for cfg in drive_cfgs)) as target, \
            _shared_drives(target, drive_cfgs, config.sample_time) as drives:
        for drive, drive_cfg in zip(drives, drive_cfgs, strict=True):
            timeout = args.state_timeout if args.state_timeout is not None else drive_cfg.state_timeout
            try:
                if args.action == "enable":
                    reports.append(power.enable(drive, state_timeout=timeout, mode=drive_cfg.operation_mode))
                else:
                    walk = power.disable if args.action == "disable" else power.fault_reset
                    reports.append(walk(drive, state_timeout=timeout))
            except BaseException:
                if args.action == "enable":
                    power.disable_all(drives[:len(reports)], state_timeout=timeout)
                raise
    return _per_node(args.action, tuple(report.to_json() for report in reports),
                     "\n".join(report.render() for report in reports))


def _per_node(action: str, documents: tuple[dict[str, Any], ...], text: str) -> CommandResult:
    """The result of an action on several nodes: one document per node, in node order."""
    from foilc_hil.commission.target import PerNodeResult

    return CommandResult(PerNodeResult(action, documents).to_json(), text)


def _params(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.commission import params

    if args.operation == "write" and not args.file:
        raise InputError("params write: give the parameter set FILE.yaml")
    if args.operation == "write" and args.out:
        raise InputError("--out: only for params read")
    parameter_set = params.load_parameter_set(args.file, need_values=args.operation == "write") if args.file else None
    config, emulator_config, drive_cfg = _load(args)
    with _target(args, config, emulator_config, drive_cfg.node_id) as target:
        drive = _open_drive(target, drive_cfg, config.sample_time)
        try:
            if args.operation == "read":
                entries = parameter_set.parameters if parameter_set else params.eds_parameters(drive)
                values = params.read_parameters(drive, entries)
            else:
                assert parameter_set is not None
                report = params.write_parameters(drive, parameter_set.parameters,
                                                 eds_check=not args.skip_eds_check)
        finally:
            drive.close()
    if args.operation == "read":
        text = params.dump_parameter_set(values)
        if args.out:
            try:
                Path(args.out).write_text(text, encoding="utf-8")
            except OSError as exc:
                raise InputError(f"--out: cannot write {args.out}: {exc}") from exc
            text = f"{len(values)} parameters written to {args.out}"
        return CommandResult({"parameters": [value.to_json() for value in values], "out": args.out}, text)
    document = report.to_json()
    if not report.ok:
        return CommandResult(document, report.render(), exit_code=ExitCode.RUNTIME_FAILURE, message=report.error)
    return CommandResult(document, report.render())


def _identify(args: argparse.Namespace) -> CommandResult:
    import numpy as np
    import yaml

    from drivers.cia402 import OperationMode
    from foilc_hil.commission import identify
    from foilc_hil.progress import step
    from foilc_hil.schema import load_document

    config, emulator_config, drive_cfg = _load(args)
    mode = args.mode or ("cst" if drive_cfg.mode == "cst" else "csv")
    spec = _campaign_spec(args, drive_cfg, mode)
    output_limit = args.output_limit if args.output_limit is not None else drive_cfg.velocity_limit
    sample_time = config.sample_time
    command = identify.build_campaign(spec, sample_time)
    base = load_document(args.config) if args.config else None
    drive_cfg = drive_cfg.model_copy(update={"mode": mode})
    with _target(args, config, emulator_config, drive_cfg.node_id) as target:
        drive = _open_drive(target, drive_cfg, sample_time)
        with drive:  # safe stop and close on every exit path
            drive.connect()
            operation = OperationMode.CYCLIC_SYNC_TORQUE if mode == "cst" else OperationMode.CYCLIC_SYNC_VELOCITY
            drive.configure(operation)
            drive.enable()
            with step("identification: step tests", total=int(command.shape[0])) as advance:
                record = identify.run_campaign(
                    drive,
                    command,
                    sample_time=sample_time,
                    output_limit=output_limit,
                    feedback_timeout=max(0.5, 20 * sample_time),
                    progress=lambda done, _total: advance(done),
                )
            drive.disable()
    fit = identify.fit_model(record, args.model)
    uncertainty = identify.uncertainty_bounds(fit, margin=args.uncertainty_margin)
    campaign = identify.CampaignSummary(
        mode=mode,
        spec=spec,
        cycles=int(command.shape[0]),
        sample_time=sample_time,
        output_quantum=1.0 / drive_cfg.velocity_scale,
        max_abs_output=float(np.max(np.abs(record.output))),
    )
    document = identify.identification_document(fit, uncertainty, campaign)
    if args.out:
        fragment = identify.fragment_document(document, sample_time, base)
        header = (
            f"# written by `foilc-hil commission identify` ({fit.kind}, {mode}, R^2 = {fit.r2:.5f});\n"
            "# plant.a/b/c/num/den/delay/uncertainty identified, other sections from --config\n"
        )
        try:
            Path(args.out).write_text(header + yaml.safe_dump(fragment, sort_keys=False), encoding="utf-8")
        except OSError as exc:
            raise InputError(f"--out: cannot write {args.out}: {exc}") from exc
    if args.plot:
        identify.plot_fit(record, fit, args.plot)
    document["out"] = args.out
    document["plot"] = args.plot
    return CommandResult(document, _render_identify(document))


def _campaign_spec(args: argparse.Namespace, drive_cfg: DriveConfig, mode: str) -> CampaignSpec:
    """The identification campaign from the command line (defaults per mode), options checked."""
    from foilc_hil.commission.identify import CampaignSpec

    for option, value in (("--hold", args.hold), ("--rest", args.rest), ("--output-limit", args.output_limit)):
        _positive(value, option)
    if not (math.isfinite(args.uncertainty_margin) and args.uncertainty_margin >= 1):
        raise InputError(f"--uncertainty-margin: must be >= 1, got {args.uncertainty_margin}")
    limit = drive_cfg.torque_limit if mode == "cst" else drive_cfg.velocity_limit
    if args.amplitudes:
        try:
            amplitudes = tuple(float(x) for x in args.amplitudes.split(",") if x.strip())
        except ValueError:
            raise InputError(f"--amplitudes: {args.amplitudes!r} is not a comma-separated list of numbers") from None
    else:
        amplitudes = tuple(f * limit for f in ((0.02, 0.04) if mode == "cst" else (0.1, 0.2, 0.3)))
    return CampaignSpec(
        amplitudes=amplitudes,
        hold=args.hold if args.hold is not None else (0.2 if mode == "cst" else 1.0),
        rest=args.rest if args.rest is not None else 1.0,
        repetitions=args.repetitions,
        limit=limit,
        pattern="doublet" if mode == "cst" else "pulse",
    )


def _render_identify(document: dict[str, Any]) -> str:
    fit = document["fit"]
    plant = document["plant"]
    unc = document["uncertainty"]
    lines = [
        f"model {fit['model']}: " + ", ".join(
            f"{k} = {v:.6g} +- {fit['standard_errors'][k]:.2g}" for k, v in fit["parameters"].items()
        ),
        f"G(s) = {plant['num']} / {plant['den']}" + (f" * exp(-{plant['delay']:.4g} s)" if plant["delay"] else ""),
        f"fit: R^2 = {fit['r2']:.5f}, residual std {fit['residual_std']:.4g}",
        f"{'step':>4} {'from':>10} {'to':>10} {'R^2':>8} {'NRMSE':>8}  per-step parameters",
    ]
    for number, step in enumerate(fit["steps"]):
        params = ", ".join(f"{k} {v:.5g}" for k, v in step["parameters"].items())
        lines.append(f"{number:>4} {step['from']:>10.4g} {step['to']:>10.4g} {step['r2']:>8.4f} "
                     f"{step['nrmse']:>8.4f}  {params}" + ("" if step["converged"] else "  (not converged)"))
    unsettled = sum(1 for step in fit["steps"] if not step["converged"])
    if unsettled or not fit["converged"]:
        lines.append(
            f"warning: {'the joint fit and ' if not fit['converged'] else ''}{unsettled} of {len(fit['steps'])} "
            "single-step fits stopped at the solver's evaluation limit: their parameters, and the uncertainty "
            "built from them, are not reliable (a model with more poles than the data shows? try --model "
            "first-order)"
        )
    lines.append(
        f"uncertainty (discrete, Ts = {document['campaign']['sample_time']}): rho_A = {unc['rho_A']:.3g} "
        f"(observed {unc['observed_max_dA']:.3g}), rho_B = {unc['rho_B']:.3g} (observed {unc['observed_max_dB']:.3g})"
    )
    if document.get("out"):
        lines.append(f"plant section written to {document['out']}")
    if document.get("plot"):
        lines.append(f"plot written to {document['plot']}")
    return "\n".join(lines)
