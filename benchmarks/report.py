"""``docs/benchmarks.md`` from one ``make bench`` run: every figure comes from ``benchmarks/results.json``.

The page is generated, never edited by hand: the prose here says how things were measured and what bounds them,
never a number; every number is read from the results document of the same run.

``python -m benchmarks.report --results benchmarks/results.json --doc docs/benchmarks.md``
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import orjson

COMMAND = "make bench  (python -m benchmarks.run --out benchmarks/results.json --doc docs/benchmarks.md)"

INTRO = """\
Every project figure below was measured in the same run as the peer it is compared with, on the same work, one
after the other, so that both see the same machine state. The machine is shared (the load average is recorded), so
read ratios rather than absolute times, and treat ratios within the spread of the repetitions as noise. Ratios are
oriented so that above 1 means the project is better (faster, or more per second). Nothing here is asserted by the
test suite: unit tests never depend on wall-clock speed. Each row is a `benchmarks.comparison.Comparison` returned by
one of the `benchmarks/bench_*.py` modules and collected by `benchmarks/run.py`; a goal is judged on the medians.
"""


def _number(value: float | None, unit: str = "") -> str:
    if value is None:
        return "-"
    magnitude = abs(value)
    text = f"{value:,.0f}" if magnitude >= 1000 else f"{value:.3g}"
    return f"{text} {unit}".strip()


def _figure(figure: dict[str, Any] | None) -> str:
    if figure is None:
        return "-"
    spread = f"{_number(figure['min'])}..{_number(figure['max'])}"
    return f"{_number(figure['median'])} ({spread}, n={len(figure['runs'])})"


def _met(value: bool | None) -> str:
    return {True: "met", False: "**missed**", None: "-"}[value]


def comparison_table(rows: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown table of comparison rows (``benchmarks.comparison.Comparison.to_json``)."""
    lines = [
        "| measurement | unit | project: median (min..max, n) | peer | peer: median (min..max, n) | ratio | goal "
        "| met |",
        "|---|---|---|---|---|---|---|---|",
    ]
    notes = []
    for row in rows:
        ratio = "-" if row["ratio"] is None else f"{row['ratio']:.2f}x"
        lines.append(
            f"| {row['target']} | {row['unit']} | {_figure(row['project'])} | {row['peer_name'] or '-'} | "
            f"{_figure(row['peer'])} | {ratio} | {row['goal'] or '-'} | {_met(row['met'])} |"
        )
        if row["note"]:
            notes.append(f"- *{row['target']}*: {row['note']}.")
    return lines + (["", *notes] if notes else [])


def _machine(results: dict[str, Any]) -> list[str]:
    machine = results["machine"]
    return [
        f"- date (UTC): {results['date']}",
        f"- machine: {machine['cpus']} CPUs, {machine['platform']}, Python {machine['python']}",
        f"- load average (1 min) at the start and end of the run: {machine['load_average_1min']:.2f}, "
        f"{results.get('load_average_end', float('nan')):.2f}",
        f"- repetitions per figure: {results['repeats']} (more where a row's n says so: the lockstep rows, whose rate "
        "moves 10 to 20 % from run to run)",
        f"- command: `{COMMAND}`",
    ]


def _lockstep(results: dict[str, Any]) -> list[str]:
    lockstep = results["can_lockstep_virtual"]
    without, logged = lockstep["without_logging"], lockstep["with_logging"]
    loop = results["loop_only"]
    return [
        "| measurement | cycles/s (median) | all runs |",
        "|---|---|---|",
        f"| CAN lockstep, embedded emulator, no logging | {_number(without['cycles_per_second'])} | "
        f"{', '.join(_number(value) for value in without['cycles_per_second_all_runs'])} |",
        f"| CAN lockstep, every frame and sample logged | {_number(logged['cycles_per_second'])} | "
        f"{', '.join(_number(value) for value in logged['cycles_per_second_all_runs'])} |",
        f"| loop alone, in-memory drive | {_number(loop['cycles_per_second'])} | - |",
    ]


def _lockstep_profile(results: dict[str, Any]) -> list[str]:
    """Where each microsecond of a lockstep cycle goes, before and after (``benchmarks/bench_profile.py``)."""
    profile = results.get("lockstep_profile")
    if profile is None:
        return []
    from benchmarks.bench_profile import markdown

    before, after = profile["load_average"]
    return [
        "## The lockstep profile: where each microsecond of a cycle goes",
        "",
        "One lockstep `run_rig` of the PMSM axis at 1 ms on the embedded emulator (3 trials of 1000 samples), "
        f"*before* on main at `{profile['baseline_commit'][:10]}` (before the lean cyclic path), *after* on this "
        "tree, each in its own process, one after the other. Every stage is the exclusive time of the functions "
        "`benchmarks/bench_profile.py` names for it, per cycle, on the control thread; the timers themselves cost a "
        "fraction of a microsecond per call, which is why the timed sum exceeds the plain cycle below it. "
        f"Load average at the start and end: {before:.2f}, {after:.2f}.",
        "",
        *markdown(profile),
        "",
    ]


