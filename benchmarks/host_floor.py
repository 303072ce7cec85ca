"""What the host allows a 1 kHz Python loop: the floor the realtime bench is judged against.

Two measurements, taken in the same condition (quiet or loaded) as the bench and its peers in
:mod:`benchmarks.realtime`:

``wakeups``
    A process under ``chrt -f 50`` (the bench's own priority) that does nothing but wait for absolute 1 ms
    deadlines (``time.sleep`` to ``t0 + k * period``, as the bench's clock does before its spin tail) and records how
    late each wake-up was: a cyclictest in Python. No CAN, no work: whatever it shows, every realtime Python process
    on this host suffers, so a bench cycle (SYNC out, the emulator's answer over a socket, the command back) cannot
    miss fewer deadlines than this probe sees wake-ups later than the cycle's budget.
``steal``
    CPU steal time over the condition (``/proc/stat``, summed over CPUs, in % of the elapsed CPU time): the time the
    hypervisor ran someone else while this guest's vCPUs wanted to run. No scheduling policy inside the guest can
    win it back.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: the bench's own priority (``bench.realtime.sched_fifo_priority`` in configs/realtime_1khz.yaml)
PROBE_FIFO = 50
#: wake-ups later than these (microseconds) are counted: half a period, and the whole 1 ms period
LATE_US = (500.0, 1000.0)

_PROBE = """
import sys, time, numpy as np
period, seconds = float(sys.argv[1]), float(sys.argv[2])
count = int(seconds / period)
late = np.empty(count)
t0 = time.perf_counter() + period
for k in range(count):
    deadline = t0 + k * period
    pause = deadline - time.perf_counter()
    if pause > 0:
        time.sleep(pause)
    late[k] = time.perf_counter() - deadline
np.save(sys.argv[3], late)
"""


@dataclass(frozen=True)
class StealMeter:
    """Steal and total CPU time (jiffies, all CPUs) at one instant, from the ``cpu`` line of ``/proc/stat``."""

    steal: int
    total: int

    @classmethod
    def now(cls) -> StealMeter:
        fields = [int(value) for value in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
        # user nice system idle iowait irq softirq steal [guest guest_nice: already inside user and nice]
        return cls(steal=fields[7], total=sum(fields[:8]))

    def percent_since(self, start: StealMeter) -> float | None:
        """Steal in % of the CPU time elapsed since ``start`` (None if no time elapsed)."""
        elapsed = self.total - start.total
        return 100.0 * (self.steal - start.steal) / elapsed if elapsed > 0 else None


def wakeups(seconds: float, period: float, work: Path) -> dict[str, float | int]:
    """Run the probe for ``seconds`` under ``chrt -f 50``; its wake-up lateness quantiles (us) and late counts."""
    out = work / "host-floor.npy"
    subprocess.run(["chrt", "-f", str(PROBE_FIFO), sys.executable, "-c", _PROBE, str(period), str(seconds), str(out)],
                   check=True)
    late_us = np.load(out) * 1e6
    p50, p99, p999 = np.percentile(late_us, [50, 99, 99.9])
    figures: dict[str, float | int] = {
        "wakeups": int(late_us.size), "p50_us": float(p50), "p99_us": float(p99), "p99_9_us": float(p999),
        "max_us": float(late_us.max()),
    }
    for limit in LATE_US:
        figures[f"over_{limit:.0f}us_fraction"] = float(np.mean(late_us > limit))
    return figures
