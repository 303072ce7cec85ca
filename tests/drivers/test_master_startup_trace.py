"""The master's start-up, frame by frame: what a CiA 402 master says to a drive before the first cycle.

Read :data:`EXPECTED` top to bottom: it is the whole conversation of ``connect()``, ``configure(CSV, 2 ms)`` and
``enable()`` with drive node 5 (master node 127, drive heartbeat 100 ms, drive watching the master at 200 ms),
captured with the master's frame tap and decoded by :func:`tests.support.can_trace.describe_frame`. Heartbeats (the
drive's and the master's) are periodic and interleave at random; they are left out, except the boot-up. Run with ``-s``
to see the table of frames.
"""

from __future__ import annotations

import threading
import uuid

import can

from drivers.cia301 import FunctionCode, NmtState, cob_id
from drivers.cia402 import OperationMode
from drivers.cia402_master import Cia402Drive
from tests.support.can_trace import describe_frame
from tests.support.mini_servo import NODE_ID, MiniServo, drive_config

Line = tuple[str, str]  # (direction, meaning)


def download(where: str, value: str) -> list[Line]:
    """An expedited SDO write and the drive's acknowledgement."""
    return [("tx", f"SDO download {where} = {value}"), ("rx", f"SDO download ack {where}")]


def upload(where: str, value: str) -> list[Line]:
    """An expedited SDO read and the drive's reply."""
    return [("tx", f"SDO upload {where}"), ("rx", f"SDO upload reply {where} = {value}")]


def pdo(com: int, cob: int, entries: list[str]) -> list[Line]:
    """CiA 301 PDO reconfiguration: disable (bit 31), transmission type 1 (SYNC), clear, map, count, enable."""
    mapping = com + 0x200
    lines = download(f"0x{com:04X}:01", f"0x{0x8000_0000 | cob:08X}")
    lines += download(f"0x{com:04X}:02", "0x01")
    lines += download(f"0x{mapping:04X}:00", "0x00")
    for sub, entry in enumerate(entries, start=1):
        lines += download(f"0x{mapping:04X}:{sub:02X}", entry)
    lines += download(f"0x{mapping:04X}:00", f"0x{len(entries):02X}")
    lines += download(f"0x{com:04X}:01", f"0x{cob:08X}")
    return lines


def verify_pdo(com: int, cob: int, entries: list[str]) -> list[Line]:
    """Read back what :func:`pdo` wrote: COB-ID, transmission type, count, entries."""
    mapping = com + 0x200
    lines = upload(f"0x{com:04X}:01", f"0x{cob:08X}") + upload(f"0x{com:04X}:02", "0x01")
    lines += upload(f"0x{mapping:04X}:00", f"0x{len(entries):02X}")
    for sub, entry in enumerate(entries, start=1):
        lines += upload(f"0x{mapping:04X}:{sub:02X}", entry)
    return lines


def step(controlword: int, statusword: int) -> list[Line]:
    """One lockstep cycle: RPDO1 (controlword, target velocity 0), SYNC, the drive's TPDO1 and TPDO2."""
    return [
        ("tx", f"RPDO1 node 5 6040=0x{controlword:04X} 60FF=0"),
        ("tx", "SYNC"),
        ("rx", f"TPDO1 node 5 6041=0x{statusword:04X} 606C=0"),
        ("rx", "TPDO2 node 5 6077=0 6064=0"),
    ]


RPDO1_MAP = ["0x60400010", "0x60FF0020"]  # controlword, target velocity (CSV)
TPDO1_MAP = ["0x60410010", "0x606C0020"]  # statusword, velocity actual value
TPDO2_MAP = ["0x60770010", "0x60640020"]  # torque actual value, position actual value

