"""The four-axis realtime benchmark's per-axis figures on synthetic frames whose answers and losses are known by
construction (no process, no bus: the analysis alone)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks.realtime_axes import SHORTEST_PERIOD, _axis_figures, _unanswered_periods, answer_times, realtime_config
from drivers.cia301 import SYNC_COB_ID, FunctionCode, cob_id
from foilc_hil.commands.run import check_bus_load
from foilc_hil.config import load_config
from foilc_hil.errors import ConfigError

PERIOD = 0.0025
NODES = (1, 2, 3, 4)


def _frames() -> tuple[np.ndarray, list[dict[str, object]]]:
    """Ten SYNCs; node k answers each ``100 k`` us after it, except node 3 at SYNC 4 (its TPDO1 never sent) and
    node 2 at SYNC 7 (sent and seen by the receiver, not logged by the bench); node 4's RPDO1 of SYNC 5 is lost."""
    received: list[tuple[int, float]] = []
    logged: list[dict[str, object]] = []
    for n in range(10):
        t = n * PERIOD
        received.append((SYNC_COB_ID, t))
        logged.append({"id": SYNC_COB_ID, "dir": "tx"})
        for node in NODES:
            rpdo = cob_id(FunctionCode.RPDO1, node)
            logged.append({"id": rpdo, "dir": "tx"})
            if not (node == 4 and n == 5):
                received.append((rpdo, t + 10e-6))
            if node == 3 and n == 4:
                continue
            received.append((cob_id(FunctionCode.TPDO1, node), t + node * 100e-6))
            if not (node == 2 and n == 7):
                logged.append({"id": cob_id(FunctionCode.TPDO1, node), "dir": "rx"})
    return np.array(received, dtype=float), logged


def test_answer_times_are_each_nodes_own_delay_after_the_sync() -> None:
    frames, _ = _frames()
    for node in NODES:
        answers = answer_times(frames, node)
        assert answers.size == (9 if node == 3 else 10)
        np.testing.assert_allclose(answers, node * 100e-6, atol=1e-12)


def test_losses_are_counted_on_the_right_axis_and_direction() -> None:
    frames, logged = _frames()
    figures = {node: _axis_figures(frames, logged, node) for node in NODES}
    assert [figures[n]["tpdo1_lost_to_bench"] for n in NODES] == [0, 1, 0, 0]
    assert [figures[n]["rpdo1_lost"] for n in NODES] == [0, 0, 0, 1]
    assert [figures[n]["rpdo1_sent_by_bench"] for n in NODES] == [10] * 4
    # node 3 unanswered at SYNC 4, node 2 unlogged at SYNC 7; the last period is cut by the run's end (not counted)
    assert [_unanswered_periods(logged, n) for n in NODES] == [0, 1, 1, 0]
    assert abs(figures[4]["emulator_answer_us"]["p50"] - 400.0) < 1e-6


def test_the_shortest_period_is_the_shortest_the_run_accepts(tmp_path: Path) -> None:
    """``--period`` at :data:`SHORTEST_PERIOD`: under the bus-load limit with a whole-sample trial; the next shorter
    whole-sample period (one sample more per trial) is refused by the bus-load check."""
    config = load_config(realtime_config(tmp_path, SHORTEST_PERIOD))
    assert config.sample_time == SHORTEST_PERIOD and config.bench.mode == "realtime"
    assert check_bus_load(config, config.bus).load == pytest.approx(0.6977, abs=1e-4)
    with pytest.raises(ConfigError, match=r"bus\.load_limit: refused"):
        check_bus_load(load_config(realtime_config(tmp_path, 0.5 / 243)), config.bus)
