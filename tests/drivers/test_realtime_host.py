"""The host setup of a realtime run (drivers.realtime): applied, reported, restored; a refusal is reported."""

from __future__ import annotations

import gc
import os
import sys
import threading
from pathlib import Path

import pytest

from drivers import realtime
from drivers.realtime import HELPER_PRIORITY_OFFSET, GcPolicy, RealtimeConfig, RealtimeSession


def _fifo_permitted() -> bool:
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        return False
    os.sched_setscheduler(0, before[0], before[1])
    return True


@pytest.mark.slow
def test_gc_and_switch_interval_are_set_for_the_session_and_restored() -> None:
    interval = sys.getswitchinterval()
    assert gc.isenabled()
    with RealtimeSession(RealtimeConfig(gc=GcPolicy.FREEZE, switch_interval=0.0003)) as session:
        assert not gc.isenabled()
        assert gc.get_freeze_count() > 0
        assert sys.getswitchinterval() == pytest.approx(0.0003)
        assert session.report is not None
        assert session.report.gc == "frozen" and session.report.switch_interval == pytest.approx(0.0003)
    assert gc.isenabled() and gc.get_freeze_count() == 0
    assert sys.getswitchinterval() == interval


def test_sessions_of_several_threads_restore_the_switch_interval_whatever_order_they_end_in() -> None:
    """An emulator's motion threads (one per drive) each hold a session, and they end in any order: the process's
    switch interval is the one from before the first, after the last (it was the ended session's value)."""
    interval = sys.getswitchinterval()
    first = RealtimeSession(RealtimeConfig(switch_interval=0.0002)).__enter__()
    second = RealtimeSession(RealtimeConfig(switch_interval=0.0002)).__enter__()
    first.__exit__(None, None, None)
    assert sys.getswitchinterval() == pytest.approx(0.0002)  # the second session still holds it
    second.__exit__(None, None, None)
    assert sys.getswitchinterval() == interval


def test_sessions_of_several_threads_keep_the_collector_frozen_until_the_last_one_ends() -> None:
    """The collector is the process's too: the first of two overlapping sessions to end left it enabled (and
    unfrozen) under the other, whose cycles it was frozen for."""
    assert gc.isenabled()
    first = RealtimeSession(RealtimeConfig(gc=GcPolicy.FREEZE, switch_interval=None)).__enter__()
    second = RealtimeSession(RealtimeConfig(gc=GcPolicy.FREEZE, switch_interval=None)).__enter__()
    first.__exit__(None, None, None)
    assert not gc.isenabled() and gc.get_freeze_count() > 0  # the second session still holds it
    second.__exit__(None, None, None)
    assert gc.isenabled() and gc.get_freeze_count() == 0


@pytest.mark.slow
def test_the_timer_slack_is_one_nanosecond_in_the_session_and_restored() -> None:
    before = realtime._timer_slack()
    if before is None:
        pytest.skip("prctl(PR_GET_TIMERSLACK) is not available here")
    with RealtimeSession(RealtimeConfig()) as session:
        assert realtime._timer_slack() == 1
        assert session.report is not None and session.report.timer_slack_ns == 1
    assert realtime._timer_slack() == before


@pytest.mark.skipif(not _fifo_permitted(), reason="this host does not permit SCHED_FIFO (the refusal is tested above)")
def test_a_drive_physics_session_keeps_the_other_drives_physics_threads_cyclic() -> None:
    """Several drives in one process: each physics thread enters its session in turn; a later one must not demote
    the earlier ones (plant_emulator.motion.physics_session)."""
    from plant_emulator.motion import PHYSICS_THREAD_PREFIX, physics_session

    release, entered = [threading.Event(), threading.Event()], [threading.Event(), threading.Event()]
    before = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority

    def physics(k: int) -> None:
        with physics_session(RealtimeConfig(sched_fifo_priority=30, gc="on", switch_interval=None)):
            entered[k].set()
            release[k].wait(10)

    threads = [threading.Thread(target=physics, args=(k,), name=f"{PHYSICS_THREAD_PREFIX}-{k + 1}") for k in (0, 1)]
    try:
        threads[0].start()
        assert entered[0].wait(10)
        threads[1].start()
        assert entered[1].wait(10)
        for thread in threads:  # both at the cyclic priority: the second session left the first one's alone
            assert thread.native_id is not None
            assert os.sched_getparam(thread.native_id).sched_priority == 30, thread.name
    finally:
        for k in (1, 0):  # in reverse: each session restores the scheduling it found (this thread's too)
            release[k].set()
            threads[k].join()
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before