EXPECTED: list[Line] = [
    # --- connect(): known communication state, identity --------------------------------------------------------
    ("tx", "NMT reset communication node 5"),
    ("rx", "boot-up node 5"),
    ("tx", "NMT enter pre operational node 5"),
    *upload("0x1000:00", "0x00020192"),  # device type: CiA 402, servo
    *upload("0x1018:01", "0x464F494C"),  # vendor id
    *upload("0x1018:02", "0x00000402"),  # product code
    *upload("0x1018:03", "0x00010000"),  # revision
    *upload("0x1018:04", "0x00000001"),  # serial number
    *upload("0x6502:00", "0x00000304"),  # supported drive modes: pv, csv, cst
    # --- configure(CSV, 2 ms): PDOs, mode, timing, heartbeats -------------------------------------------------
    ("tx", "NMT enter pre operational node 5"),
    *pdo(0x1400, 0x205, RPDO1_MAP),
    *download("0x1401:01", "0x80000305"),  # RPDO2..4 unused: disabled
    *download("0x1402:01", "0x80000405"),
    *download("0x1403:01", "0x80000505"),
    *pdo(0x1800, 0x185, TPDO1_MAP),
    *pdo(0x1801, 0x285, TPDO2_MAP),
    *download("0x1802:01", "0x80000385"),  # TPDO3..4 unused: disabled
    *download("0x1803:01", "0x80000485"),
    *download("0x6060:00", "0x09"),  # modes of operation: cyclic synchronous velocity
    *download("0x605A:00", "0x0002"),  # quick stop option: quick stop ramp, then disable
    *download("0x6007:00", "0x0003"),  # abort connection option: quick stop
    *download("0x1006:00", "0x000007D0"),  # communication cycle period 2000 us
    *download("0x1017:00", "0x0064"),  # drive heartbeat every 100 ms
    *download("0x1016:01", "0x007F00C8"),  # drive watches node 127 (the master) with 200 ms
    # read back everything written
    *verify_pdo(0x1400, 0x205, RPDO1_MAP),
    *verify_pdo(0x1800, 0x185, TPDO1_MAP),
    *verify_pdo(0x1801, 0x285, TPDO2_MAP),
    *upload("0x6060:00", "0x09"),
    *upload("0x605A:00", "0x0002"),
    *upload("0x6007:00", "0x0003"),
    *upload("0x1006:00", "0x000007D0"),
    *upload("0x1017:00", "0x0064"),
    *upload("0x1016:01", "0x007F00C8"),
    *upload("0x6061:00", "0x09"),  # modes of operation display confirms the mode
    ("tx", "NMT start node 5"),
    # --- enable(): CiA 402 state machine through the RPDO, one SYNC per step ----------------------------------
    *step(0x0000, 0x0240),  # disable voltage        -> SWITCH ON DISABLED
    *step(0x0006, 0x0231),  # shutdown               -> READY TO SWITCH ON
    *step(0x0007, 0x0233),  # switch on              -> SWITCHED ON
    *step(0x000F, 0x0237),  # enable operation       -> OPERATION ENABLED
]


def is_periodic_heartbeat(msg: can.Message) -> bool:
    return msg.arbitration_id & 0x780 == FunctionCode.HEARTBEAT and bytes(msg.data) != bytes(
        [NmtState.INITIALISING]
    )


def test_startup_trace_matches_the_documented_sequence() -> None:
    channel = f"test-trace-{uuid.uuid4()}"
    servo = MiniServo(channel)
    bus = can.Bus(interface="virtual", channel=channel)
    frames: list[tuple[can.Message, str]] = []
    lock = threading.Lock()

    def record(msg: can.Message, direction: str) -> None:
        with lock:
            frames.append((msg, direction))

    drive = Cia402Drive.open(bus, drive_config(), sample_time=0.002)
    try:
        drive.add_frame_listener(record)
        drive.connect()
        drive.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
        drive.enable()
        with lock:
            captured = [(m, d) for m, d in frames if not is_periodic_heartbeat(m)]
        heartbeats_sent = [m for m, d in frames if d == "tx" and is_periodic_heartbeat(m)]
        codecs = drive.pdo_codecs
    finally:
        drive.safe_stop()
        drive.close()
        bus.shutdown()
        servo.close()

    actual = [(direction, describe_frame(msg, codecs)) for msg, direction in captured]
    print(f"\n{'#':>3}  {'dir':3}  {'COB-ID':6}  {'data':23}  meaning")
    for n, ((msg, direction), (_, meaning)) in enumerate(zip(captured, actual, strict=True), start=1):
        print(f"{n:3}  {direction:3}  0x{msg.arbitration_id:03X}   {bytes(msg.data).hex(' '):23}  {meaning}")

    for n, (got, want) in enumerate(zip(actual, EXPECTED, strict=False), start=1):
        assert got == want, f"frame {n}: got {got}, expected {want}"
    assert len(actual) == len(EXPECTED), f"{len(actual)} frames, expected {len(EXPECTED)}"
    # the master's own heartbeat (node 127, operational) runs from configure() on
    assert heartbeats_sent and all(m.arbitration_id == cob_id(FunctionCode.HEARTBEAT, 127) for m in heartbeats_sent)
    assert all(bytes(m.data) == bytes([NmtState.OPERATIONAL]) for m in heartbeats_sent)
    assert NODE_ID == 5  # the literal COB-IDs above are for node 5
