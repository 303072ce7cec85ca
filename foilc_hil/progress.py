"""Progress on stderr: a bench run's bar per trial and live table of per-trial SSE / RMSE, and the slow steps of
every command (tuning, the LMI, certificates, co-design, identification, robustness, reports).

Shown with ``rich`` only when stderr is a terminal and neither ``--quiet`` nor ``--json`` is given; otherwise
nothing is printed, so ``--json`` stdout and CI logs stay clean. The bench uses :class:`NullProgress` then and
updates its bar a few times per trial, never per cycle, so the view costs nothing on the hot path.

Steps: the CLI runs every command inside :func:`steps`, which makes the step view current (a
:class:`contextvars.ContextVar`, so a library caller that never enters it sees no output); code that may take more
than a second marks itself with :func:`step` (a context manager yielding an ``advance(done)`` callback) or the
:func:`as_step` decorator. Each step shows a spinner (a bar when its total is known) and the elapsed time while it
runs, then one line ``done: NAME (S s)``; steps nest.
"""

from __future__ import annotations

import contextlib
import enum
import functools
import sys
import time
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from types import TracebackType
from typing import Any, ParamSpec, Protocol, TypeVar

__all__ = [
    "NullProgress",
    "ProgressEvent",
    "ProgressView",
    "QueueProgress",
    "RichProgress",
    "RichRunsProgress",
    "RichSteps",
    "as_step",
    "make_progress",
    "shows_progress",
    "step",
    "steps",
]

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


def _live_table(title: str, columns: tuple[str, ...]) -> tuple[Any, Any, Any, Any]:
    """The bench's live view on stderr, started: ``(console, progress, table, live)``, a table of finished trials
    with ``columns`` above the bars of ``progress``."""
    from rich.console import Console, Group
    from rich.live import Live
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    console = Console(stderr=True)
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        console=console)
    table = Table(title=title, expand=False)
    for column in columns:
        table.add_column(column, justify="right")
    live = Live(Group(table, progress), console=console, refresh_per_second=8)
    live.start()
    return console, progress, table, live


def shows_progress(*, quiet: bool) -> bool:
    """Whether progress is shown: stderr is a terminal and the command is not ``quiet`` (``--quiet``, ``--json``)."""
    return not quiet and sys.stderr.isatty()


class RichProgress:
    """``rich`` live view on stderr: the current trial's bar above a table of finished trials.

    Parameters
    ----------
    title
        Shown above the table, e.g. ``"FOILC on virtual:bench-1"``.
    """

    def __init__(self, title: str) -> None:
        self._console, self._progress, self._table, self._live = _live_table(title, ("trial", "SSE", "RMSE", "max |e|"))
        self._task: Any = None

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


@enum.unique
class ProgressEvent(enum.Enum):
    """What :class:`QueueProgress` sends: one per :class:`ProgressView` method."""

    BEGIN_TRIAL = "begin_trial"
    ADVANCE = "advance"
    END_TRIAL = "end_trial"
    NOTE = "note"


class EventQueue(Protocol):
    """Where :class:`QueueProgress` puts its events (a ``multiprocessing`` queue)."""

    def put(self, item: tuple[str, ProgressEvent, tuple[Any, ...]]) -> None: ...


class QueueProgress:
    """A :class:`ProgressView` in a worker process: every call goes to the parent's :class:`RichRunsProgress`
    through ``events``, tagged with the run's ``name`` (the demo runs its laws in two processes, one view shows
    both). Closing it closes nothing: the parent's view outlives the run."""

    def __init__(self, events: EventQueue, name: str) -> None:
        self._events = events
        self._name = name

    def begin_trial(self, trial: int, total_trials: int, samples: int) -> None:
        self._events.put((self._name, ProgressEvent.BEGIN_TRIAL, (trial, total_trials, samples)))

    def advance(self, samples_done: int) -> None:
        self._events.put((self._name, ProgressEvent.ADVANCE, (samples_done,)))

    def end_trial(self, trial: int, sse: float, rmse: float, max_abs_error: float) -> None:
        self._events.put((self._name, ProgressEvent.END_TRIAL, (trial, sse, rmse, max_abs_error)))

    def note(self, message: str) -> None:
        self._events.put((self._name, ProgressEvent.NOTE, (message,)))

    def close(self) -> None:
        return None