def _design_grid(results: dict[str, Any]) -> list[str]:
    """Issue 26's grid: every law x Q-filter x N, seconds against the goal, what each certificate proves."""
    from benchmarks.bench_design_grid import table

    grid = results.get("design_grid")
    if not grid:
        return []
    return [
        "## Certified design at scale",
        "",
        f"One in-process design (`foilc_hil.design.pipeline.build_design`, the CAN loop's one-cycle delay) per cell, "
        f"on {grid['plant']}, the eq. (52) profile stretched to each length; the goal is 2 s at N = 6,000 and 8 s at "
        f"N = 20,000 ({grid['goal_met']} of {grid['goal_cells']} cells with a goal met). *outcome*: what the "
        "certificate proves for the worst plant (nominal and every uncertainty vertex): monotone (the induced 2-norm "
        "of the trial-to-trial map below 1), asymptotic only, or refused (exit 3, with the best bound found); "
        "*method*: how the 2-norm was bounded.",
        "",
        *table(grid),
        "",
    ]


def _science(results: dict[str, Any]) -> list[str]:
    science = results["science"]
    lines = [
        "### Fractional derivative: direct vs zero-padded FFT vs `scipy.signal.lfilter`",
        "",
        "| samples | direct (ms) | FFT (ms) | lfilter (ms) | max abs difference direct - FFT |",
        "|---|---|---|---|---|",
    ]
    for row in science["fractional_derivative"]:
        lines.append(
            f"| {row['samples']} | {row['direct_s'] * 1e3:.3f} | {row['fft_s'] * 1e3:.3f} | "
            f"{row['scipy_lfilter_s'] * 1e3:.3f} | {row['max_abs_difference_direct_fft']:.1e} |"
        )
    lines += ["", "### LMI (31) on the paper's plant: CLARABEL vs SCS", ""]
    lines += ["| requested | solved by | seconds | gamma | fallback |", "|---|---|---|---|---|"]
    for row in science["lmi_synthesis"]:
        fallback = "; ".join(row["fallbacks"]) or "-"
        lines.append(
            f"| {row['requested_solver']} | {row['solved_by']} | {row['seconds']:.3f} | {row['gamma']:.4f} | "
            f"{fallback} |"
        )
    return lines


def render(results: dict[str, Any]) -> str:
    """The whole page."""
    jit = results["physics"]["jit"]
    lines = [
        "# Benchmarks",
        "",
        "<!-- generated by `make bench` from benchmarks/results.json; do not edit by hand -->",
        "",
        INTRO,
        *_machine(results),
        "",
        "## Project against peers, and the issue's goals",
        "",
        *comparison_table(results["comparisons"]),
        "",
        "## Compiled physics: what the JIT costs",
        "",
        "The kernels (`plant_emulator/physics/kernels.py`) are compiled by numba with `cache=True` and run once at "
        "import, so no control loop pays for compilation. A fresh process with an empty numba cache imported them "
        f"in {jit['first_import_compiles_s']:.2f} s (compiling); with the cache filled, in "
        f"{jit['cached_import_s']:.2f} s (numba's own import included).",
        "",
        "## Lockstep loop over CAN, with and without logging",
        "",
        *_lockstep(results),
        "",
        *_lockstep_profile(results),
        "## Science",
        "",
        *_science(results),
        "",
        *_design_grid(results),
        *_realtime(),
        *MEASURED_OUTSIDE,
        *_missed(results),
    ]
    return "\n".join(lines)


