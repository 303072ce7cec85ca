"""SYNC from a process of its own: :class:`ProcessSync` and the producer it runs (``python -m drivers.sync_process``).

A SYNC producer thread (:class:`drivers.sync_clock.SyncProducer`) shares the bench's interpreter: when a SYNC is
due it first waits for the GIL, which the loop, the receive thread or the log's feeder may hold, and its SYNCs were
2-3x later than python-can's ``send_periodic`` under the same privileges. Across processes (``udp_multicast``) the
bench's SYNC therefore comes from a child process with an interpreter of its own that does nothing else:

- it sleeps to absolute deadlines ``t0 + k * period`` on ``CLOCK_MONOTONIC`` with ``clock_nanosleep(TIMER_ABSTIME)``
  (no drift from relative sleeps), and sends one prepared SYNC frame on its own bus object on the same channel;
- a wake-up later than a whole period (the host stalled it) sends ONE late SYNC for the latest slot passed and
  counts the others as skipped, never a burst, as the thread does; the bench's loop, however late, never delays it;
- its host setup is the bench loop's, one step up: started from a SCHED_FIFO loop thread it runs SCHED_FIFO one
  priority above it (the loop's priority plus one), with its memory locked, timer slack 1 ns and the garbage
  collector frozen; it starts with normal scheduling (its interpreter's start-up must not hold a FIFO CPU) and
  raises itself once ready;
- it dies with the bench: it checks that its parent is still the one that started it at start-up and after every
  wake-up, and exits when not (re-parented: the bench is gone), so even a SIGKILL of the bench leaves no orphan
  sending SYNC (at most the one SYNC of the slot it woke up for); before ``go`` the end of its stdin ends it;
- it sends under the channel's frame order (:mod:`drivers.send_order`), as every bus :func:`drivers.bus.open_bus`
  opens on it does: a SYNC and the bench's RPDO sent within microseconds reach every receiver in one order. Not
  ``PR_SET_PDEATHSIG``: Linux sends that signal when the *thread* that started the child ends, not the process,
  so a producer started from a thread that then finished (the network listening from a worker thread) was
  SIGKILLed mid-run by itself -- ``killed by signal 9`` with the bench alive.

Supervision (:class:`ProcessSync`, the bench's side): the network starts the child when it starts listening (its
interpreter's start-up, about 0.3 s and seconds on a loaded host, must not fall between the loop's last SYNC and
the clock's first: the drives' SYNC supervision would see the gap). The child opens its bus and says ``ready`` on
stdout, then waits; :meth:`ProcessSync.start` hands it the period and priority on its stdin, it applies its settings
and says ``started``, and the bench runs on the SYNCs it reads from the bus, counting each as it sees its echo, as
with the kernel's broadcast manager. A child that exits is a fault like any other:
:attr:`ProcessSync.error` names its exit status and last words, which :meth:`drivers.network.DriveNetwork.await_sync`
raises at once, and the loop then stops the drive and reads its state back. :meth:`ProcessSync.stop` (SIGTERM, then
SIGKILL) returns only once the child is gone, so no SYNC goes out after it.

Child's command line: ``python -m drivers.sync_process --parent PID --interface I --channel C [--port P]``; on its
stdin, ``go PERIOD FIFO`` (FIFO 0: normal scheduling).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import gc
import math
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any

from drivers.errors import DriveError
from drivers.sync_clock import SyncRecord

__all__ = ["READY_TIMEOUT", "ProcessSync", "main"]

READY_TIMEOUT = 30.0
"""Seconds the bench waits for the producer's ``ready`` (its interpreter's start-up and python-can's import: about
0.3 s on a quiet host, several on a loaded one)."""
STOP_TIMEOUT = 2.0  # s a SIGTERMed producer has to exit before it is killed
_PR_SET_TIMERSLACK = 29  # <linux/prctl.h>
_MCL_CURRENT, _MCL_FUTURE = 1, 2  # <sys/mman.h>
_TIMER_ABSTIME = 1  # <time.h>
_EINTR = 4


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class ProcessSync:
    """The bench's handle of a SYNC producer process (module docstring); a :class:`drivers.sync_clock.SyncClock`.

    Parameters
    ----------
    interface, channel
        The bus the producer opens its own bus object on (python-can's names).
    period
        Seconds between SYNCs.
    port
        ``udp_multicast``'s UDP port (python-can's default when None).
    """

    name = "process"

    def __init__(self, interface: str, channel: str, *, port: int | None = None) -> None:
        command = [sys.executable, "-m", "drivers.sync_process", "--parent", str(os.getpid()), "--interface",
                   interface, "--channel", channel, *(["--port", str(port)] if port is not None else [])]
        # started with normal scheduling whatever the calling thread's: see the module docstring
        self._process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                         text=True, preexec_fn=_normal_scheduling, close_fds=True)
        self.pid = self._process.pid
        self.period = math.nan  # until start()
        self._t0 = math.nan  # the producer's first deadline, perf_counter seconds (after start())
        self.settings = ""  # the producer's line on what it applied, after start()
        self.summary = ""  # the producer's closing line (SYNCs sent, slots skipped, sends unordered), after stop()
        self._error: str | None = None
        self._expect("ready")

    def start(self, period: float) -> None:
        """SYNC every ``period`` seconds from one period from now, at the calling thread's SCHED_FIFO priority plus
        one (normal scheduling when it has none)."""
        if not (period > 0 and math.isfinite(period)):
            raise ValueError(f"period must be a positive number of seconds, got {period!r}")
        stdin = self._process.stdin
        assert stdin is not None
        fifo = _fifo_priority()
        try:
            stdin.write(f"go {period!r} {fifo + 1 if fifo is not None else 0}\n")
            stdin.flush()
        except OSError:
            raise DriveError(f"the SYNC producer process is gone: {self.error}") from None
        self.period = float(period)
        self.settings = self._expect("started")
        words = dict(word.split("=", 1) for word in self.settings.split() if "=" in word)
        self._t0 = int(words["t0"]) / 1e9  # CLOCK_MONOTONIC: time.perf_counter's clock on Linux

    def slot_of(self, seen: float) -> float:
        """The deadline (``perf_counter`` seconds) of the slot a SYNC received at ``seen`` was sent in: the last one of
        the producer's grid ``t0 + k * period`` at or before it (a SYNC goes out after its deadline, and less than
        a period after, or its slot is skipped)."""
        return self._t0 + math.floor((seen - self._t0) / self.period + 1e-9) * self.period

    def _expect(self, word: str) -> str:
        """The producer's next line, which must begin with ``word`` (bounded by :data:`READY_TIMEOUT`)."""
        stdout = self._process.stdout
        assert stdout is not None
        ready, _, _ = select.select([stdout], [], [], READY_TIMEOUT)
        line = stdout.readline() if ready else ""
        if not line.startswith(word):
            self.stop()
            raise DriveError(f"the SYNC producer process did not start: {self.error or 'it said ' + repr(line)}")
        return line.strip()

    @property
    def error(self) -> str | None:
        """None while the producer runs; else its exit status and its last stderr line."""
        if self._error is not None:
            return self._error
        code = self._process.poll()
        if code is None:
            return None
        stderr = self._process.stderr
        said = stderr.read().strip().splitlines() if stderr is not None and not stderr.closed else []
        how = f"killed by signal {-code}" if code < 0 else f"exit {code}"
        self._error = f"the SYNC producer process (pid {self.pid}) ended: {how}" + (f": {said[-1]}" if said else "")
        return self._error

    def record(self, number: int) -> SyncRecord | None:
        return None  # its deadlines are in another process: the bench takes each SYNC's time from its echo

    def next_due(self, number: int) -> float | None:
        return None

    def stop(self) -> None:
        """Stop the producer (idempotent): SIGTERM, SIGKILL after :data:`STOP_TIMEOUT`; it is gone on return."""
        process = self._process
        with contextlib.suppress(OSError):
            if process.stdin is not None:
                process.stdin.close()  # a producer not started yet reads the end of its input and exits
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            if not _exited_within(process.pid, STOP_TIMEOUT):
                process.kill()
            process.wait()
        with contextlib.suppress(OSError, ValueError):
            if process.stdout is not None and not process.stdout.closed:
                self.summary = process.stdout.read().strip() or self.summary
                process.stdout.close()
            if process.stderr is not None:
                process.stderr.close()


