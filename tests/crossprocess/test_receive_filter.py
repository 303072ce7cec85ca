"""A drive's receive path sees only its own COB-IDs, dropped below Python (:mod:`drivers.receive_filter`).

The BPF program is run two ways: by a small classic-BPF interpreter here on python-can's own ``pack_message`` bytes
(every id encoding msgpack gives: fixint, uint8, uint16, uint32; a layout python-can does not write passes), and
attached to a real ``udp_multicast`` socket inside a private network namespace this test creates, where the kernel
drops the foreign datagrams (counted in the socket's drops) and ``recv`` returns only the wanted ones.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import can
import pytest
from can.interfaces.udp_multicast.utils import pack_message

from drivers.receive_filter import UDP_HEADER, FilteredNetwork, FilterKind, install_id_filter, udp_id_filter
from tests.support.netns import NETNS_SETUP, unshare_available

ROOT = Path(__file__).resolve().parents[2]
WANTED = (0x000, 0x080, 0x201, 0x601, 0x12345678)
OTHERS = (0x7F, 0x100, 0x181, 0x202, 0x281, 0x581, 0x701, 0x12345679)


def _run_bpf(program: list[tuple[int, int, int, int]], packet: bytes) -> int:
    """Classic BPF as the kernel runs a socket filter (only the opcodes the program uses); a load past the end
    returns 0, as the kernel's does."""
    a, pc = 0, 0
    while True:
        code, jt, jf, k = program[pc]
        if code in (0x30, 0x28, 0x20):  # ld b/h/w abs
            size = {0x30: 1, 0x28: 2, 0x20: 4}[code]
            if k + size > len(packet):
                return 0
            a = int.from_bytes(packet[k:k + size], "big")
        elif code == 0x15:  # jeq k
            pc += jt if a == k else jf
        elif code == 0x35:  # jge k
            pc += jt if a >= k else jf
        elif code == 0x06:  # ret k
            return k
        else:
            raise AssertionError(f"opcode {code:#x} not interpreted")
        pc += 1


def _datagram(can_id: int) -> bytes:
    message = can.Message(arbitration_id=can_id, data=b"\x01\x02", is_extended_id=can_id > 0x7FF)
    return bytes(UDP_HEADER) + pack_message(message)


def test_the_program_passes_the_wanted_ids_and_drops_the_others_in_every_msgpack_encoding() -> None:
    program = udp_id_filter(WANTED)
    for can_id in WANTED:
        assert _run_bpf(program, _datagram(can_id)) > 0, hex(can_id)
    for can_id in OTHERS:
        assert _run_bpf(program, _datagram(can_id)) == 0, hex(can_id)


def test_a_datagram_of_another_layout_is_passed_to_python_not_lost() -> None:
    program = udp_id_filter(WANTED)
    message = can.Message(arbitration_id=0x181, data=b"")
    message.timestamp = 5  # an int timestamp: msgpack writes a fixint, and every offset after it moves
    assert _run_bpf(program, bytes(UDP_HEADER) + pack_message(message)) > 0
    assert _run_bpf(program, bytes(UDP_HEADER) + b"\x80" * 60) > 0  # not python-can's at all


def test_an_empty_set_drops_every_frame_and_too_many_ids_are_refused() -> None:
    assert _run_bpf(udp_id_filter(()), _datagram(0x80)) == 0
    with pytest.raises(ValueError, match="at most 200"):
        udp_id_filter(range(201))


def test_a_network_refilters_on_every_subscription_and_other_buses_stay_unfiltered() -> None:
    with can.Bus(interface="virtual", channel="filter-test") as bus:
        assert install_id_filter(bus, WANTED) is FilterKind.NONE  # python-can's virtual: nothing below Python
        network = FilteredNetwork(bus)
        canopen_own = tuple(sorted(network.subscribers))  # canopen's own (LSS) from its construction
        installed: list[tuple[int, ...]] = []
        network._refilter = lambda: installed.append(tuple(sorted(network.subscribers)))  # type: ignore[method-assign]
        network.subscribe(0x80, lambda *a: None)
        network.subscribe(0x201, lambda *a: None)
        network.unsubscribe(0x80)
        assert installed == [tuple(sorted({*canopen_own, *ids})) for ids in ((0x80,), (0x80, 0x201), (0x201,))]


_SOCKET_CHECK = """
import os, sys, time, can
from drivers.receive_filter import FilterKind, install_id_filter
group, wanted, others = sys.argv[1], [int(x) for x in sys.argv[2].split(",")], [int(x) for x in sys.argv[3].split(",")]
tx, rx = can.Bus(interface="udp_multicast", channel=group), can.Bus(interface="udp_multicast", channel=group)
assert install_id_filter(rx, wanted) is FilterKind.BPF
for can_id in [*others, *wanted]:
    tx.send(can.Message(arbitration_id=can_id, data=b"\\x01", is_extended_id=can_id > 0x7FF))
time.sleep(0.2)
got = []
while (m := rx.recv(0.2)) is not None:
    got.append(m.arbitration_id)
inode = os.fstat(rx.fileno()).st_ino
drops = [int(f.split()[-1]) for f in list(open("/proc/net/udp"))[1:] if int(f.split()[9]) == inode][0]
tx.shutdown(); rx.shutdown()
print(",".join(map(str, got)), drops)
"""


@pytest.mark.netns
@pytest.mark.slow
def test_the_kernel_drops_foreign_datagrams_on_a_real_socket() -> None:
    reason = unshare_available()
    if reason is not None:
        pytest.skip(reason)
    command = shlex.join([sys.executable, "-c", _SOCKET_CHECK, "239.74.163.11", ",".join(map(str, WANTED)),
                          ",".join(map(str, OTHERS))])
    result = subprocess.run(["unshare", "--net", "--", "sh", "-c", f"{NETNS_SETUP}; {command}"], capture_output=True,
                            text=True, timeout=120, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    got, drops = result.stdout.split()
    assert [int(x) for x in got.split(",")] == list(WANTED)  # every wanted one, in order, and nothing else
    assert int(drops) == len(OTHERS)  # each foreign datagram dropped by the socket's filter, in the kernel


def test_socketcan_filters_are_the_kernels_can_raw_filter() -> None:
    if "vcan0" not in os.listdir("/sys/class/net"):
        pytest.skip("no vcan0 here (this kernel has no SocketCAN): the CAN_RAW_FILTER path is not run")
    with can.Bus(interface="socketcan", channel="vcan0") as bus:
        assert install_id_filter(bus, WANTED) is FilterKind.CAN_RAW_FILTER
        # python-can does not filter again in Python
        assert bus._is_filtered is True  # type: ignore[attr-defined]
