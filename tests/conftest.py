"""Shared test settings.

Hypothesis runs without per-example deadlines: these machines are shared and noisy, and a deadline is a timing
assertion in disguise. Under CI (``CI`` set) examples are derandomised so a run is reproducible.
"""

from __future__ import annotations

import contextlib
import gc
import os
import sys
import threading
import time
import weakref
from collections.abc import Iterator
from typing import Any

import can
import pytest
from hypothesis import settings

settings.register_profile("default", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")


# --- leak guard ---------------------------------------------------------------------------------------------------
# Every test must leave no open bus, no thread and no file descriptor behind (python-can's own test suite checks
# buses the same way): a leaked Notifier or emulator thread keeps running into the next test and makes faults there
# irreproducible, and a leaked bus keeps receiving frames forever.

_LIVE_BUSES: weakref.WeakSet[can.BusABC] = weakref.WeakSet()
_original_bus_init = can.BusABC.__init__


def _tracking_bus_init(self: can.BusABC, *args: Any, **kwargs: Any) -> None:
    _original_bus_init(self, *args, **kwargs)
    _LIVE_BUSES.add(self)


can.BusABC.__init__ = _tracking_bus_init  # type: ignore[method-assign]

#: how long a test's threads may take to finish after it returned (Notifier threads poll their bus)
_THREAD_GRACE_S = 5.0


def _open_fds() -> set[int]:
    return {int(name) for name in os.listdir("/proc/self/fd")} if os.path.isdir("/proc/self/fd") else set()


def _stopped_periodic_task(thread: threading.Thread) -> bool:
    """A python-can ``send_periodic`` thread whose task was stopped: python-can does not wake it, so it sleeps out
    its period (up to a heartbeat's second) and then ends without sending. Waiting for it would only cost time."""
    task = getattr(getattr(thread, "_target", None), "__self__", None)
    return isinstance(task, can.broadcastmanager.CyclicSendTaskABC) and getattr(task, "stopped", False) is True


def _leaked_threads(before: set[threading.Thread]) -> list[threading.Thread]:
    deadline = time.monotonic() + _THREAD_GRACE_S
    while True:
        leaked = [t for t in threading.enumerate()
                  if t not in before and t.is_alive() and not _stopped_periodic_task(t)
                  and not t.name.startswith(_LIBRARY_THREADS)]
        if not leaked or time.monotonic() > deadline:
            return leaked
        time.sleep(0.01)


#: Process-wide thread pools a library starts once and keeps for the life of the process (not a test's leak):
#: dask.distributed's offload executor (`distributed.utils._offload_executor`), started by the first in-process
#: cluster of a worker process.
_LIBRARY_THREADS = ("Dask-Offload",)
_LIBRARY_DATA = (sys.prefix, sys.base_prefix, "/usr/share/")


def _leaked_fds(before: set[int]) -> list[str]:
    """Descriptors opened during the test and still open, by target; collected garbage first (only when needed:
    a full collection per test is slow). Files of the Python installation and the system's shared data are library
    caches, not leaks of the test: matplotlib keeps the font it loaded open, its own copy or, depending on its font
    cache, the system's (/usr/share/fonts)."""
    if not _open_fds() - before:
        return []
    gc.collect()
    leaked = []
    for fd in sorted(_open_fds() - before):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/self/fd/{fd}")
            if not target.startswith(_LIBRARY_DATA):
                leaked.append(target)
    return leaked


@pytest.fixture(autouse=True)
def no_leaks(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail a test that leaves a bus open, a thread running or a file descriptor open."""
    threads_before = set(threading.enumerate())
    buses_before = set(_LIVE_BUSES)
    fds_before = _open_fds()
    yield
    open_buses = [bus for bus in _LIVE_BUSES if bus not in buses_before and not bus._is_shutdown]
    for bus in open_buses:
        bus.shutdown()  # do not let one leak cascade into the next test
    leaked_threads = _leaked_threads(threads_before)
    leaked_fds = _leaked_fds(fds_before)
    problems = []
    if open_buses:
        problems.append(f"{len(open_buses)} bus(es) not shut down: {[b.channel_info for b in open_buses]}")
    if leaked_threads:
        problems.append(f"threads still running: {[t.name for t in leaked_threads]}")
    if leaked_fds:
        problems.append(f"file descriptors left open: {leaked_fds}")
    if problems:
        pytest.fail(f"{request.node.nodeid} leaks: " + "; ".join(problems), pytrace=False)
