"""Bus specs, opening buses with clear errors, simulated-bus detection and the frame tap."""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path

import can
import pytest

from drivers.bus import FrameTap, is_simulated_bus, open_bus, parse_bus_spec
from drivers.config import BusConfig
from foilc_hil.errors import DriveError, InputError


@pytest.mark.parametrize(
    ("spec", "interface", "channel"),
    [
        ("socketcan:vcan0", "socketcan", "vcan0"),
        ("virtual:bench", "virtual", "bench"),
        ("udp_multicast:239.74.163.2", "udp_multicast", "239.74.163.2"),
        ("pcan:PCAN_USBBUS1", "pcan", "PCAN_USBBUS1"),
        ("virtual:a:b", "virtual", "a:b"),  # only the first colon separates
    ],
)
def test_parse_bus_spec(spec: str, interface: str, channel: str) -> None:
    cfg = parse_bus_spec(spec, bitrate=500_000)
    assert (cfg.interface, cfg.channel, cfg.bitrate) == (interface, channel, 500_000)


@pytest.mark.parametrize("spec", ["vcan0", "socketcan:", ":vcan0", "", "embedded:x"])
def test_bad_bus_spec_names_the_option(spec: str) -> None:
    with pytest.raises(InputError, match=r"^--bus: "):
        parse_bus_spec(spec)


def test_simulated_interfaces() -> None:
    assert is_simulated_bus("virtual") and is_simulated_bus("udp_multicast") and is_simulated_bus("embedded")
    assert not is_simulated_bus("socketcan") and not is_simulated_bus("pcan")


def test_open_virtual_bus() -> None:
    bus = open_bus(BusConfig(interface="virtual", channel=f"test-bus-{uuid.uuid4()}"))
    try:
        assert isinstance(bus, can.BusABC)
    finally:
        bus.shutdown()


def test_open_missing_socketcan_interface_says_how_to_create_it() -> None:
    if Path("/sys/class/net/nosuchcan0").exists():
        pytest.skip("an interface named nosuchcan0 exists here")
    with pytest.raises(DriveError, match="ip link add dev nosuchcan0 type vcan"):
        open_bus(BusConfig(interface="socketcan", channel="nosuchcan0"))


def test_unknown_interface_is_input_error() -> None:
    with pytest.raises(InputError, match="not available in python-can"):
        open_bus(BusConfig(interface="no_such_interface", channel="x"))


def test_frame_tap_sees_tx_and_rx_including_periodic_tasks() -> None:
    channel = f"test-tap-{uuid.uuid4()}"
    ours, theirs = can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)
    tap = FrameTap()
    seen: list[tuple[int, str]] = []
    lock = threading.Lock()

    def listener(msg: can.Message, direction: str) -> None:
        with lock:
            seen.append((msg.arbitration_id, direction))

    def broken(msg: can.Message, direction: str) -> None:
        raise RuntimeError("a broken logger must not break the bus")

    tap.add_listener(listener)
    tap.add_listener(broken)
    tap.attach(ours)
    notifier = can.Notifier(ours, [tap], timeout=0.05)
    try:
        ours.send(can.Message(arbitration_id=0x201, data=b"\x01", is_extended_id=False))
        theirs.send(can.Message(arbitration_id=0x181, data=b"\x02", is_extended_id=False))
        task = ours.send_periodic(can.Message(arbitration_id=0x77F, data=b"\x05", is_extended_id=False), 0.01)
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            with lock:
                if (0x181, "rx") in seen and seen.count((0x77F, "tx")) >= 2:
                    break
            time.sleep(0.01)
        task.stop()
        received = theirs.recv(0.5)
        assert received is not None and received.arbitration_id == 0x201  # the wrapped send still sends
        with lock:
            assert (0x201, "tx") in seen
            assert (0x181, "rx") in seen
            assert seen.count((0x77F, "tx")) >= 2
        assert tap.listener_errors >= 3
        tap.remove_listener(listener)
        tap.detach()
        count = len(seen)
        ours.send(can.Message(arbitration_id=0x202, data=b"", is_extended_id=False))
        assert len(seen) == count  # detached: no more tx reports
        assert "send" not in vars(ours)
    finally:
        notifier.stop()
        ours.shutdown()
        theirs.shutdown()