#: For each goal this page can miss: what bounds the figure, and what was tried. Matched on the start of a row's
#: target; a missed row without an entry says so (the table is then out of date, not the reader).
MISSED_WHY: dict[str, tuple[str, str]] = {
    "foilc-hil synthesize --config configs/paper_sim.yaml --json, whole command": (
        "the imports of the libraries the design uses: a new process that only imports them takes the peer's "
        "figure, more than the goal; the design step itself is the row above it",
        "the design step from 20.8 s to under 0.7 s (the certificates from the Toeplitz symbol, the LMI in standard "
        "form); the lazy command registry (a command imports its own modules only)",
    ),
    "lockstep foilc-hil run, PMSM axis at 1 ms": (
        "the Python of a cycle, spread thin: the profile above has no stage over a quarter of the cycle (the "
        "in-process transport's copies, the emulator's SYNC consumer and PDO engine, the master's RPDO and SYNC, the "
        "receive dispatch, the bench's bookkeeping); counted with sys.setprofile over one run, a cycle makes about 248 "
        "Python and C calls (four frames built, copied, routed and decoded; the object store read 5 times and written "
        "4; 15 lock round trips): the cost is in their number, not in one of them",
        "a synchronous in-process transport without threads; direct routes for the cyclic COB-IDs past canopen's "
        "listener chain; compiled law step and PMSM physics called without numba's dispatcher; frames built without "
        "Message.__init__; the rate counted from the loop's first cycle, not from before the commissioning",
    ),
    "frames written per second": (
        "the per-frame Python of the row the writer keeps (about 15 operations against BLF's 40 for its whole path) "
        "and the host: the margin over BLFWriter is 20 to 30 % in quiet runs, within the run-to-run spread of either",
        "a compiled kernel for a batch's records and JSON; the timestamps' repr by C loops; orjson, then templates "
        "(0.58x) before that",
    ),
    "robustness target": (
        "NOILC's per-draw certificate: one Cholesky test of the frozen plant's N x N trial map (0.18 s of NOILC's "
        "0.38 s a draw at N = 2000, one process, cProfile; FOILC and IOILC take 0.04 s a draw), so the 1,000 draws "
        "cost about 0.45 CPU-s each on two cores that the host shares; a measured 1,000-draw run on a quiet machine "
        "took 230 s (docs/robustness.md)",
        "per-draw certificates by an FFT map and a Cholesky bound instead of SVD; the NOILC gain transformed once per "
        "chunk; NOILC's bound through the plant's transfer function and the gain's Gram (0.72 -> 0.375 s a draw); "
        "16 chunks per worker and law; the workers without Dask's MALLOC_TRIM_THRESHOLD_",
    ),
    "CAN lockstep throughput with every frame and sample logged": (
        "a second process sharing two cores with the loop and the emulator; the spread of the runs is wider than "
        "the goal's margin",
        "a writer process fed marshal batches, reading on its own clock in SCHED_BATCH; columns per trial for the "
        "samples; a compiled kernel for the frames' records; in the writer process, a batch's frames as columns and "
        "their documents by C loops (9.5 -> 5.3 us a frame); a trial's sample rows as one batch built from its "
        "columns (13.0 -> 4.0 us a row) and zstd at level 1 (1.4x faster, the same ratio)",
    ),
}
#: The realtime targets: one bound and one list of attempts for all (benchmarks.realtime's host floor section).
REALTIME_WHY = (
    "the host: a FIFO process that only sleeps to 1 ms deadlines, even with the PM QoS request held, wakes more "
    "than 1 ms late in the share the floor lines above give, and a cycle waits on three wake-ups in series; CPU "
    "steal of the virtual machine; misses come in bursts (in one 3-trial run 90, 10 and 65 per trial)",
    "a receive path on the loop's thread (no Notifier hand-off); SYNC anticipation in the emulator; gc frozen and "
    "off during trials; opt-in SCHED_FIFO, CPU affinity and mlockall; a spin tail; missed deadlines counted, never "
    "fatal; the watchdog on unanswered SYNCs. Spinning the whole period instead of sleeping (the bench's deadline and "
    "receive waits, the emulator's SYNC window, or both; 2 runs each, 2 trials at time scale 0.4): the emulator's "
    "answer p99 fell from 0.9-1.3 ms to 0.2 ms, but the FIFO spinners starved their processes' other threads, and "
    "all 6 runs aborted (the heartbeat lost, or 21 SYNCs unanswered around the between-trial update); spinning half "
    "of it (a 0.5 ms spin tail, 0.6 ms receive spin, a 0.4 ms SYNC window): 3 of 3 runs aborted, 21 SYNCs "
    "unanswered; the shipped settings missed 6.8 to 21 % of deadlines in the same session (7 runs). Then (session 11) "
    "the CPUs' idle states: a PM QoS request of 0 us on /dev/cpu_dma_latency for the run (cpu_latency_us, shipped): "
    "quiet, missed deadlines 11.13 -> 2.95 % (in quick A/B pairs 9.4-12.7 % -> 0.3-3.2 %), the host floor's "
    "wake-ups later than 1 ms 2.39 % (session 10, without it) -> 0.16 %; with the spins off as well (receive "
    "spin, spin tail, SYNC anticipation; 5 pairs) 2.7-13.3 % (median 5.4) against 1.3-4.6 % (median 4.1) "
    "shipped: the spins stay. Session 15: CPU affinity (bench.realtime.cpus and emulator.realtime.cpus: the bench "
    "on CPU 0 and the emulator on CPU 1, or the emulator alone on CPU 1; 6 alternated 3-trial runs of each against "
    "the shipped settings): trial-cycle misses median 0.105 and 0.07 % against 0.15 %, Mann-Whitney p 0.52 and 0.57, "
    "inside the noise, so not shipped; the kernel's softirq threads at SCHED_FIFO 52, above every cyclic thread (3 "
    "alternated pairs): 0.08-0.19 % against 0.01-0.03 %, worse, reverted",
)
#: Figures measured by hand, outside ``make bench`` (this page is their one home: the README, the Makefile and
#: pyproject point here). Update them when a change moves them, with how they were measured.
MEASURED_OUTSIDE = (
    "## Measured outside `make bench`",
    "",
    "Measured by hand on the 2-core test machine, not by `make bench`; wall clock unless said otherwise.",
    "",
    "- **`make demo`** on a fresh clone, the `.venv` bootstrap included: 31.3 s (the demo itself 27.1 s, its design "
    "4.1 s) with the cores to itself; 24.0 s on 2026-11-28 07:13 at load about 1 (29.0 s at 05:19, load about 2); "
    "84.8 s at a load of 6-10 from other "
    "work. The trial is eq. (52) at 1 ms between "
    "two 0.25 s ramps, 6500 samples, 30 trials per law (about 460k CAN cycles); the two laws run at once, each in its "
    "own worker process; the rest is the two reports and `comparison.png`.",
    "- **`make test`** on a fresh clone, the `.venv` bootstrap included: 2 min 58 s on 2026-11-28 07:09 at load "
    "0.5-2 (pytest: 2,498 tests in 132 s, two skipped with their reason: no `vcan0` here); 2 min 59 s at 05:16 "
    "(2,456 tests in 129 s) at load about 2-4; 2 min 19 s (2,320 tests in 117 s) with the cores to itself "
    "in an earlier session; 4 min 3 s and 10 min 6 s at loads of about 6 and 10 from other work beside it. ruff, "
    "mypy, pytest and the API reference at once, pytest on four pytest-xdist workers. CPU-bound: about 300 CPU-s on "
    "two cores.",
    "- **pytest workers** (the Makefile's two per core): a quarter of the suite's test time is waiting (timeouts that "
    "are the point of a test, emulator and CLI processes, a drive's heartbeat); on 2 cores 316 s of test time held "
    "241 CPU-s, and 4 workers took 141-144 s against 156 s for 3, 160-170 s for 2 and 168 s for 6 (an earlier, "
    "smaller suite: 107 s on two workers against about 190 s in one process). With `PYTHONDONTWRITEBYTECODE` set, "
    "every worker re-rewrote every test module (about 3 s of CPU each), which is why the Makefile unexports it.",
    "- **The inner loop**, `OPENBLAS_NUM_THREADS=1 pytest -m \"not slow\" -n 2` (README, \"Development\"): 1,758 "
    "of the suite's 2,458 tests (the `slow` ones left out): 31 s wall and 40 CPU-s on a fresh clone at load about 2 "
    "(2026-11-28 05:20); 74 to 87 s in three runs at a load average of 3.5 to 11 (other sessions' work on the same 2 "
    "cores). The two workers' collection (every test module imported in each) is about 16 CPU-s of it.",
    "- **The bootstrap**: uv installs the `.venv` in about 5 s with its cache warm and 15 s cold, against about a "
    "minute for pip, most of it byte-compiling every module of every package.",
    "- **Commands** (under load, load average 6; Python start-up included): `synthesize` of `paper_sim.yaml` 4 s, "
    "`simulate` of 10 FOILC trials 5 s, `run` of 5 trials of `demo.yaml` (6 s each, lockstep on the embedded "
    "emulator) 23 s, `replay --verify` of that log 4 s, `report` 6 s, `commission info` 3 s.",
    "- **`make bench-realtime`**: about 10 minutes (root, a private network namespace): the 1 kHz runs, the peers "
    "and the producers alone (6 alternated rounds per condition, since session 15) 420 s, the four-axes runs (5 "
    "rounds of both topologies) 161 s, on 2026-11-28 08:37 at load about 1; before the alternated rounds the 1 kHz "
    "part took about 290 s.",
    "",
)
#: Goals measured outside ``make bench`` (their figures: :data:`MEASURED_OUTSIDE`).
OUTSIDE = (
    "- **`make test` under 3 minutes on 2 cores** (measured outside `make bench`, figures above): met with little "
    "room, so a slower host can miss it. Bounded by CPU: the run is CPU-bound on two cores (mypy's cold run, numba's "
    "first compilation of the kernels and one test "
    "collection come before or beside pytest, and many tests are whole bench runs with their processes). Tried: "
    "pytest-xdist with two workers per core (a quarter of the tests' time is waiting), the caches filled once before "
    "the workers start, a uv bootstrap, the log writer's child without python-can, one compiled overload per kernel, "
    "the dense reference maps by indexing; then a parsed EDS kept per process (651 parses of 17 ms), the P-type "
    "grid response in one stacked solve, the LMI handed to cvxpy in standard form (a solve 134 -> 43 ms).",
)


