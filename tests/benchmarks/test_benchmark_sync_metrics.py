"""The realtime benchmark's SYNC statistics on synthetic receive times whose lateness is known by construction."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.realtime import LATENESS_WINDOW, answer_times, sync_statistics

PERIOD = 0.001


def test_lateness_and_empty_slots_under_clock_drift_and_a_phase_jump() -> None:
    slots = np.arange(3000)
    late = np.where(slots % 10 == 3, 300e-6, 0.0)  # every tenth SYNC 300 us late, the others on their slot
    phase = np.where(slots < 1500, 0.0, 0.0002)  # the grid jumps by 0.2 ms at slot 1500 (a start-up phase ends)
    times = 50.0 + slots * PERIOD * (1 + 3e-5) + late + phase  # the sender's clock runs 30 ppm fast
    keep = ~np.isin(slots, [700, 701, 702])  # three slots without a SYNC
    stats = sync_statistics(times[keep], PERIOD)
    assert stats["syncs"] == 2997
    assert stats["empty_slots"] == 3 and stats["intervals_over_1_5_periods"] == 1
    lateness = stats["lateness_us"]
    # the LATENESS_WINDOW SYNCs after the jump are judged against the earlier grid: 0.2 ms late, 0.5 ms if also
    # late themselves; the top 1 % is otherwise the tenth of SYNCs 0.3 ms late. Drift within a window: 30 ppm x
    # 1 ms x the window's width.
    drift = 3e-5 * PERIOD * (2 * LATENESS_WINDOW + 1) * 1e6
    assert lateness["max"] == pytest.approx(500.0, abs=drift + 1e-3)
    assert lateness["p99"] == pytest.approx(300.0, abs=drift + 1e-3)
    assert lateness["p50"] == pytest.approx(0.0, abs=drift + 1e-3)
    assert np.percentile(np.abs(np.diff(times[keep]) - PERIOD), 50) * 1e6 == pytest.approx(
        stats["interval_deviation_us"]["p50"]
    )


def test_answer_times_pair_each_sync_with_the_first_tpdo1_after_it() -> None:
    frames = np.array(
        [[0x80, 1.0], [0x181, 1.0002], [0x281, 1.0003], [0x181, 1.0004], [0x80, 1.001], [0x80, 1.002], [0x181, 1.0025]]
    )
    assert answer_times(frames) == pytest.approx([0.0002, 0.0005])


def test_host_floor_steal_share_and_the_estimate_from_half_period_wakeups() -> None:
    from benchmarks.host_floor import StealMeter
    from benchmarks.realtime import HOPS, _floor_lines

    # 30 of 1200 jiffies elapsed were stolen
    assert StealMeter(steal=130, total=1200).percent_since(StealMeter(steal=100, total=0)) == pytest.approx(2.5)
    assert StealMeter(steal=5, total=10).percent_since(StealMeter(steal=5, total=10)) is None
    floor = {"wakeups": 1000, "p50_us": 50.0, "p99_us": 900.0, "p99_9_us": 2000.0, "max_us": 5000.0,
             "over_500us_fraction": 0.1, "over_1000us_fraction": 0.01}
    (line,) = _floor_lines({"host_floor": floor, "steal_percent": 4.0})
    expected = 100 * (1 - 0.9**HOPS)  # independent hops, each late with probability 0.1
    assert f"about {expected:.1f} % of cycles" in line and "4.00 %" in line
    assert _floor_lines({}) == []


@pytest.mark.parametrize(("syncs_lost", "tpdo1_lost", "met"), [(0, 0, True), (20, -20, False), (0, 3, False)])
def test_no_frame_lost_is_judged_per_kind_never_summed(syncs_lost: int, tpdo1_lost: int, met: bool) -> None:
    """A receiver that missed 20 cycles (20 SYNCs not seen, 20 TPDO1 fewer than the bench logged) once read as
    "no frame lost": +20 and -20 summed to 0."""
    from benchmarks.realtime import targets

    stats = {"lateness_us": {"p99": 100.0}, "interval_deviation_us": {"p99": 100.0}}
    document = {"conditions": {"quiet": {
        "bench": {"exit_code": 0, "missed_deadline_fraction": 0.0,
                  "receiver": {**stats, "syncs_lost": syncs_lost, "tpdo1_lost_to_bench": tpdo1_lost}},
        "peers": [{"peer": peer, "sched_fifo": False, **stats} for peer in ("canopen", "python-can")],
    }}}
    (row,) = [row for row in targets(document) if row["target"].startswith("no frame lost")]
    assert row["met"] is met
    assert row["bench"] == f"{syncs_lost}, {tpdo1_lost}"


def test_privileged_peers_and_the_floor_say_which_pm_qos_request_they_held(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from benchmarks import realtime as bench_realtime
    from drivers import realtime as host_setup

    assert bench_realtime._privileges({"sched_fifo": False}) == ""
    assert bench_realtime._privileges({"sched_fifo": True}) == " (chrt -f 50)"  # a document from before the field
    assert bench_realtime._privileges({"sched_fifo": True, "cpu_latency_us": 0}) == " (chrt -f 50, PM QoS 0 us)"
    floor = {"wakeups": 10, "p50_us": 1.0, "p99_us": 2.0, "p99_9_us": 3.0, "max_us": 4.0,
             "over_500us_fraction": 0.0, "over_1000us_fraction": 0.0, "cpu_latency_us": 0}
    (line,) = bench_realtime._floor_lines({"host_floor": floor})
    assert "1 ms deadlines, PM QoS 0 us held, 10 wake-ups" in line
    with bench_realtime._privileged(False) as held:  # a user's plain start holds nothing
        assert bench_realtime._held_latency(held) is None
    # a host that refuses the request: the privileged run goes on without it, and its row says so
    monkeypatch.setattr(host_setup, "CPU_LATENCY_DEVICE", str(tmp_path / "no-such-device"))
    with bench_realtime._privileged(True) as held:
        assert bench_realtime._held_latency(held) is None


def test_the_latched_truth_check_reconstructs_each_sync_from_the_frames_it_saw() -> None:
    """SYNC 1, RPDO 100, SYNC 2, SYNC 3 (the RPDO of cycle 2 after it: missed), RPDO 200, RPDO 300, SYNC 4: the drive
    latched 100 at SYNCs 2 and 3, 300 at SYNC 4; a log saying otherwise at one sample is found there."""
    from types import SimpleNamespace

    import numpy as np

    from benchmarks.realtime import RPDO1_ID, SYNC_ID, latched_truth

    frames = np.array([(SYNC_ID, 0.0, 0), (RPDO1_ID, 0.1, 100), (SYNC_ID, 1.0, 0), (SYNC_ID, 2.0, 0),
                       (RPDO1_ID, 2.1, 200), (RPDO1_ID, 2.2, 300), (SYNC_ID, 3.0, 0)], dtype=float)
    trials = [{"trial": 1, "first_sync": 1}]
    rows = [{"trial": 1, "sample": i, "control": c, "latched": value}
            for i, (c, value) in enumerate([(0.1, 0.1), (0.2, 0.1), (0.3, 0.3)])]
    truth = latched_truth(frames, SimpleNamespace(trials=trials, samples=rows), 1000.0)
    assert truth == {"samples": 3, "agree": 3, "first_disagreement": None, "latched_not_command": 1}
    rows[1]["latched"] = 0.2  # the command, as if it had run
    truth = latched_truth(frames, SimpleNamespace(trials=trials, samples=rows), 1000.0)
    assert truth["agree"] == 2
    assert truth["first_disagreement"] == {"trial": 1, "sample": 1, "logged": 0.2, "on_wire": 0.1}


def test_missed_deadlines_are_judged_against_the_same_runs_host_floor() -> None:
    from benchmarks.realtime import HOPS, _issue28_rows, floor_estimate

    floor = {"over_500us_fraction": 0.01}
    bench: dict[str, Any] = {"missed_deadline_fraction": 0.05, "latched_truth": {"samples": 10, "agree": 10}}
    condition: dict[str, Any] = {"host_floor": floor, "bench": bench}
    estimate = 1 - 0.99**HOPS
    assert floor_estimate(condition) == pytest.approx(estimate)
    ratio_row, truth_row = _issue28_rows("load", condition)
    assert ratio_row["ratio"] == pytest.approx(0.05 / estimate) and ratio_row["met"] is (0.05 / estimate <= 2.0)
    assert truth_row["met"] is True and truth_row["bench"] == "10 of 10"
    bench["missed_deadline_fraction"] = 0.01
    assert _issue28_rows("load", condition)[0]["met"] is True
    assert _issue28_rows("quiet", {"bench": {"missed_deadline_fraction": 0.0}})[0]["met"] is False  # no floor


def test_the_alternated_producers_verdict_is_a_statistic_never_a_single_difference() -> None:
    from benchmarks.realtime import _issue28_rows, alternated_verdict

    # the bench earlier every round
    earlier: list[dict[str, float | None]] = [{"bench": 20.0 + k, "python-can": 40.0 + 3 * k} for k in range(6)]
    assert alternated_verdict(earlier)["verdict"] == "better"
    assert alternated_verdict(earlier)["median_ratio"] == pytest.approx(np.exp(np.median(
        [np.log((40.0 + 3 * k) / (20.0 + k)) for k in range(6)])))
    later: list[dict[str, float | None]] = [{"bench": p["python-can"], "python-can": p["bench"]} for p in earlier]
    assert alternated_verdict(later)["verdict"] == "worse"
    mixed = [*earlier[:3], *later[3:]]  # three rounds each way: a difference inside the noise, whatever the median
    assert alternated_verdict(mixed)["verdict"] == "inside the noise"
    assert alternated_verdict(earlier[:4])["verdict"] == "inside the noise"  # 4 rounds can never be significant
    assert alternated_verdict([{"bench": None, "python-can": 30.0}])["verdict"] == "not measured"
    condition: dict[str, Any] = {"bench": {"missed_deadline_fraction": 0.0},
                                 "alone": {"seconds": 5.0, "rounds": later, **alternated_verdict(later)}}
    row = _issue28_rows("quiet", condition)[1]
    assert row["met"] is False and row["bench"] == pytest.approx(np.median([p["bench"] for p in later]))


def test_a_late_first_sync_is_late_alone_and_makes_no_other_late() -> None:
    # a producer's first SYNC 0.65 ms late, the next 87 us late, then every one on its slot
    late = np.zeros(5000)
    late[:2] = 650e-6, 87e-6
    stats = sync_statistics(50.0 + np.arange(5000) * PERIOD + late, PERIOD)
    assert stats["lateness_us"]["max"] == pytest.approx(650.0, abs=1e-3)
    assert stats["lateness_us"]["p99"] == pytest.approx(0.0, abs=1e-3)  # 2 late SYNCs in 5000: not the top 1 %
