"""Experiments from a script: :func:`design`, :func:`simulate` and the :class:`Bench`, the one rig of
``foilc-hil run`` (:class:`foilc_hil.loop.rig.Rig`) trial by trial."""

from __future__ import annotations

from collections.abc import Generator, Iterator, Mapping
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

from foilc_hil.api.results import TrialResult
from foilc_hil.errors import ConfigError, InputError

if TYPE_CHECKING:
    from drivers.config import BusConfig
    from drivers.drive import StopReport
    from foilc_hil.config import Config
    from foilc_hil.design.record import Design
    from foilc_hil.loop.interfaces import TrialRecord
    from foilc_hil.loop.rig import Rig, RunReport
    from plant_emulator.embedded import EmbeddedEmulator

__all__ = ["Bench", "design", "load_config", "simulate"]

#: the CAN loop applies a command one SYNC after it computes it (foilc_hil.loop.settings.CAN_INPUT_DELAY)
_BENCH_INPUT_DELAY = 1


def _one_axis(config: Config, what: str) -> int:
    """``N``, the samples of one trial of ``config``'s one axis; a config with ``axes:`` is refused."""
    from foilc_hil.references import trial_samples

    if config.axes:
        raise ConfigError(f"{what} runs one axis; a run of several is `foilc-hil run`'s", key="axes")
    return trial_samples(config.reference, config.sample_time)


def load_config(path: str | Path | None, overrides: Mapping[str, Any] | None = None) -> Config:
    """Load and validate a configuration file, with dotted-key overrides on top (as ``--set`` gives them).

    Parameters
    ----------
    path
        The YAML file (``configs/demo.yaml``); ``None``: the defaults alone.
    overrides
        ``{"trials": 3, "law.kind": "ioilc", "reference.segments": [...]}``: each key a dotted path into the
        document (``docs/config-reference.md`` lists every field).

    Returns
    -------
    Config
        The resolved configuration (a validated pydantic model: ``cfg.sample_time``, ``cfg.law.kind``, ...).

    Raises
    ------
    ConfigError
        The first bad value, naming the file and the key (exit code 2).
    """
    from foilc_hil.config import load_config as load

    return load(path, overrides)


def design(config: Config, *, law: str | None = None, input_delay: int = _BENCH_INPUT_DELAY) -> Design:
    """The certified design of ``config``'s law, for its trial length: gains, model and certificates.

    Parameters
    ----------
    config
        The configuration (:func:`foilc_hil.load_config`), one axis.
    law
        ``foilc``, ``ioilc``, ``p-type``, ``noilc`` or ``gradient``; ``None``: ``config.law.kind``.
    input_delay
        Cycles between computing a command and the plant applying it: 1, the bench's CAN loop (the default, so the
        design runs on :class:`Bench` and in :func:`simulate` alike); 0, an ideal offline loop.

    Returns
    -------
    Design
        ``P`` (the gain that runs), ``kp``, ``r``, ``gain_scale``, ``certificates`` (spectral radius and 2-norm of the
        law's trial-to-trial map, nominal and at the uncertainty's vertices) and the model it was designed on.

    Raises
    ------
    ConfigError
        An unknown law, a config with ``axes:``, a configuration the design cannot use (the key named).
    InfeasibleDesignError
        Tuning, the LMI or the certificate fails: no certified design exists (exit code 3).
    """
    from foilc_hil.design.pipeline import build_design

    return build_design(config, law or config.law.kind, _one_axis(config, "design"), input_delay=input_delay)


def simulate(config: Config, *, law: str | None = None, trials: int | None = None, design: Design | None = None,
             input_delay: int = _BENCH_INPUT_DELAY, out: str | Path | None = None) -> list[TrialResult]:
    """Run learning trials offline: the bench's trial loop on the plant's physics (no CAN), in lockstep.

    Parameters
    ----------
    config
        The configuration (:func:`foilc_hil.load_config`), one axis.
    law
        ``foilc``, ``ioilc``, ``p-type``, ``noilc`` or ``gradient``; ``None``: the design's law, else
        ``config.law.kind``.
    trials
        How many; ``None``: ``config.trials``.
    design
        A design of :func:`design` (skips tuning and synthesis); ``None``: designed here.
    input_delay
        Without ``design``: the loop's transport delay in cycles (1, the default, as on the CAN bench).
    out
        An MCAP log to write (the layout of ``foilc-hil simulate --out``); ``None``: none.

    Returns
    -------
    list of TrialResult
        One per completed trial; a divergence stop ends the list at the diverged trial.

    Raises
    ------
    ConfigError
        Bad trial count, a design of another law, a config with ``axes:`` (the key named).
    InfeasibleDesignError
        No certified design exists for the law.
    """
    from foilc_hil.loop.simulation import simulate as simulate_trials

    _one_axis(config, "simulate")
    kind = law or (str(design.law) if design is not None else str(config.law.kind))
    result = simulate_trials(config, law=kind, trials=trials if trials is not None else config.trials,
                             design=design, input_delay=input_delay, out=out)
    # the result's (K, N, 1) stacks hold the trials' arrays as the loop logged them (copies, the same floats)
    return [TrialResult(metrics.trial, result.reference[:, 0].copy(), result.outputs[k, :, 0],
                        result.controls[k, :, 0], result.errors[k, :, 0], result.learned[k, :, 0], metrics,
                        config.sample_time) for k, metrics in enumerate(result.metrics)]