class RichRunsProgress:
    """``rich`` live view of several runs at once: a bar per run (its current trial) above one table of finished
    trials, a row per trial and run.

    Parameters
    ----------
    names
        The runs, in the order of their bars.
    title
        Shown above the table.
    """

    def __init__(self, names: list[str], title: str) -> None:
        self._console, self._progress, self._table, self._live = _live_table(
            title, ("run", "trial", "SSE", "RMSE", "max |e|")
        )
        self._tasks = {name: self._progress.add_task(f"{name}: starting", total=None) for name in names}

    def handle(self, name: str, event: ProgressEvent, args: tuple[Any, ...]) -> None:
        """One event of a :class:`QueueProgress` of the run ``name``."""
        task = self._tasks[name]
        if event is ProgressEvent.BEGIN_TRIAL:
            trial, total_trials, samples = args
            self._progress.update(task, description=f"{name}: trial {trial}/{total_trials}", total=samples,
                                  completed=0)
        elif event is ProgressEvent.ADVANCE:
            self._progress.update(task, completed=args[0])
        elif event is ProgressEvent.END_TRIAL:
            trial, sse, rmse, max_abs_error = args
            self._table.add_row(name, str(trial), f"{sse:.6g}", f"{rmse:.6g}", f"{max_abs_error:.6g}")
        else:
            self._console.print(f"{name}: {args[0]}")

    def close(self) -> None:
        self._live.stop()


def make_progress(title: str, *, quiet: bool) -> ProgressView:
    """A rich view when stderr is a terminal and not ``quiet``, else :class:`NullProgress`."""
    if not shows_progress(quiet=quiet):
        return NullProgress()
    return RichProgress(title)


# --- steps --------------------------------------------------------------------------------------------------------

_P = ParamSpec("_P")
_R = TypeVar("_R")


class RichSteps:
    """The rich view of :func:`step`: one spinner (or bar) per running step, one line per finished step."""

    def __init__(self) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

        self._console = Console(stderr=True)
        self._progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                  TimeElapsedColumn(), console=self._console, transient=True)
        self._running = 0

    def begin(self, name: str, total: int | None) -> Any:
        """Show ``name`` running; returns the handle :meth:`advance` and :meth:`end` take."""
        from rich.errors import LiveError

        if self._running == 0:
            with contextlib.suppress(LiveError):  # another live view (the bench's) owns the terminal: lines only
                self._progress.start()
        self._running += 1
        return self._progress.add_task(name, total=total)

    def advance(self, handle: Any, done: int) -> None:
        self._progress.update(handle, completed=done)

    def end(self, handle: Any, name: str, seconds: float) -> None:
        self._progress.remove_task(handle)
        self._running -= 1
        if self._running == 0:
            self._progress.stop()
        self._console.print(f"done: {name} ({seconds:.1f} s)", highlight=False)


_STEPS: ContextVar[RichSteps | None] = ContextVar("foilc_hil_steps", default=None)


@contextlib.contextmanager
def steps(*, quiet: bool) -> Iterator[None]:
    """Show the :func:`step` progress of the code run inside, on a terminal stderr unless ``quiet``."""
    view = RichSteps() if shows_progress(quiet=quiet) else None
    token = _STEPS.set(view)
    try:
        yield
    finally:
        _STEPS.reset(token)


def _ignore(done: int) -> None:
    return None


@contextlib.contextmanager
def step(name: str, total: int | None = None) -> Iterator[Callable[[int], None]]:
    """Mark a step that may take more than a second; yields ``advance(done)`` (of ``total``, when known)."""
    view = _STEPS.get()
    if view is None:
        yield _ignore
        return
    started = time.monotonic()
    handle = view.begin(name, total)
    try:
        yield functools.partial(view.advance, handle)
    finally:
        view.end(handle, name, time.monotonic() - started)


def as_step(name: str) -> Callable[[Callable[_P, _R]], Callable[_P, _R]]:
    """Decorator: every call of the function is the step ``name``."""

    def decorate(function: Callable[_P, _R]) -> Callable[_P, _R]:
        @functools.wraps(function)
        def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
            with step(name):
                return function(*args, **kwargs)

        return wrapper

    return decorate
