"""A ``udp_multicast`` bus from :func:`drivers.bus.open_bus`, and the SYNC producer's, send under the channel's lock.

In a private network namespace this test creates: a bus opened by ``open_bus`` and one wrapped as the SYNC producer
wraps its own (``order_multicast_sends``) each send a frame with their socket's ``sendto`` replaced by a probe that
tries the channel's lock from a descriptor of its own. The try must be refused during every ``sendto`` (the frame
reaches every socket with the lock held), and the frames still arrive at a third bus. See :mod:`drivers.send_order`.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.netns import NETNS_SETUP, unshare_available

pytestmark = [pytest.mark.netns, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]

_CHECK = """
import fcntl, os, sys, can
from drivers.bus import open_bus
from drivers.config import BusConfig
from drivers.send_order import order_multicast_sends
group = sys.argv[1]
bench = open_bus(BusConfig(interface="udp_multicast", channel=group))
producer = can.Bus(interface="udp_multicast", channel=group)
order = order_multicast_sends(producer)
listener = can.Bus(interface="udp_multicast", channel=group)
held = []
for bus in (bench, producer):
    sock = bus._multicast
    real = sock.send
    def probe(data, timeout=None, real=real):
        fd = os.open(order.path, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held.append(False)
        except BlockingIOError:
            held.append(True)
        finally:
            os.close(fd)
        real(data, timeout)
    sock.send = probe
bench.send(can.Message(arbitration_id=0x201, data=b"\\x0f\\x00"))
producer.send(can.Message(arbitration_id=0x80, data=b""))
got = [listener.recv(2.0) for _ in range(2)]
print(",".join(str(h) for h in held), ",".join(hex(m.arbitration_id) for m in got if m is not None), order.unordered)
for bus in (bench, producer, listener):
    bus.shutdown()
"""


def test_both_senders_hold_the_channel_lock_during_every_sendto() -> None:
    reason = unshare_available()
    if reason is not None:
        pytest.skip(reason)
    command = shlex.join([sys.executable, "-c", _CHECK, "239.74.163.12"])
    result = subprocess.run(["unshare", "--net", "--", "sh", "-c", f"{NETNS_SETUP}; {command}"], capture_output=True,
                            text=True, timeout=120, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    held, arrived, unordered = result.stdout.split()
    assert held == "True,True"
    assert arrived == "0x201,0x80"
    assert unordered == "0"