def _exited_within(pid: int, timeout: float) -> bool:
    """Whether child ``pid`` exits within ``timeout`` seconds, known the moment it does (a pidfd polled by
    ``select``). Why not ``Popen.wait(timeout)``: it polls with sleeps doubling up to 50 ms, and the producer's exit
    took 7.5-8.6 ms to be seen that way, a gap in SYNC before the drive's stop sends its own."""
    try:
        fd = os.pidfd_open(pid)
    except (OSError, AttributeError):  # gone already, or no pidfd (Linux < 5.3): Popen's own wait decides
        return True
    try:
        return bool(select.select([fd], [], [], timeout)[0])
    finally:
        os.close(fd)


def _fifo_priority() -> int | None:
    """The calling thread's SCHED_FIFO priority, or None under normal scheduling."""
    with contextlib.suppress(OSError):
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            return int(os.sched_getparam(0).sched_priority)
    return None


def _normal_scheduling() -> None:
    """In the forked child before exec: back to SCHED_OTHER (a child inherits its creator thread's policy)."""
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


# --- the producer process ------------------------------------------------------------------------------------------


def _libc() -> Any:
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def _require_parent(parent: int) -> None:
    """Exit now if the parent that started us is gone (we were re-parented)."""
    if os.getppid() != parent:
        raise SystemExit(f"sync_process: parent {parent} is gone")


