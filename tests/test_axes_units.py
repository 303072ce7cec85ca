"""The pieces of a several-axes run on their own: the composite drive's stop of every axis, and single-axis logs
having no axes (they keep reading as before)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from foilc_hil.errors import DriveError
from foilc_hil.io.mcap_log import read_log
from foilc_hil.logtools.axes import log_axes
from foilc_hil.loop.axes import AxisGroup, AxisLimiter
from foilc_hil.loop.safety import CommandLimiter

DATA = Path(__file__).resolve().parent / "data"


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