def _shortfall(row: dict[str, Any]) -> str:
    """By how much a row misses its goal, from its medians."""
    parts = []
    ratio, min_ratio, limit = row["ratio"], row.get("min_ratio"), row.get("limit")
    if min_ratio is not None and (ratio is None or ratio < min_ratio):
        parts.append(f"ratio {ratio:.2f}x against {min_ratio:g}x" if ratio is not None else "no ratio")
    median = row["project"]["median"]
    if limit is not None and (median < limit if row["higher_is_better"] else median > limit):
        parts.append(f"{_number(median)} against {_number(limit)} {row['unit']} ({100 * abs(median / limit - 1):.0f} % "
                     f"{'short' if row['higher_is_better'] else 'over'})")
    return "; ".join(parts) or f"goal {row['goal']}"


def _missed(results: dict[str, Any]) -> list[str]:
    """Every missed goal: by how much, what bounds it, what was tried."""
    lines = ["## Missed targets", ""]
    for row in results["comparisons"]:
        if row["met"] is not False:
            continue
        why = next((text for prefix, text in MISSED_WHY.items() if row["target"].startswith(prefix)), None)
        bound, tried = why or ("not described: add it to benchmarks.report.MISSED_WHY", "-")
        lines.append(f"- **{row['target']}**: {_shortfall(row)}. Bounded by {bound}. Tried: {tried}.")
    if REALTIME_RESULTS.exists():
        from benchmarks.realtime import cell, targets

        for row in targets(orjson.loads(REALTIME_RESULTS.read_bytes())):
            if not row["met"]:
                own = row["bench"]
                unit = " us" if "p99" in row["target"] else ""
                shown = f"{100 * own:.2f} %" if row["target"].startswith("missed deadlines") else cell(own) + unit
                figures = shown + (f" against the peer's {cell(row['peer'])}{unit}" if row["peer"] else "")
                lines.append(f"- **realtime, {row['condition']}: {row['target']}**: {figures}.")
        lines.append(f"- The realtime targets above are bounded by {REALTIME_WHY[0]}. Tried: {REALTIME_WHY[1]}.")
    if AXES_RESULTS.exists():
        from benchmarks.realtime_axes import targets as axes_targets

        lines += [f"- **four axes, {row['condition']}: {row['target']}**: {row['bench']}."
                  for row in axes_targets(orjson.loads(AXES_RESULTS.read_bytes())) if not row["met"]]
    return [*lines, *OUTSIDE, ""]