class Bench:
    """The bench as a context manager: commissioned and enabled in ``with``, every drive safe-stopped at its end.

    It is the rig every ``foilc-hil run`` goes through (:class:`foilc_hil.loop.rig.Rig`): the log (a writer
    process), the embedded emulator unless the config names a bus (``bus:``), the master, the commissioning, the
    enable; the trials run in the one trial loop, settle phases and the between-trial update included.

    Parameters
    ----------
    config
        The configuration (:func:`foilc_hil.load_config`), one axis.
    design
        The design to run (:func:`design`); ``None``: designed on entry for the CAN loop.
    law
        ``None``: the design's law, else ``config.law.kind``.
    out
        The MCAP log to write (read it back with :func:`foilc_hil.open_log`); ``None``: no log.
    bus
        A ``drivers.BusConfig`` to run on instead of ``config.bus``.
    quiet
        No progress view on stderr.

    Notes
    -----
    Leaving the ``with`` block on any path -- the end, ``break``, an exception in its body, an abort of the loop --
    quick-stops and disables every drive and reads its state back (:attr:`stop_report`); an unconfirmed or faulted
    stop is raised as a :class:`~foilc_hil.errors.DriveError` when nothing else is. Between two trials no cycle runs
    while the loop body works: in realtime keep it short (the drive supervises SYNC).

    Inside the block, SIGINT and SIGTERM are the bench's stop request (as in ``foilc-hil run``): the trial loop ends
    at its next cycle with :class:`~foilc_hil.errors.RunInterruptedError`; a signal never cuts the stop short.

    Examples
    --------
    >>> with fh.Bench(cfg, design=fh.design(cfg), out="run.mcap") as bench:   # doctest: +SKIP
    ...     for trial in bench.trials(3):
    ...         print(trial.index, trial.sse)
    """

    def __init__(self, config: Config, *, design: Design | None = None, law: str | None = None,
                 out: str | Path | None = None, bus: BusConfig | None = None, quiet: bool = True) -> None:
        from foilc_hil.loop.rig import RunRequest

        _one_axis(config, "Bench")
        kind = law or (str(design.law) if design is not None else None)
        self._request = RunRequest(config=config, out=out, law=kind, bus=bus, quiet=quiet, design=design)
        self._rig: Rig | None = None
        self._running: Generator[TrialRecord, None, None] | None = None

    def __enter__(self) -> Bench:
        from foilc_hil.loop.rig import Rig

        if self._rig is not None:
            raise InputError("a Bench is entered once; make another")
        rig = Rig(self._request)  # the plan (and the design, when none was given) before anything is opened
        self._rig = rig.__enter__()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        if self._rig is None:
            return
        try:
            self._end_trials()  # the body left a trial loop mid-way: end it before the drives stop
        except BaseException as error:  # the drives are stopped all the same, and the error is what the run says
            self._rig.__exit__(type(error), error, error.__traceback__)
            raise
        self._rig.__exit__(exc_type, exc, traceback)

    def _end_trials(self) -> None:
        """End the trial loop a ``trials`` iteration left suspended (its log and counts finished)."""
        running, self._running = self._running, None
        if running is not None:
            running.close()

    def trials(self, count: int | None = None) -> Iterator[TrialResult]:
        """Run ``count`` more trials, yielding each as it finishes.

        Parameters
        ----------
        count
            How many; ``None``: ``config.trials``. Another call continues the numbering.

        Yields
        ------
        TrialResult
            Each trial once its update is done and it is in the log's queue. A divergence stop yields the diverged
            trial and ends (learning stopped, the best input restored, :attr:`stopped` says why).

        Raises
        ------
        ConfigError
            ``count`` below 1.
        DriveError
            An abort of the loop (drive fault, lost feedback, heartbeat), raised after the drive's quick stop.
        """
        rig = self._open_rig()
        count = rig.plan.trials if count is None else count
        if count < 1:
            raise ConfigError(f"must be >= 1, got {count}", key="trials")
        self._end_trials()  # a previous iteration still suspended (kept in a variable): it ends here
        running = rig.loop.iter_trials(count)
        self._running = running
        try:
            for record in running:
                yield TrialResult.from_record(record)
        finally:
            running.close()
            if self._running is running:
                self._running = None

    def _open_rig(self) -> Rig:
        if self._rig is None:
            raise InputError("the bench is not open: use it in a with block")
        return self._rig

    @property
    def design(self) -> Design:
        """The design that runs."""
        return self._open_rig().plan.axes[0].design

    @property
    def stopped(self) -> str | None:
        """Why learning stopped early (the divergence rule), or ``None``."""
        return self._open_rig().loop.outcome.stopped

    @property
    def emulator(self) -> EmbeddedEmulator | None:
        """The embedded emulator the bench runs on (its ``drive`` is the emulated drive), ``None`` on a bus."""
        emulators = self._open_rig().emulators
        return emulators[0] if emulators else None

    @property
    def stop_report(self) -> StopReport | None:
        """The drive's stop, read back from its statusword once the block has ended (``None`` before)."""
        rig = self._open_rig()
        return rig.stops.get(rig.plan.node_ids[0])

    def report(self) -> RunReport:
        """What the run produced once the block has ended: every trial's metrics, timing, faults, the stop (the
        ``foilc-hil run --json`` document is its ``to_json()``)."""
        return self._open_rig().report()
