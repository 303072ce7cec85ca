"""Progress of a bench run on stderr: a bar per trial and a live table of per-trial SSE / RMSE.

Shown with ``rich`` only when stderr is a terminal and ``--quiet`` is not given; otherwise the bench uses
:class:`NullProgress` (nothing is printed, so ``--json`` stdout and CI logs stay clean). The bench updates the
bar a few times per trial, never per cycle, so the view costs nothing on the hot path.
"""

from __future__ import annotations

import sys
from types import TracebackType
from typing import Any, Protocol

__all__ = ["NullProgress", "ProgressView", "RichProgress", "make_progress"]

#: how many bar updates per trial (the loop calls :meth:`ProgressView.advance` this often)
UPDATES_PER_TRIAL = 20


class ProgressView(Protocol):
    """What the bench reports to: trial start, samples done, trial metrics, the end."""

    def begin_trial(self, trial: int, total_trials: int, samples: int) -> None: ...

    def advance(self, samples_done: int) -> None: ...

    def end_trial(self, trial: int, sse: float, rmse: float, max_abs_error: float) -> None: ...

    def note(self, message: str) -> None: ...

    def close(self) -> None: ...


class NullProgress:
    """No output at all."""

    def begin_trial(self, trial: int, total_trials: int, samples: int) -> None:
        return None

    def advance(self, samples_done: int) -> None:
        return None

    def end_trial(self, trial: int, sse: float, rmse: float, max_abs_error: float) -> None:
        return None

    def note(self, message: str) -> None:
        return None

    def close(self) -> None:
        return None


class RichProgress:
    """``rich`` live view on stderr: the current trial's bar above a table of finished trials.

    Parameters
    ----------
    title
        Shown above the table, e.g. ``"FOILC on virtual:bench-1"``.
    """

    def __init__(self, title: str) -> None:
        from rich.console import Console, Group
        from rich.live import Live
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
        from rich.table import Table

        self._console = Console(stderr=True)
        self._progress = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=self._console,
        )
        self._table = Table(title=title, expand=False)
        for column in ("trial", "SSE", "RMSE", "max |e|"):
            self._table.add_column(column, justify="right")
        self._task: Any = None
        self._live = Live(Group(self._table, self._progress), console=self._console, refresh_per_second=8)
        self._live.start()

    def begin_trial(self, trial: int, total_trials: int, samples: int) -> None:
        if self._task is not None:
            self._progress.remove_task(self._task)
        self._task = self._progress.add_task(f"trial {trial}/{total_trials}", total=samples)

    def advance(self, samples_done: int) -> None:
        if self._task is not None:
            self._progress.update(self._task, completed=samples_done)

    def end_trial(self, trial: int, sse: float, rmse: float, max_abs_error: float) -> None:
        self._table.add_row(str(trial), f"{sse:.6g}", f"{rmse:.6g}", f"{max_abs_error:.6g}")

    def note(self, message: str) -> None:
        self._console.print(message)

    def close(self) -> None:
        self._live.stop()

    def __enter__(self) -> RichProgress:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def make_progress(title: str, *, quiet: bool) -> ProgressView:
    """A rich view when stderr is a terminal and not ``quiet``, else :class:`NullProgress`."""
    if quiet or not sys.stderr.isatty():
        return NullProgress()
    return RichProgress(title)