@pytest.mark.slow
def test_a_refused_fifo_is_reported_and_normal_scheduling_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(pid: int, policy: int, param: os.sched_param) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(realtime.os, "sched_setscheduler", refuse)
    with RealtimeSession(RealtimeConfig(sched_fifo_priority=50)) as session:
        report = session.report
        assert report is not None
        assert report.scheduler == "SCHED_OTHER" and report.fifo_threads == ()
        assert any("sched_fifo_priority 50" in line and "not permitted" in line for line in report.not_applied)
        assert report.to_json()["not_applied"] == list(report.not_applied)


@pytest.mark.skipif(not _fifo_permitted(), reason="this host does not permit SCHED_FIFO (the refusal is tested above)")
def test_fifo_for_the_cyclic_threads_and_below_for_the_helpers_then_restored() -> None:
    release = threading.Event()
    seen: dict[str, tuple[int, int]] = {}

    def helper() -> None:
        release.wait(10)

    def started_by_the_cyclic_thread() -> None:
        realtime.demote_current_thread()
        seen["child"] = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority

    worker = threading.Thread(target=helper, name="helper")
    worker.start()
    try:
        before = os.sched_getscheduler(0)
        with RealtimeSession(RealtimeConfig(sched_fifo_priority=30), cyclic_threads=[]) as session:
            assert os.sched_getscheduler(0) == os.SCHED_FIFO and os.sched_getparam(0).sched_priority == 30
            assert worker.native_id is not None
            assert os.sched_getscheduler(worker.native_id) == os.SCHED_FIFO
            assert os.sched_getparam(worker.native_id).sched_priority == 30 - HELPER_PRIORITY_OFFSET
            child = threading.Thread(target=started_by_the_cyclic_thread)  # inherits priority 30
            child.start()
            child.join()
            assert session.report is not None and session.report.scheduler == "SCHED_FIFO 30"
            assert session.report.fifo_threads == (threading.current_thread().name,)
        assert seen["child"] == (os.SCHED_FIFO, 30 - HELPER_PRIORITY_OFFSET)
        assert os.sched_getscheduler(0) == before
        assert os.sched_getscheduler(worker.native_id) == before
    finally:
        release.set()
        worker.join()


@pytest.mark.slow
def test_affinity_is_set_and_restored_and_a_bad_cpu_is_reported() -> None:
    before = os.sched_getaffinity(0)
    cpu = min(before)
    with RealtimeSession(RealtimeConfig(cpus=[cpu])) as session:
        assert os.sched_getaffinity(0) == {cpu}
        assert session.report is not None and session.report.cpus == (cpu,)
    assert os.sched_getaffinity(0) == before
    with RealtimeSession(RealtimeConfig(cpus=[4096])) as session:
        assert session.report is not None and any(line.startswith("cpus [4096]") for line in session.report.not_applied)
        assert os.sched_getaffinity(0) == before


def _latency_requests_held() -> int:
    """This process's open files on the PM QoS device (each one a request the kernel holds)."""
    fds = Path("/proc/self/fd")
    return sum(1 for fd in fds.iterdir() if os.path.realpath(fd) == realtime.CPU_LATENCY_DEVICE)


def _latency_device_usable() -> bool:
    try:
        os.close(os.open(realtime.CPU_LATENCY_DEVICE, os.O_WRONLY))
    except OSError:
        return False
    return True


@pytest.mark.slow
@pytest.mark.skipif(not _latency_device_usable(), reason=f"{realtime.CPU_LATENCY_DEVICE} cannot be opened here "
                    "(no PM QoS device, or not root): the refusal is tested below")
