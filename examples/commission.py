"""Commission a CiA 402 drive from a script: scan the bus, connect, read and write objects over SDO by name,
enable, and disable with the confirmed-stop report.

By default it talks to the embedded emulator (an emulated drive in this process, from the config's ``plant:`` and
``drive:``); ``--bus socketcan:can0`` talks to a real bus. Uses only the documented API (docs/api.md)::

    python examples/commission.py
    python examples/commission.py --config configs/demo.yaml --bus socketcan:can0 --nodes 1-8
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Sequence

import drivers
import foilc_hil as fh
from plant_emulator import EmbeddedEmulator


def node_range(text: str) -> range:
    """``"1-8"`` -> node ids 1..8."""
    low, _, high = text.partition("-")
    return range(int(low), int(high or low) + 1)


def commission(config: fh.Config, bus_config: drivers.BusConfig, nodes: range, listen: float) -> drivers.StopReport:
    """Scan, connect, SDO by name, enable, confirmed stop; print each step."""
    with drivers.open_bus(bus_config) as bus:
        network = drivers.DriveNetwork(bus)
        try:
            found = network.scan(nodes, listen=listen)
            for node in found.nodes:
                print(f"found node {node.node_id}: profile {node.profile}, NMT {node.nmt_state}, "
                      f"vendor 0x{node.vendor_id or 0:08X}, found by {', '.join(node.found_by)}")
            drive = drivers.Cia402Drive.on_network(network, config.drive, sample_time=config.sample_time)
            try:
                info = drive.connect()
                print(f"connected to node {info.node_id}: product 0x{info.product_code:X}, "
                      f"modes {[mode.name for mode in info.supported_modes]}")
                print(f"statusword 0x{drive.read_object('Statusword'):04X}, "
                      f"serial {drive.read_object('Identity object', 'Serial number')}")
                drive.write_object("Producer heartbeat time", 0, 250)
                print(f"producer heartbeat time now {drive.read_object(0x1017)} ms")
                drive.configure(config.drive.operation_mode)
                drive.enable()
                print(f"enabled: statusword 0x{drive.read_object('Statusword'):04X}")
                report = drive.safe_stop()
                state = report.state.name if report.state is not None else "unknown"
                print(f"stop: {'confirmed' if report.confirmed else 'NOT confirmed'}, {state}, "
                      f"statusword 0x{report.statusword or 0:04X}")
                return report
            finally:
                drive.close()
        finally:
            network.close()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/demo.yaml", help="the drive: and plant: to use")
    parser.add_argument("--bus", default=None, metavar="INTERFACE:CHANNEL", help="a real bus (default: embedded)")
    parser.add_argument("--nodes", default="1-8", help="node ids to scan, e.g. 1-8")
    parser.add_argument("--listen", type=float, default=0.3, help="seconds to listen for heartbeats")
    args = parser.parse_args(argv)
    config = fh.load_config(args.config)
    with contextlib.ExitStack() as stack:
        if args.bus is None:
            emulator = stack.enter_context(EmbeddedEmulator.from_config(config))
            bus_config = emulator.bus_config
        else:
            interface, _, channel = args.bus.partition(":")
            bus_config = drivers.BusConfig(interface=interface, channel=channel)
        report = commission(config, bus_config, node_range(args.nodes), args.listen)
    return 0 if report.confirmed else 1


if __name__ == "__main__":
    raise SystemExit(main())