def _prepare(libc: Any) -> list[str]:
    """The host setup that takes time, done before ``ready`` (memory locked: faulting every page in took tens of
    milliseconds, which fell between the loop's last SYNC and the clock's first); one line per step not applied."""
    gc.collect()
    gc.freeze()
    gc.disable()
    libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(1), 0, 0, 0)
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        return [f"mlockall: {os.strerror(ctypes.get_errno())}"]
    return []


def _raise_priority(fifo: int | None) -> list[str]:
    """SCHED_FIFO at ``fifo`` (None: normal scheduling kept); one line when refused."""
    if fifo is None:
        return []
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo))
    except OSError as exc:
        return [f"SCHED_FIFO {fifo}: {exc.strerror}"]
    return []


def _serve(bus: Any, period_ns: int, t0: int, libc: Any, stopped: list[int], parent: int) -> tuple[int, int]:
    """Send SYNC on absolute deadlines ``t0 + k period_ns`` (CLOCK_MONOTONIC ns) until SIGTERM or until ``parent``
    is no longer ours (the bench died); (SYNCs sent, slots skipped)."""
    import can

    from drivers.cia301 import SYNC_COB_ID

    message = can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)
    send, clock, parent_now = bus.send, time.clock_gettime_ns, os.getppid
    deadline = _Timespec()
    sleep = libc.clock_nanosleep
    index = sent = skipped = 0
    while not stopped:
        due = t0 + index * period_ns
        deadline.tv_sec, deadline.tv_nsec = divmod(due, 1_000_000_000)
        while sleep(time.CLOCK_MONOTONIC, _TIMER_ABSTIME, ctypes.byref(deadline), None) == _EINTR:
            if stopped:
                return sent, skipped
        if parent_now() != parent:  # re-parented: the bench is gone, and nobody may be left sending SYNC
            return sent, skipped
        late = clock(time.CLOCK_MONOTONIC) - due
        if late >= period_ns:  # a stall: one late SYNC for the latest slot passed, the others skipped
            passed = late // period_ns
            index += passed
            skipped += passed
        send(message)
        sent += 1
        index += 1
    return sent, skipped


def main(argv: Sequence[str] | None = None) -> int:
    """The producer process (module docstring): open the bus, say ``ready``, wait for ``go PERIOD FIFO`` on stdin
    (FIFO 0: normal scheduling), say ``started``, send SYNC until SIGTERM, say how many."""
    parser = argparse.ArgumentParser(prog="python -m drivers.sync_process")
    parser.add_argument("--parent", type=int, required=True)
    parser.add_argument("--interface", required=True)
    parser.add_argument("--channel", required=True)
    parser.add_argument("--port", type=int)
    args = parser.parse_args(argv)
    libc = _libc()
    _require_parent(args.parent)
    stopped: list[int] = []
    signal.signal(signal.SIGTERM, lambda *_: stopped.append(1))
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C reaches the whole group: the bench stops us itself
    import can

    options = {"port": args.port} if args.port is not None else {}
    with can.Bus(interface=args.interface, channel=args.channel, **options) as bus:
        from drivers.receive_filter import install_id_filter
        from drivers.send_order import order_multicast_sends

        order = order_multicast_sends(bus)  # the bench's RPDOs and this SYNC: one order for every receiver
        install_id_filter(bus, ())  # it sends only: the bus's frames are dropped before they queue on its socket
        prepared = _prepare(libc)
        print("ready", flush=True)
        words = sys.stdin.readline().split()  # the end of input (the bench stopped us first): words == []
        if stopped or len(words) != 3 or words[0] != "go":
            return 0
        period, fifo = float(words[1]), int(words[2]) or None
        problems = [*(prepared if fifo is not None else []), *_raise_priority(fifo)]  # asked for realtime: all
        period_ns = round(period * 1e9)
        t0 = time.clock_gettime_ns(time.CLOCK_MONOTONIC) + period_ns
        print("started", f"t0={t0}", f"fifo={fifo}", *(f"not applied: {p}" for p in problems), flush=True)
        sent, skipped = _serve(bus, period_ns, t0, libc, stopped, args.parent)
        unordered = order.unordered if order is not None else sent
        print(f"sent {sent} skipped {skipped} unordered {unordered}", flush=True)
        # gone at once: the bench waits for this exit before its drives' stop sends SYNC again, and an interpreter's
        # teardown (the bus shut down, modules freed) took longer under load than the drives' SYNC-loss time (100
        # periods: 0.2 s at 2 ms); the kernel closes the socket
        os._exit(0)


if __name__ == "__main__":
    raise SystemExit(main())
