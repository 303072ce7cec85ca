"""The SYNC producer process (:mod:`drivers.sync_process`): supervised like any child of the bench.

Its life cycle on python-can's ``virtual`` interface (in the child's own process it reaches nobody: nothing leaves it):
ready, stopped with SIGTERM and gone on return with its count; a child that dies is an error the bench raises at once
with its exit status; a SIGKILLed parent leaves no orphan, and a producer started from a thread outlives that thread.
Its SYNCs on a real ``udp_multicast`` bus, in a private network namespace this test creates: they come on their period's
grid (counted in slots, no time bound asserted), and a run stopped by the child's death ends with the drive confirmed
stopped (``tests/crossprocess/test_latched_crossprocess.py`` runs the whole bench on it).
"""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from drivers.errors import DriveError
from drivers.sync_process import ProcessSync
from tests.support.netns import NETNS_SETUP, unshare_available

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def _gone(pid: int, within: float = 30.0) -> bool:
    """True once ``pid`` no longer exists (a zombie of ours counts as gone: it sends nothing)."""
    end = time.monotonic() + within
    while True:  # looked at once at least
        try:
            with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
                if stat.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return True
        except FileNotFoundError:
            return True
        if time.monotonic() >= end:
            return False
        time.sleep(0.05)


def test_the_producer_starts_ready_and_is_gone_when_stop_returns() -> None:
    clock = ProcessSync("virtual", "sync-process-test")
    clock.start(0.002)
    try:
        assert clock.settings.startswith("started") and clock.error is None
        time.sleep(0.1)
    finally:
        clock.stop()
    assert _gone(clock.pid, within=0.0)  # stop() waited for it
    assert clock.summary.startswith("sent ") and int(clock.summary.split()[1]) > 0
    clock.stop()  # idempotent


def test_a_producer_that_dies_is_an_error_naming_how() -> None:
    clock = ProcessSync("virtual", "sync-process-test")
    clock.start(0.002)
    try:
        os.kill(clock.pid, signal.SIGKILL)
        assert _gone(clock.pid)
        assert clock.error is not None and "killed by signal 9" in clock.error
        assert clock.error == clock.error  # the same words every time it is asked
    finally:
        clock.stop()


def test_a_producer_never_started_exits_when_stopped() -> None:
    clock = ProcessSync("virtual", "sync-process-test")
    clock.stop()
    assert _gone(clock.pid, within=0.0) and clock.summary == ""  # it sent nothing


def test_a_producer_that_cannot_open_its_bus_fails_the_start() -> None:
    with pytest.raises(DriveError, match="did not start"):
        ProcessSync("no-such-interface", "x")


def test_a_producer_started_from_a_thread_outlives_that_thread() -> None:
    """The network may listen (and start its producer) on a worker thread that then ends; the producer is the
    bench's, not that thread's (``PR_SET_PDEATHSIG`` killed it when the thread ended)."""
    clocks: list[ProcessSync] = []
    spawner = threading.Thread(target=lambda: clocks.append(ProcessSync("virtual", "sync-process-test")))
    spawner.start()
    spawner.join()
    (clock,) = clocks
    try:
        clock.start(0.002)  # raised DriveError: the producer was gone
        assert clock.error is None
    finally:
        clock.stop()
    assert clock.summary.startswith("sent ")


_PARENT = """
import sys, time
from drivers.sync_process import ProcessSync
clock = ProcessSync("virtual", "orphan-test")
clock.start(0.002)
print(clock.pid, flush=True)
time.sleep(600)
"""


def test_a_sigkilled_parent_leaves_no_orphan() -> None:
    parent = subprocess.Popen([sys.executable, "-c", _PARENT], stdout=subprocess.PIPE, text=True, cwd=ROOT,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert parent.stdout is not None
    child = int(parent.stdout.readline())
    try:
        assert not _gone(child, within=0.0)
        parent.kill()
        parent.wait()
        assert _gone(child), f"the SYNC producer {child} outlived its SIGKILLed parent"
    finally:
        parent.kill()
        if not _gone(child, within=0.0):  # only the producer this test's parent started, by its id
            os.kill(child, signal.SIGKILL)


_ON_THE_BUS = """
import sys, can
from drivers.sync_process import ProcessSync
group, period = sys.argv[1], float(sys.argv[2])
listener = can.Bus(interface="udp_multicast", channel=group)
clock = ProcessSync("udp_multicast", group)
clock.start(period)
stamps = []
while len(stamps) < 200:
    m = listener.recv(5.0)
    assert m is not None, "no SYNC within 5 s"
    if m.arbitration_id == 0x80:
        stamps.append(m.timestamp)
clock.stop()
listener.shutdown()
print(" ".join(repr(s) for s in stamps), "|", clock.summary)
"""


@pytest.mark.netns
@pytest.mark.slow
def test_its_syncs_reach_the_bus_on_their_period_grid() -> None:
    reason = unshare_available()
    if reason is not None:
        pytest.skip(reason)
    period = 0.002
    command = shlex.join([sys.executable, "-c", _ON_THE_BUS, "239.74.163.12", repr(period)])
    result = subprocess.run(["unshare", "--net", "--", "sh", "-c", f"{NETNS_SETUP}; {command}"], capture_output=True,
                            text=True, timeout=300, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    stamps_text, summary = result.stdout.split("|")
    stamps = [float(s) for s in stamps_text.split()]
    # at most one SYNC a slot, whatever the host's load: a SYNC is late by less than a period or its slot is skipped,
    # so the count between the first and the last is below their distance in periods plus one (a burst of catch-up
    # SYNCs after a stall would exceed it)
    assert len(stamps) - 1 < (stamps[-1] - stamps[0]) / period + 1
    assert summary.split()[0] == "sent"
