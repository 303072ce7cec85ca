"""One project-versus-peer measurement, as ``make bench`` records and renders it (``docs/benchmarks.md``).

A :class:`Comparison` holds the project's figure and, when there is one, a peer's figure measured in the same run
on the same work, each with every repetition (the median is the figure, min..max the spread), the ratio oriented so
that above 1 means the project is better, and the issue's goal with whether it was met. Any benchmark module can
return comparisons; :mod:`benchmarks.report` renders them all.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["Comparison", "Figure", "alternate", "comparisons_json", "repeat", "seconds"]


@dataclass(frozen=True)
class Figure:
    """Repetitions of one measurement; :attr:`median` is the figure."""

    runs: tuple[float, ...]

    @property
    def median(self) -> float:
        return float(statistics.median(self.runs))

    def to_json(self) -> dict[str, Any]:
        return {"median": self.median, "min": min(self.runs), "max": max(self.runs), "runs": list(self.runs)}


def repeat(measure: Callable[[], float], repeats: int) -> Figure:
    """``repeats`` calls of ``measure`` (each returns one value) as a :class:`Figure`."""
    return Figure(tuple(float(measure()) for _ in range(repeats)))


def alternate(first: Callable[[], float], second: Callable[[], float], repeats: int) -> tuple[Figure, Figure]:
    """``repeats`` measurements of each, alternated (first, second, first, ...), so that a load change on the shared
    machine hits both sides alike."""
    runs: tuple[list[float], list[float]] = ([], [])
    for _ in range(repeats):
        runs[0].append(float(first()))
        runs[1].append(float(second()))
    return Figure(tuple(runs[0])), Figure(tuple(runs[1]))


def seconds(call: Callable[[], object]) -> float:
    """Wall-clock seconds of one ``call()``."""
    started = time.perf_counter()
    call()
    return time.perf_counter() - started


@dataclass(frozen=True)
class Comparison:
    """The project against a peer (or against an absolute goal), measured in one run.

    Attributes
    ----------
    target
        What is measured, in words (the issue's target it belongs to).
    unit
        Unit of both figures (``"us/step"``, ``"frames/s"``, ``"s"``).
    higher_is_better
        ``True`` for rates, ``False`` for times.
    project, peer
        The figures; ``peer`` is ``None`` when the goal is absolute.
    peer_name
        Who the peer is (``"python-can BLFWriter"``).
    min_ratio
        Goal: the project at least this many times better than the peer (``ratio >= min_ratio``).
    limit
        Goal: an absolute bound on the project's figure (a maximum for times, a minimum for rates).
    note
        What bounds the figure or how it was measured, when a reader needs it.
    """

    target: str
    unit: str
    higher_is_better: bool
    project: Figure
    peer: Figure | None = None
    peer_name: str = ""
    min_ratio: float | None = None
    limit: float | None = None
    note: str = ""

    @property
    def ratio(self) -> float | None:
        """How many times better the project is than the peer (above 1: better), from the medians."""
        if self.peer is None or self.peer.median == 0 or self.project.median == 0:
            return None
        if self.higher_is_better:
            return self.project.median / self.peer.median
        return self.peer.median / self.project.median

    @property
    def goal(self) -> str:
        """The goal in words (empty: none, the figure is for information)."""
        parts = []
        if self.min_ratio is not None:
            parts.append(f">= {self.min_ratio:g}x the peer")
        if self.limit is not None:
            parts.append(f"{'>=' if self.higher_is_better else '<='} {self.limit:g} {self.unit}")
        return ", ".join(parts)

    @property
    def met(self) -> bool | None:
        """Whether every goal holds on the medians (``None``: no goal)."""
        checks: list[bool] = []
        ratio = self.ratio
        if self.min_ratio is not None:
            checks.append(ratio is not None and ratio >= self.min_ratio)
        if self.limit is not None:
            value = self.project.median
            checks.append(value >= self.limit if self.higher_is_better else value <= self.limit)
        return all(checks) if checks else None

    def to_json(self) -> dict[str, Any]:
        return {
            "target": self.target,
            "unit": self.unit,
            "higher_is_better": self.higher_is_better,
            "project": self.project.to_json(),
            "peer_name": self.peer_name,
            "peer": None if self.peer is None else self.peer.to_json(),
            "ratio": self.ratio,
            "goal": self.goal,
            "min_ratio": self.min_ratio,
            "limit": self.limit,
            "met": self.met,
            "note": self.note,
        }


def comparisons_json(rows: Sequence[Comparison]) -> list[dict[str, Any]]:
    """The rows as JSON (what ``results.json`` stores under ``comparisons``)."""
    return [row.to_json() for row in rows]
