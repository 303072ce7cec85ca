"""Verdicts as statistics: the spread of a figure over seeds and the paired rule that says "holds", "fails" or
"a tie" (issue 26, target 9; ``docs/paper-reproduction.md`` states the rule as :data:`RULE`).

A figure (trials to tolerance, an SSE, ...) is measured once per seed for each law; the seeds are the same for both
laws (same noise, same phases), so the comparison is paired: ``d_i = FOILC_i - IOILC_i``. A verdict is never read
off one run: the difference must lie outside what the seeds move, and be large enough to matter.

Pure functions of the samples (no simulation here), so the rule itself is tested on synthetic samples
(``tests/benchmarks/test_reproduction.py``).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "LEVEL",
    "RELEVANCE",
    "RESAMPLES",
    "RULE",
    "PairedJudgement",
    "Samples",
    "Spread",
    "Verdict",
    "combine",
    "judge",
    "sign_test_p",
    "spread",
]

#: Per-seed values of one figure: a sequence or a 1-D array.
Samples = Sequence[float] | np.ndarray

#: Confidence level of the bootstrap interval of the median paired difference.
LEVEL = 0.95
#: The smallest difference that counts, relative to IOILC's median: below it the laws tie however consistent the sign
#: (issue 26's 0.03 % between two integer-order laws is such a difference).
RELEVANCE = 0.05
#: Bootstrap resamples of the seeds (fixed generator: the page is the same for the same runs).
RESAMPLES = 4000
#: The quantiles of the spread shown for each law and for the paired difference.
SPREAD_QUANTILES = (0.05, 0.95)

RULE = (
    f"Each figure is measured on every seed for both laws with the same noise and phases, so the laws are compared "
    f"seed by seed: `d = FOILC - IOILC` (lower is better for every figure here). A claim **holds** only when the "
    f"{100 * LEVEL:.0f} % paired bootstrap interval of the median of `d` ({RESAMPLES} resamples of the seeds, "
    f"percentile method) lies entirely below 0 **and** the median of `d` is at least {100 * RELEVANCE:.0f} % of "
    f"IOILC's median; it **fails** when the same holds on the other side (interval above 0, FOILC worse by at least "
    f"{100 * RELEVANCE:.0f} %); otherwise it is **a tie**. The sign counts (FOILC better / equal / worse) and the "
    f"5-95 % spread of `d` over the seeds are shown beside it."
)


class Verdict(enum.StrEnum):
    """What the paired rule says about FOILC against IOILC on one figure."""

    HOLDS = "holds"
    FAILS = "fails"
    TIE = "a tie"


@dataclass(frozen=True)
class Spread:
    """The spread of one figure over the seeds: median, the 5-95 % interval and the extremes."""

    median: float
    low: float
    high: float
    minimum: float
    maximum: float

    def text(self, spec: str) -> str:
        """``median [low, high]`` formatted with ``spec``."""
        return f"{self.median:{spec}} [{self.low:{spec}}, {self.high:{spec}}]"


@dataclass(frozen=True)
class PairedJudgement:
    """The paired comparison of FOILC with IOILC on one figure over ``n`` seeds.

    Attributes
    ----------
    n
        Seeds.
    difference
        The spread of ``d = FOILC - IOILC`` over the seeds.
    interval
        The bootstrap interval (:data:`LEVEL`) of the median of ``d``.
    reference
        IOILC's median: the scale of :data:`RELEVANCE`.
    better, equal, worse
        Seeds where FOILC's figure is lower, the same, higher.
    verdict
        The rule's answer (:data:`RULE`).
    """

    n: int
    difference: Spread
    interval: tuple[float, float]
    reference: float
    better: int
    equal: int
    worse: int
    verdict: Verdict


def spread(values: Samples) -> Spread:
    """The :class:`Spread` of ``values`` (at least one, all finite)."""
    data = np.asarray(values, dtype=float)
    if data.size == 0 or not np.all(np.isfinite(data)):
        raise ValueError("a spread needs at least one value, all finite")
    low, high = np.quantile(data, SPREAD_QUANTILES)
    return Spread(float(np.median(data)), float(low), float(high), float(data.min()), float(data.max()))


def _bootstrap_median(differences: np.ndarray, resamples: int, level: float) -> tuple[float, float]:
    """The percentile interval of the median of ``differences`` over ``resamples`` resamples of the seeds."""
    rng = np.random.default_rng(26)  # fixed: the same runs give the same page
    picks = rng.integers(0, differences.size, size=(resamples, differences.size))
    medians = np.median(differences[picks], axis=1)
    tail = 0.5 * (1.0 - level)
    low, high = np.quantile(medians, (tail, 1.0 - tail))
    return float(low), float(high)


def judge(
    foilc: Samples,
    ioilc: Samples,
    *,
    relevance: float = RELEVANCE,
    level: float = LEVEL,
    resamples: int = RESAMPLES,
) -> PairedJudgement:
    """Judge "FOILC's figure is lower than IOILC's" on paired samples (entry ``i`` of both is seed ``i``).

    Parameters
    ----------
    foilc, ioilc
        The figure per seed, same length (at least 2), finite; lower is better.
    relevance
        The smallest median difference that counts, relative to ``|median(ioilc)|`` (with a zero median, any
        non-zero difference counts).
    level
        Confidence level of the bootstrap interval of the median difference.
    resamples
        Bootstrap resamples.

    Returns
    -------
    PairedJudgement
        ``HOLDS`` when the interval lies below 0 and the median difference is relevant, ``FAILS`` when it lies above
        0 and is relevant, ``TIE`` otherwise.
    """
    f, i = np.asarray(foilc, dtype=float), np.asarray(ioilc, dtype=float)
    if f.shape != i.shape or f.ndim != 1 or f.size < 2:
        raise ValueError(f"paired samples need the same length >= 2, got {f.shape} and {i.shape}")
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(i))):
        raise ValueError("paired samples must be finite")
    d = f - i
    low, high = _bootstrap_median(d, resamples, level)
    median = float(np.median(d))
    reference = float(np.median(i))
    relevant = abs(median) >= relevance * abs(reference) and median != 0.0
    verdict = Verdict.TIE
    if relevant and high < 0.0:
        verdict = Verdict.HOLDS
    elif relevant and low > 0.0:
        verdict = Verdict.FAILS
    return PairedJudgement(
        n=int(d.size),
        difference=spread(d),
        interval=(low, high),
        reference=reference,
        better=int(np.sum(d < 0)),
        equal=int(np.sum(d == 0)),
        worse=int(np.sum(d > 0)),
        verdict=verdict,
    )


def combine(verdicts: Sequence[Verdict]) -> Verdict:
    """One verdict for a claim made of several parts: it holds when every part holds, fails when every part fails,
    and is a tie otherwise (parts that disagree settle nothing)."""
    if not verdicts:
        raise ValueError("a claim needs at least one part")
    if all(v is Verdict.HOLDS for v in verdicts):
        return Verdict.HOLDS
    if all(v is Verdict.FAILS for v in verdicts):
        return Verdict.FAILS
    return Verdict.TIE


def sign_test_p(better: int, worse: int) -> float:
    """Two-sided exact sign test: the probability, with no difference between the laws, of a split at least as
    uneven as ``better`` / ``worse`` (ties left out); 1.0 with no untied seed."""
    n = better + worse
    if n == 0:
        return 1.0
    k = min(better, worse)
    tail = sum(math.comb(n, j) for j in range(k + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)
