"""The pieces of a several-axes run on their own: the composite drive's stop of every axis, and single-axis logs
having no axes (they keep reading as before)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import numpy as np
import pytest

from drivers.cia402 import State402
from drivers.drive import Feedback
from foilc_hil.errors import DriveError, FeedbackTimeoutError
from foilc_hil.io.mcap_log import read_log
from foilc_hil.logtools.axes import log_axes
from foilc_hil.loop.axes import AxisGroup, AxisLimiter
from foilc_hil.loop.rig import _commission
from foilc_hil.loop.safety import CommandLimiter

DATA = Path(__file__).resolve().parents[1] / "data"


class _Drive:
    def __init__(self, node_id: int, fails: bool = False) -> None:
        self.node_id = node_id
        self.fails = fails
        self.quick_stops = 0
        self.targets: list[float] = []

    def quick_stop(self) -> None:
        self.quick_stops += 1
        if self.fails:
            raise DriveError(f"node {self.node_id} did not answer")

    def set_target(self, value: float) -> float:
        self.targets.append(value)
        return round(value, 1)


def test_quick_stop_reaches_every_axis_even_when_one_fails() -> None:
    drives = [_Drive(1), _Drive(2, fails=True), _Drive(3), _Drive(4, fails=True)]
    with pytest.raises(DriveError, match="node 2"):  # the first failure, after every axis was tried
        AxisGroup(drives).quick_stop()
    assert [drive.quick_stops for drive in drives] == [1, 1, 1, 1]


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class _AnsweringDrive(_Drive):
    """Answers after ``delay`` seconds of the test's clock, or not at all (``delay`` None: waits out its timeout)."""

    def __init__(self, node_id: int, clock: _Clock, delay: float | None) -> None:
        super().__init__(node_id)
        self.clock, self.delay = clock, delay
        self.timeouts: list[float] = []

    def wait_feedback(self, timeout: float) -> Feedback:
        self.timeouts.append(timeout)
        if self.delay is None or self.delay > timeout:
            self.clock.now += timeout
            raise FeedbackTimeoutError(f"node {self.node_id}: no answer within {timeout} s")
        self.clock.now += self.delay
        return Feedback(cycle=7, statusword=0x0237, state=State402.OPERATION_ENABLED, velocity=float(self.node_id),
                        torque=0.0, position=0, timestamp=self.clock.now)


def test_feedback_waits_share_one_deadline_across_the_axes() -> None:
    clock = _Clock()
    drives = [_AnsweringDrive(1, clock, 0.4), _AnsweringDrive(2, clock, 0.3), _AnsweringDrive(3, clock, 0.0)]
    feedback = AxisGroup(drives, clock=clock).wait_feedback(1.0)
    assert feedback.velocity.tolist() == [1.0, 2.0, 3.0] and feedback.cycle == 7
    assert [drive.timeouts for drive in drives] == [[1.0], [pytest.approx(0.6)], [pytest.approx(0.3)]]
    # a late axis spends the group's time: the next waits get what is left (none), not a timeout of their own
    late = [_AnsweringDrive(1, clock, 0.2), _AnsweringDrive(2, clock, None), _AnsweringDrive(3, clock, 0.0)]
    start = clock.now
    with pytest.raises(FeedbackTimeoutError, match="node 2"):
        AxisGroup(late, clock=clock).wait_feedback(0.5)
    assert late[1].timeouts == [pytest.approx(0.3)] and clock.now == pytest.approx(start + 0.5)


def test_a_lost_axis_is_reported_with_every_other_axis_answer() -> None:
    """One axis's lost set must not hide the others' answers: the loop holds the lost axis alone."""
    from foilc_hil.loop.interfaces import AxesFeedbackLostError

    clock = _Clock()
    drives = [_AnsweringDrive(1, clock, 0.1), _AnsweringDrive(2, clock, None), _AnsweringDrive(3, clock, 0.0),
              _AnsweringDrive(4, clock, None)]
    with pytest.raises(AxesFeedbackLostError, match="node 2") as caught:
        AxisGroup(drives, clock=clock).wait_feedback(0.5)
    lost = caught.value
    assert isinstance(lost, FeedbackTimeoutError)  # the loop's lost-feedback path, and its watchdog, take it
    assert lost.lost.tolist() == [False, True, False, True]
    assert np.isnan(lost.velocity[[1, 3]]).all() and lost.velocity[[0, 2]].tolist() == [1.0, 3.0]
    assert [len(drive.timeouts) for drive in drives] == [1, 1, 1, 1]  # every axis was read


def test_set_target_sends_each_axis_its_own_command_or_one_for_all() -> None:
    drives = [_Drive(1), _Drive(2), _Drive(3)]
    group = AxisGroup(drives)
    assert group.set_target(np.array([1.04, -2.0, 3.26])).tolist() == [1.0, -2.0, 3.3]
    group.set_target(0.0)
    assert [drive.targets for drive in drives] == [[1.04, 0.0], [-2.0, 0.0], [3.26, 0.0]]


def test_the_limiter_clamps_each_axis_to_its_own_limits_and_counts_them() -> None:
    limiter = AxisLimiter([CommandLimiter(-1.0, 1.0), CommandLimiter(-5.0, 5.0)])
    assert limiter.clamp(np.array([2.0, 2.0])).tolist() == [1.0, 2.0]
    assert limiter.clamp(np.array([-7.0, -7.0])).tolist() == [-1.0, -5.0]
    assert limiter.clamped_count == 3


def test_a_single_axis_log_has_no_axes() -> None:
    contents = read_log(DATA / "run_layout1.mcap")
    assert contents.samples and log_axes(contents) == ()


class _CommissionedDrive:
    def __init__(self, node_id: int, calls: list[str]) -> None:
        self.node_id, self.calls = node_id, calls

    def connect(self) -> None:
        self.calls.append(f"connect {self.node_id}")

    def configure(self, mode: object) -> None:
        self.calls.append(f"configure {self.node_id}")

    def enable(self) -> None:
        self.calls.append(f"enable {self.node_id}")


class _Session:
    def __init__(self, calls: list[str]) -> None:
        self.calls = calls

    def __enter__(self) -> None:
        self.calls.append("realtime host setup")


def test_a_realtime_axes_run_enters_the_host_setup_once_every_receive_path_exists() -> None:
    """As for one axis: after every drive is connected (the network's CAN receive thread exists to be raised), and
    before any is configured (the drives supervise SYNC from then on: nothing slow may follow)."""
    calls: list[str] = []
    drives = [_CommissionedDrive(node, calls) for node in (1, 2)]
    axis = SimpleNamespace(config=SimpleNamespace(drive=SimpleNamespace(operation_mode="csv")))
    plan = cast(Any, SimpleNamespace(axes=[axis, axis], config=SimpleNamespace(sample_time=0.0025)))
    _commission(cast(Any, drives), plan, None, cast(Any, _Session(calls)))
    assert calls == ["connect 1", "connect 2", "realtime host setup", "configure 1", "configure 2", "enable 1",
                     "enable 2"]