def test_the_cpu_latency_request_is_in_force_for_the_session_and_dropped_after() -> None:
    before = _latency_requests_held()
    with RealtimeSession(RealtimeConfig(cpu_latency_us=0)) as session:
        # the kernel's aggregate (the lowest request of all processes) is what reading the device gives
        with open(realtime.CPU_LATENCY_DEVICE, "rb") as device:
            in_force = int.from_bytes(device.read(4), sys.byteorder, signed=True)
        assert in_force == 0
        assert _latency_requests_held() == before + 1
        assert session.report is not None and session.report.cpu_latency_us == 0
        assert session.report.to_json()["cpu_latency_us"] == 0 and session.report.not_applied == ()
    assert _latency_requests_held() == before


@pytest.mark.slow
def test_a_refused_cpu_latency_request_is_reported(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(realtime, "CPU_LATENCY_DEVICE", str(tmp_path / "no-such-device"))
    with RealtimeSession(RealtimeConfig(cpu_latency_us=0)) as session:
        report = session.report
        assert report is not None and report.cpu_latency_us is None
        assert [line for line in report.not_applied if line.startswith("cpu_latency_us 0:")] == [
            f"cpu_latency_us 0: {tmp_path / 'no-such-device'}: No such file or directory"
        ]
    with RealtimeSession(RealtimeConfig()) as session:  # not asked: neither held nor reported
        assert session.report is not None and session.report.cpu_latency_us is None
        assert not any("cpu_latency" in line for line in session.report.not_applied)


def test_exiting_a_session_never_entered_changes_nothing() -> None:
    interval = sys.getswitchinterval()
    RealtimeSession(RealtimeConfig(sched_fifo_priority=10, lock_memory=True)).__exit__(None, None, None)
    assert gc.isenabled() and sys.getswitchinterval() == interval


# --- the emulator's SYNC-loss supervision: time it could not watch does not count --------------------------------


class _Node:
    alive = True
    link = None

    def __init__(self) -> None:
        from drivers.cia301 import NmtState

        self.nmt_state = NmtState.OPERATIONAL


class _Pdos:
    def send_event_driven(self, timer_only: bool = False) -> None:
        pass


class _ScriptedPolls:
    """The supervisor's ``stop``: each wait moves the fake monotonic clock to the next scripted poll time."""

    def __init__(self, clock: list[float], polls: list[float]) -> None:
        self.clock = clock
        self.polls = list(polls)

    def wait(self, timeout: float) -> bool:
        if not self.polls:
            return True
        self.clock[0] = self.polls.pop(0)
        return False


def _losses(polls: list[float]) -> list[tuple[float, object]]:
    from plant_emulator.supervision import Supervisor

    clock = [0.0]
    losses: list[tuple[float, object]] = []
    supervisor = Supervisor(
        _Node(),  # type: ignore[arg-type]
        threading.RLock(),
        _Pdos(),  # type: ignore[arg-type]
        on_loss=lambda kind: losses.append((clock[0], kind)),
        cycle_period=lambda: 0.001,
        sync_loss_cycles=100,  # 0.1 s
        clock=lambda: clock[0],
    )
    supervisor.sync_received()  # at t = 0
    supervisor.run(_ScriptedPolls(clock, polls))  # type: ignore[arg-type]
    return losses


def test_sync_loss_is_reported_one_timeout_after_the_last_sync() -> None:
    from plant_emulator.application import FaultKind

    polls = [0.002 * k for k in range(1, 80)]  # regular polls up to 0.158 s
    assert _losses(polls) == [(pytest.approx(0.102), FaultKind.SYNC_LOSS)]


def test_a_stall_of_the_emulator_itself_restarts_the_sync_loss_timer() -> None:
    from plant_emulator.application import FaultKind

    # polled regularly to 10 ms, then this process is stalled for half a second (SYNCs may be waiting unread)
    polls = [0.002 * k for k in range(1, 6)] + [0.5 + 0.002 * k for k in range(0, 80)]
    # no loss for the stall; a real one (no SYNC ever again) one timeout after the watch resumed
    assert _losses(polls) == [(pytest.approx(0.602), FaultKind.SYNC_LOSS)]
