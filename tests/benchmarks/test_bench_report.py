"""``make bench``'s comparison rows and the generated page: ratios oriented (above 1: the project is better), goals
judged on the medians, every number on the page taken from the results document."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.comparison import Comparison, Figure
from benchmarks.report import comparison_table


def test_ratio_is_oriented_so_that_above_one_means_better() -> None:
    faster = Comparison("t", "us/step", False, Figure((2.0, 4.0, 3.0)), Figure((30.0, 33.0, 36.0)), "peer")
    assert faster.ratio == pytest.approx(11.0)  # medians 3 and 33: a time, lower is better
    rate = Comparison("r", "frames/s", True, Figure((100.0,)), Figure((400.0,)), "peer")
    assert rate.ratio == pytest.approx(0.25)


@pytest.mark.parametrize(
    ("project", "peer", "min_ratio", "limit", "met"),
    [
        ((3.0,), (70.0,), 20.0, None, True),
        ((4.0,), (70.0,), 20.0, None, False),  # 17.5x < 20x
        ((0.4,), None, None, 0.5, True),
        ((0.6, 0.4, 0.7), None, None, 0.5, False),  # the median 0.6 decides, not the best run
        ((1.0,), None, None, None, None),
    ],
)
def test_goals_are_judged_on_the_medians(
    project: tuple[float, ...],
    peer: tuple[float, ...] | None,
    min_ratio: float | None,
    limit: float | None,
    met: bool | None,
) -> None:
    row = Comparison("x", "s", False, Figure(project), None if peer is None else Figure(peer), "p", min_ratio, limit)
    assert row.met is met


def test_table_rows_carry_the_figures_spread_and_verdict() -> None:
    row = Comparison(
        "PMSM step",
        "us/step",
        False,
        Figure((3.0, 5.0, 4.0)),
        Figure((80.0, 90.0, 100.0)),
        "before",
        min_ratio=20.0,
        note="why",
    )
    lines = comparison_table([row.to_json()])
    assert lines[2] == (
        "| PMSM step | us/step | 4 (3..5, n=3) | before | 90 (80..100, n=3) | 22.50x | >= 20x the peer | met |"
    )
    assert lines[-1] == "- *PMSM step*: why."
    missed = Comparison("sim", "s", False, Figure((9.0,)), limit=0.3).to_json()
    assert comparison_table([missed])[2].endswith("| - | <= 0.3 s | **missed** |")


def test_the_missed_section_says_by_how_much_and_why_for_every_missed_row(monkeypatch: pytest.MonkeyPatch) -> None:
    from benchmarks import report

    monkeypatch.setattr(report, "REALTIME_RESULTS", report.REALTIME_RESULTS.with_name("no-such-results.json"))
    rows = [
        Comparison("lockstep foilc-hil run, PMSM axis at 1 ms, whole run", "cycles/s", True, Figure((8000.0,)),
                   Figure((3000.0,)), "peer", 1.5, 10_000.0).to_json(),
        Comparison("something new", "s", False, Figure((2.0,)), None, "", None, 1.0).to_json(),
        Comparison("met", "s", False, Figure((0.5,)), None, "", None, 1.0).to_json(),
    ]
    lines = report._missed({"comparisons": rows})
    text = "\n".join(lines)
    assert "8,000 against 10,000 cycles/s (20 % short)" in text  # the ratio 2.67x meets its 1.5x: not said
    assert "ratio" not in text.split("**something new**")[0].split("whole run**")[1]
    assert "**something new**: 2 against 1 s (100 % over). Bounded by not described" in text
    assert "**met**" not in text
    assert "`make test` under 3 minutes" in text


def test_every_target_the_benches_judge_and_the_page_shows_missed_is_described() -> None:
    """The committed page names no missed row without its bound and its attempts (``MISSED_WHY``)."""
    page = (Path(__file__).resolve().parents[2] / "docs" / "benchmarks.md").read_text()
    undescribed = [line for line in page.splitlines() if "not described" in line]
    assert undescribed == []
