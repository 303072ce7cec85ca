"""Loop-thread stalls, a fault injection of the bench's own: ``stall@TRIAL+CYCLE[:duration=S,count=K]``.

A stall sleeps the trial loop's thread alone for ``duration`` seconds in cycle ``CYCLE`` of trial ``TRIAL`` (and the
``count - 1`` cycles after it), between the law's command and its RPDO: what a host stall of the loop does, and
nothing else. With SYNC from a clock (:mod:`drivers.sync_clock`) the SYNCs go on meanwhile, so a stall longer than
what is left of the period makes the command miss its SYNC: the drive latches the previous command once more
(``/ilc/sample.latched``, ``/timing`` ``missed``). With the loop sending SYNC (lockstep, ``bench.realtime.sync:
loop``) the next SYNC waits for the loop instead.

It belongs to the loop, not to the bus (:class:`drivers.faults.FaultyBus` refuses it): :func:`LoopStalls.of`
picks the loop kinds (:data:`drivers.injection.LOOP_KINDS`) out of a run's injections, and the rig hands the plan to
:class:`~foilc_hil.loop.bench.TrialLoop` (``stalls=``).
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers.injection import LOOP_KINDS, Injection, InjectionReport

__all__ = ["LoopStalls"]


class LoopStalls:
    """The loop's stall plan: which cycles of which trial sleep how long, and what was done (the run's report).

    Parameters
    ----------
    injections
        Injections of the loop kinds (each with a trial, as :class:`~drivers.injection.Injection` requires).
    """

    def __init__(self, injections: Sequence[Injection]) -> None:
        self.injections = tuple(injections)
        self._started: dict[int, int] = {}  # injection index -> the SYNC its first stalled cycle answered
        self._stalled: dict[int, int] = {}  # injection index -> cycles stalled

    @classmethod
    def of(cls, injections: Sequence[Injection]) -> LoopStalls | None:
        """The plan of the loop kinds among ``injections``; None without any."""
        picked = [injection for injection in injections if injection.kind in LOOP_KINDS]
        return cls(picked) if picked else None

    def cycles(self, trial: int) -> dict[int, float]:
        """``{sample: seconds}`` of trial ``trial`` (several stalls of one cycle add up)."""
        plan: dict[int, float] = {}
        for injection in self.injections:
            if injection.trial == trial:
                for sample in range(injection.cycle, injection.cycle + injection.count):
                    plan[sample] = plan.get(sample, 0.0) + injection.duration
        return plan

    def stalled(self, trial: int, sample: int, sync: int) -> None:
        """The loop stalled in ``sample`` of ``trial``, the cycle of SYNC ``sync`` (the bus's count)."""
        for index, injection in enumerate(self.injections):
            if injection.trial == trial and injection.cycle <= sample < injection.cycle + injection.count:
                self._started.setdefault(index, sync)
                self._stalled[index] = self._stalled.get(index, 0) + 1

    def reports(self) -> list[InjectionReport]:
        """What each stall did: the SYNC of its first stalled cycle (None: never reached) and the cycles stalled
        (``frames``)."""
        return [InjectionReport(injection, self._started.get(index), self._stalled.get(index, 0))
                for index, injection in enumerate(self.injections)]
