"""``plant-emulator``: the virtual CiA 402 servo drive as a process on a CAN bus.

``plant-emulator --config C --bus SPEC [--node-id N[,N...]] [--mode lockstep|realtime]
[--inject KIND@cCYCLE[:K=V,...]]...``

It reads the bench's own config file but validates only the sections it uses -- ``plant``, ``emulator``,
``sample_time`` and ``drive`` (for ``node_id`` and the ``velocity_scale`` / ``torque_scale`` the master uses, so
both ends convert units alike) -- and ignores the rest, which the bench validates (layer 2 must not import the
whole-document model of layer 3). Without ``--config`` it drives a default PMSM axis. Bad input: exit 2 with one
line on stderr. It runs until SIGINT or SIGTERM (exit 0) and says so on stderr when it is ready; its last line
says how many SYNCs it served and the drive's final CiA 402 and NMT states.

``--node-id 1,2,3,4`` emulates several drives in the one process, one :class:`~plant_emulator.device.VirtualDrive`
per node, each with its own end of the one bus (a virtual drive takes its bus object over) and answering every
SYNC. A node that is an entry of the config's ``axes:`` list gets that axis's ``plant`` and ``drive`` sections
(where it gives them) and the seed ``plant.seed + emulator.seed`` of its own plant, exactly what a process of its
own (``--config`` of that axis alone) would build, so one process serves the same four axes as four processes do;
any other node has the top-level plant, the ``k``-th with the seed ``plant.seed + emulator.seed + k`` (the first
is the single-node one). It prints one ready line and one final line per node.

``--inject`` (repeatable, :mod:`drivers.faults`) injects faults on the drive's side for cross-process runs: the
emulator kinds (``emulator-kill``, ``emcy-over-current``, ...) and the bus kinds on its own bus (e.g. ``nmt-stop``
from a third party, ``drop-tpdo``). A process has no trials, so ``WHEN`` is ``cCYCLE``: the SYNCs it received.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType
from typing import TYPE_CHECKING, Any, NoReturn

from pydantic import ConfigDict, Field

from drivers.config import DriveConfig
from drivers.errors import ConfigError, ExitCode, InputError, ProductError
from drivers.faults import FaultyBus, Injection, Role, parse_injection, split_by_axis
from drivers.schema import Section, validate
from drivers.yaml_document import apply_overrides, load_document
from plant_emulator.config import PlantConfig
from plant_emulator.settings import EmulatorConfig

if TYPE_CHECKING:
    from plant_emulator.device import VirtualDrive

PROG = "plant-emulator"


class EmulatorAxis(Section):
    """The parts of one ``axes:`` entry the emulator uses (a section given replaces the top-level one)."""

    model_config = ConfigDict(extra="ignore", frozen=True, populate_by_name=True)

    node_id: int = Field(ge=1, le=127)
    plant: PlantConfig | None = None
    drive: DriveConfig | None = None


class EmulatorDocument(Section):
    """The parts of a bench config the emulator uses; every other section is ignored here."""

    model_config = ConfigDict(extra="ignore", frozen=True, populate_by_name=True)

    plant: PlantConfig = PlantConfig(model="pmsm")
    emulator: EmulatorConfig = EmulatorConfig()
    sample_time: float = Field(default=0.01, gt=0)
    drive: DriveConfig = DriveConfig()
    axes: tuple[EmulatorAxis, ...] = ()


class _OneLineParser(argparse.ArgumentParser):
    """argparse with its usage errors on one line and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(int(ExitCode.USAGE), f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``plant-emulator``."""
    parser = _OneLineParser(prog=PROG, description="A virtual CiA 402 servo drive (plant emulator) on a CAN bus.")
    parser.add_argument("--config", help="bench config file (YAML); uses plant, emulator, sample_time, drive")
    parser.add_argument("--bus", required=True, help="INTERFACE:CHANNEL, e.g. socketcan:vcan0, virtual:bench, "
                        "udp_multicast:239.74.163.2")
    parser.add_argument("--node-id", type=parse_node_ids, metavar="N[,N...]",
                        help="CANopen node id(s), e.g. 3 or 1,2,3,4 (default: drive.node_id, else 1)")
    parser.add_argument("--mode", choices=("lockstep", "realtime"), help="timing (default: emulator.timing)")
    parser.add_argument("--inject", action="append", default=[], metavar="KIND@cCYCLE[:K=V,...]",
                        help="inject a fault at the CYCLE-th SYNC received (repeatable), e.g. emulator-kill@c400, "
                        "nmt-stop@c300, drop-tpdo@c200:count=3")
    return parser


def parse_node_ids(text: str) -> tuple[int, ...]:
    """``"1,2,3,4"`` -> ``(1, 2, 3, 4)``: distinct node ids in 1..127 (argparse turns the error into exit 2)."""
    try:
        nodes = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of node ids") from None
    outside = [node for node in nodes if not 1 <= node <= 127]
    if outside:
        raise argparse.ArgumentTypeError(f"{outside[0]} is outside 1..127")
    if len(set(nodes)) != len(nodes):
        raise argparse.ArgumentTypeError(f"{text!r} repeats a node id")
    return nodes


def parse_injections(specs: Sequence[str]) -> list[Injection]:
    """The ``--inject`` specs; a trial-based ``WHEN`` is refused (exit 2): a drive's process knows no trials."""
    injections = [parse_injection(spec) for spec in specs]
    for spec, injection in zip(specs, injections, strict=True):
        if injection.trial is not None:
            raise InputError(f"--inject {spec}: {PROG} has no trials; give the SYNC count as KIND@cCYCLE")
    return injections


def load_settings(path: str | None, overrides: dict[str, Any]) -> EmulatorDocument:
    """The emulator's view of a config file (``None``: defaults), with dotted-key ``overrides`` on top."""
    document = load_document(path) if path is not None else {}
    if path is not None and "plant" not in document:
        document = {**document, "plant": {"model": "first_order"}}  # a file's default plant is the paper's model
    document = apply_overrides(document, overrides)
    return validate(EmulatorDocument, document, source=path or "")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the emulator until SIGINT/SIGTERM; return the process exit code."""
    args = build_parser().parse_args(argv)
    try:
        return _serve(args)
    except ProductError as exc:
        if isinstance(exc, ConfigError) and exc.key and not exc.source and args.config:
            exc = ConfigError(exc.message, key=exc.key, source=args.config)  # name the file it came from
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return int(exc.exit_code)


def _build_drives(settings: EmulatorDocument, nodes: tuple[int, ...]) -> list[VirtualDrive]:
    """One virtual drive per node id: an axis of ``axes:`` with its own plant and drive sections (module docstring),
    any other node the ``k``-th with the physics seed ``plant.seed + emulator.seed + k``."""
    from plant_emulator.device import VirtualDrive
    from plant_emulator.physics import build_plant

    axes = {axis.node_id: axis for axis in settings.axes}
    drives = []
    for k, node in enumerate(nodes):
        axis = axes.get(node)
        plant = axis.plant if axis is not None and axis.plant is not None else settings.plant
        drive = axis.drive if axis is not None and axis.drive is not None else settings.drive
        offset = 0 if axis is not None else k  # an axis's plant is seeded as in a process of its own
        drives.append(VirtualDrive(
            build_plant(plant, seed=plant.seed + settings.emulator.seed + offset),
            node_id=node,
            cycle_period=settings.sample_time,
            settings=settings.emulator,
            velocity_scale=drive.velocity_scale,
            torque_scale=drive.torque_scale,
        ))
    return drives


def _serve(args: argparse.Namespace) -> int:
    from drivers.bus import open_bus, parse_bus_spec

    injections = parse_injections(args.inject)
    nodes: tuple[int, ...] | None = args.node_id
    if nodes is not None and len(nodes) > 1 and injections:
        raise InputError(f"--inject: give one --node-id to inject faults into (got {len(nodes)} nodes)")
    settings = load_settings(args.config, {"drive.node_id": nodes[0] if nodes else None,
                                           "emulator.timing": args.mode})
    bus_cfg = parse_bus_spec(args.bus)
    drives = _build_drives(settings, nodes or (settings.drive.node_id,))
    split_by_axis(injections, [drive.node_id for drive in drives], key="--inject")  # an axis= of another node: exit 2
    stop = threading.Event()

    def _on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, _on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    faulty: FaultyBus | None = None
    try:
        for drive in drives:
            bus = open_bus(bus_cfg)
            if injections:
                from plant_emulator.faults import emulator_actions

                bus = faulty = FaultyBus(bus, injections, node_id=drive.node_id, role=Role.DRIVE,
                                         actions=emulator_actions(drive))
            drive.start(bus)
            print(
                f"{PROG}: ready: node {drive.node_id} on {bus_cfg.interface}:{bus_cfg.channel} "
                f"({settings.plant.model}, {drive.timing.value}, {settings.sample_time * 1e3:g} ms, receive filter "
                f"{drive.receive_filter})",
                file=sys.stderr,
                flush=True,
            )
        while not stop.wait(0.2):
            pass
    finally:
        for drive in drives:
            drive.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    for report in faulty.reports() if faulty is not None else []:
        started = "never started" if report.started_at_sync is None else f"started at SYNC {report.started_at_sync}"
        print(f"{PROG}: injected {report.injection.describe()}: {started}, {report.frames} frame(s)", file=sys.stderr)
    for drive in drives:
        late = f" ({drive.stale_syncs} handled a period late, unanswered)" if drive.stale_syncs else ""
        state = f"drive {drive.state.name}, NMT {drive.nmt_state.name}"
        print(f"{PROG}: stopped after {drive.sync_count} SYNC{late}; {state}"
              + (f" (node {drive.node_id})" if len(drives) > 1 else ""), file=sys.stderr, flush=True)
    return int(ExitCode.OK)


def run() -> None:
    """Console-script entry point."""
    sys.exit(main())