REALTIME_RESULTS = Path(__file__).with_name("realtime.json")
AXES_RESULTS = Path(__file__).with_name("realtime_axes.json")  # make bench-realtime's four-axes runs


def _realtime() -> list[str]:
    """The realtime section from the last ``make bench-realtime`` (about 10 minutes in a private network namespace, so
    not part of ``make bench``); nothing when it was never run."""
    if not REALTIME_RESULTS.exists():
        return []
    from benchmarks.realtime import markdown

    note = ("*From `make bench-realtime` (`benchmarks/realtime.json`), a separate run: its date is its own, not "
            "this page's.*")
    section = [note, "", markdown(orjson.loads(REALTIME_RESULTS.read_bytes())), ""]
    if AXES_RESULTS.exists():
        from benchmarks.realtime_axes import markdown as axes_markdown

        section += ["*From `make bench-realtime` (`benchmarks/realtime_axes.json`).*", "",
                    axes_markdown(orjson.loads(AXES_RESULTS.read_bytes())), ""]
    return section


def write(results_path: Path, doc_path: Path) -> None:
    """Render ``results_path`` into ``doc_path``."""
    doc_path.write_text(render(orjson.loads(results_path.read_bytes())), encoding="utf-8")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.report", description=__doc__)
    parser.add_argument("--results", default="benchmarks/results.json")
    parser.add_argument("--doc", default="docs/benchmarks.md")
    args = parser.parse_args(argv)
    write(Path(args.results), Path(args.doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
