"""``docs/paper-reproduction.md`` regenerated from fresh runs: the generated blocks of the page, never typed by hand.

``python -m benchmarks.reproduction --robustness DIR/robustness.json --update-doc docs/paper-reproduction.md``

- ``paper-table``: every law (co-designed FOILC, IOILC, the fair P-type, NOILC, gradient) on
  ``configs/paper_sim.yaml`` over at least 20 seeds (:mod:`benchmarks.seed_study`: each seed moves the sensor
  noise and the phases of the time-varying parameters and of the disturbance): per law the spread of each figure
  over the seeds, and the paper's two claims judged seed by seed (:mod:`benchmarks.verdicts`: "holds", "fails" or
  "a tie", by the rule the page states);
- ``demo-table``: the same on the demo axis, ``configs/demo.yaml`` (the PMSM with its drive's loops);
- ``robustness``: the distributions of a ``foilc-hil robustness --json`` document (quantiles per law and figure) and
  a verdict on each claim the Monte Carlo can test, whichever way it falls.

Each block sits between ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``; the prose around them is kept. The times
in each block's first line are measured by the run that wrote it. A docs generator, not product code: it lives
outside the package (issue 27) and nothing in ``foilc_hil`` imports it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.seed_study import LawStudy, PlantStudy, RunFigures, StudySettings, moved_signals, run_study
from benchmarks.verdicts import RELEVANCE, RULE, PairedJudgement, Verdict, combine, judge, sign_test_p, spread
from foilc_hil.config import Config, LawKind
from foilc_hil.errors import FoilcHilError, InputError

__all__ = ["MIN_SEEDS", "claims_lines", "robustness_block", "seed_block", "update_blocks"]

#: The fewest seeds a verdict is given on (issue 26: "at least 20 seeds").
MIN_SEEDS = 20


# --- the seed blocks ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FigureRow:
    """One figure of the seed tables: its heading (``{start}``, ``{before}``: the disturbance trial and the one before
    it), its number format, how it is read from a run, and the claim it decides (empty: shown, not a claim)."""

    heading: str
    spec: str
    read: Callable[[RunFigures], float]
    claim: str = ""

    def title(self, start: int) -> str:
        return self.heading.format(start=start, before=start - 1)


FIGURES = (
    FigureRow("trials to tolerance", "g", lambda run: run.trials_to_tolerance, "1"),
    FigureRow("learnable RMSE, trial 3", ".3g", lambda run: run.rmse_trial_3),
    FigureRow("transient SSE, trials 2-{before}", ".3g", lambda run: run.transient_sse, "2a"),
    FigureRow("SSE, trial {start}", ".3g", lambda run: run.disturbance_sse, "2b"),
    FigureRow("SSE added in trial {start} (trial {start} - trial {before})", ".3g", lambda run: run.disturbance_jump),
    FigureRow("trials after {start} to tolerance", "g", lambda run: run.recovery_trials),
    FigureRow("final learnable RMSE", ".3g", lambda run: run.final_rmse),
)


def _finite(values: Sequence[float]) -> list[float]:
    return [value for value in values if math.isfinite(value)]


def _design_table(study: PlantStudy) -> list[str]:
    """Each law's design (once, seed-independent) and where this run's time went."""

    def cell(value: float | None, spec: str = ".4g") -> str:
        return "-" if value is None else format(value, spec)

    lines = [
        "| law | kp, r | spectral radius | 2-norm | gamma | gain_scale | design [s] | runs [s] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for law in study.laws:
        if law.refused:
            lines.append(f"| {law.law} | no design: {law.refused} | | | | | {law.design_seconds:.1f} | |")
            continue
        pair = "-" if law.kp is None else f"{law.kp:.4g}, {law.r:.4g}" if law.kp else "0 (integer order)"
        lines.append(
            f"| {law.law} | {pair} | {cell(law.spectral_radius)} | {cell(law.norm_2)} | {cell(law.gamma)} | "
            f"{cell(law.gain_scale)} | {law.design_seconds:.1f} | {law.run_seconds:.1f} |"
        )
    return lines


def _spread_table(study: PlantStudy) -> list[str]:
    """Per law and figure: median [5 %, 95 %] over the seeds."""
    start = study.settings.disturbance_trial
    lines = [
        "| law | " + " | ".join(row.title(start) for row in FIGURES) + " | stopped early |",
        "|---" * (len(FIGURES) + 2) + "|",
    ]
    for law in study.laws:
        if law.refused:
            continue
        cells = []
        for row in FIGURES:
            values = _finite([row.read(run) for run in law.runs])
            cells.append(spread(values).text(row.spec) if values else "-")
        stopped = sum(1 for run in law.runs if run.stopped)
        lines.append(f"| {law.law} | " + " | ".join(cells) + f" | {stopped} of {len(law.runs)} |")
    return lines


def _sse_table(study: PlantStudy) -> list[str]:
    """Median learnable SSE by trial over the seeds."""
    trials = study.settings.trials
    lines = ["| law | " + " | ".join(str(k) for k in range(1, trials + 1)) + " |", "|---" * (trials + 1) + "|"]
    for law in study.laws:
        if law.refused:
            continue
        cells = []
        for k in range(trials):
            values = [run.sse_by_trial[k] for run in law.runs if len(run.sse_by_trial) > k]
            cells.append(f"{float(np.median(values)):.3g}" if values else "-")
        lines.append(f"| {law.law} | " + " | ".join(cells) + " |")
    return lines


def _paired(foilc: LawStudy, ioilc: LawStudy, row: FigureRow) -> PairedJudgement | None:
    """The paired judgement of ``row`` over the seeds where both laws have the figure (a run that stopped early
    lacks the trials it did not run)."""
    pairs = [(row.read(f), row.read(i)) for f, i in zip(foilc.runs, ioilc.runs, strict=True)]
    kept = [(f, i) for f, i in pairs if math.isfinite(f) and math.isfinite(i)]
    if len(kept) < 2:
        return None
    return judge([f for f, _ in kept], [i for _, i in kept])


def _why_a_tie(judgement: PairedJudgement, row: FigureRow, foilc: LawStudy, ioilc: LawStudy) -> str:
    """What a tie rests on, where the rule's reason is not the spread: unanimous seeds under the relevance floor, or
    a tolerance neither law reaches."""
    if judgement.verdict is not Verdict.TIE:
        return ""
    if row.claim == "1" and not any(run.reached for run in (*foilc.runs, *ioilc.runs)):
        return " (neither law gets within tolerance on any seed: this figure cannot separate them)"
    low, high = judgement.interval
    if low > 0 or high < 0:
        side = "better" if high < 0 else "worse"
        share = abs(judgement.difference.median) / abs(judgement.reference) if judgement.reference else math.inf
        return (
            f" (consistent in sign: FOILC {side} on {judgement.better if high < 0 else judgement.worse} of "
            f"{judgement.n} seeds, but by {100 * share:.2g} % of IOILC's median, under the "
            f"{100 * RELEVANCE:.0f} % floor)"
        )
    return ""


def _claims_table(
    study: PlantStudy, foilc: LawStudy, ioilc: LawStudy
) -> tuple[list[str], dict[str, Verdict], dict[str, str]]:
    """Every figure judged FOILC against IOILC, seed by seed; the verdicts of the figures that decide a claim, and
    what a tied one rests on."""
    start = study.settings.disturbance_trial
    lines = [
        "| claim | figure | seeds | d = FOILC - IOILC: median [5 %, 95 %] | 95 % interval of the median of d | "
        "IOILC's median | FOILC better / equal / worse | sign test p | verdict |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    verdicts: dict[str, Verdict] = {}
    notes: dict[str, str] = {}
    for row in FIGURES:
        judgement = _paired(foilc, ioilc, row)
        claim = row.claim or "(shown)"
        if judgement is None:
            lines.append(f"| {claim} | {row.title(start)} | fewer than 2 | | | | | | {Verdict.TIE} |")
            verdicts[row.claim], notes[row.claim] = Verdict.TIE, " (fewer than 2 seeds with this figure)"
            continue
        low, high = judgement.interval
        lines.append(
            f"| {claim} | {row.title(start)} | {judgement.n} | {judgement.difference.text('.3g')} | "
            f"[{low:.3g}, {high:.3g}] | {judgement.reference:.3g} | {judgement.better} / {judgement.equal} / "
            f"{judgement.worse} | {sign_test_p(judgement.better, judgement.worse):.2g} | {judgement.verdict} |"
        )
        verdicts[row.claim], notes[row.claim] = judgement.verdict, _why_a_tie(judgement, row, foilc, ioilc)
    return lines, verdicts, notes


def claims_lines(study: PlantStudy) -> list[str]:
    """The paper's two claims on ``study``, judged by the paired rule (:data:`benchmarks.verdicts.RULE`)."""
    foilc, ioilc = study.law(LawKind.FOILC), study.law(LawKind.IOILC)
    if foilc is None or ioilc is None:
        return ["- not checkable: FOILC or IOILC has no design (see above)."]
    table, verdicts, notes = _claims_table(study, foilc, ioilc)
    n, start = len(foilc.runs), study.settings.disturbance_trial
    by_third = sum(1 for run in foilc.runs if run.reached and run.trials_to_tolerance <= 3)
    after_fourth = sum(1 for run in ioilc.runs if run.trials_to_tolerance > 4)
    transient, disturbance = verdicts["2a"], verdicts["2b"]
    same_order = " FOILC's co-design chose `kp = 0` on this plant: both laws are integer-order." if not foilc.kp else ""
    return [
        *table,
        "",
        f'- **Claim 1**, "FOILC tracks by the 3rd cycle, IOILC needs more than 4": FOILC within tolerance by trial 3 '
        f"on {by_third} of {n} seeds, IOILC still outside it after trial 4 on {after_fourth} of {n}; trials to "
        f"tolerance, seed by seed -> **{verdicts['1']}**{notes['1']}.",
        f'- **Claim 2**, "FOILC has better transients and is more robust to the disturbance from cycle {start}": '
        f"transient SSE (2a) {transient}{notes['2a']}, SSE of trial {start} (2b) {disturbance}{notes['2b']} -> "
        f"**{combine([transient, disturbance])}** (both parts must hold).{same_order}",
    ]


def _reference_span(config: Config) -> float:
    from foilc_hil.references import reference_profile

    reference = reference_profile(config.reference, config.sample_time)
    return float(np.max(reference) - np.min(reference)) or float(np.max(np.abs(reference))) or 1.0


def seed_block(study: PlantStudy, total_seconds: float) -> str:
    """The block of one plant: what the seeds move, the designs, the spread per law, the medians by trial and the
    claims; its first line carries this run's wall times (``total_seconds``: the whole generation)."""
    from foilc_hil.references import trial_samples

    s, config = study.settings, study.config
    span = _reference_span(config)
    noise = (
        "the config's `plant.output_noise`" if config.plant.output_noise > 0
        else f"{100 * s.noise / span:.2g} % of the reference range, added for this study: the config has none"
    )
    designs = ", ".join(f"{law.law} {law.design_seconds:.1f} s" for law in study.laws)
    runs = sum(len(law.runs) for law in study.laws)
    run_seconds = sum(law.run_seconds for law in study.laws)
    lines = [
        f"This run: {study.seconds:.1f} s wall for this block (designs, once per law: {designs}; {runs} runs: "
        f"{run_seconds:.1f} s), {total_seconds:.1f} s for the whole generation.",
        "",
        f"{len(s.seeds)} seeds ({s.seeds[0]}-{s.seeds[-1]}), {s.trials} trials of "
        f"{trial_samples(config.reference, config.sample_time)} samples per run. Each seed moves the sensor noise "
        f"(`plant.noise_seed`; std {s.noise:g}, {noise}), {', '.join(moved_signals(config))}; every law runs the "
        f"same seeds. Tolerance: learnable RMSE < {s.tolerance:g} ({s.tolerance / span:.0%} of the reference range "
        f"{span:g}); disturbance from trial {s.disturbance_trial}. A run that never gets within tolerance counts as "
        f"one trial past the last.",
        "",
        *_design_table(study),
        "",
        "Per law over the seeds, median [5 %, 95 %] (SSE and RMSE over the learnable samples):",
        "",
        *_spread_table(study),
        "",
        "Median learnable SSE by trial:",
        "",
        *_sse_table(study),
        "",
        "The paper's claims, FOILC against IOILC seed by seed. The rule (`benchmarks/verdicts.py`): " + RULE,
        "",
        *claims_lines(study),
    ]
    return "\n".join(lines) + "\n"



# --- the robustness block -----------------------------------------------------------------------------------------

#: The figures of the robustness table: (key, heading, format).
_FIGURES = (
    ("norm_2", "certified 2-norm (frozen plant)", ".4g"),
    ("trials_to_tolerance", "trials to tolerance", "g"),
    ("final_rmse", "final learnable RMSE", ".3g"),
    ("noise_floor", "noise floor", ".3g"),
)


@dataclass(frozen=True)
class LawSummary:
    """What the verdicts read from one law of a robustness document."""

    law: str
    median_trials: float | None
    worst_trials: float | None
    median_floor: float | None
    divergence_rate: float
    monotonic_rate: float
    reached_rate: float

    @classmethod
    def from_json(cls, document: dict[str, Any]) -> LawSummary:
        return cls(
            law=document["law"],
            median_trials=document["trials_to_tolerance"]["0.5"],
            worst_trials=document["trials_to_tolerance"]["worst"],
            median_floor=document["noise_floor"]["0.5"],
            divergence_rate=float(document["divergence_rate"]),
            monotonic_rate=float(document["monotonic_rate"]),
            reached_rate=float(document["reached_rate"]),
        )


def _cell(value: Any, spec: str) -> str:
    return "never" if value is None else format(value, spec)


def _table(document: dict[str, Any]) -> list[str]:
    head = "| law | figure | worst | median | q0.9 | q0.99 |"
    lines = [head, "|---|---|---|---|---|---|"]
    for law in document["laws"]:
        for key, name, spec in _FIGURES:
            q = law[key]
            cells = " | ".join(_cell(q[k], spec) for k in ("worst", "0.5", "0.9", "0.99"))
            lines.append(f"| {law['law']} | {name} | {cells} |")
        lines.append(
            f"| {law['law']} | diverged / monotonic / within tolerance | "
            f"{100 * law['divergence_rate']:.1f} % | {100 * law['monotonic_rate']:.1f} % | "
            f"{100 * law['reached_rate']:.1f} % | |"
        )
    return lines


def _verdicts(laws: dict[str, LawSummary], trials: int) -> list[str]:
    """The claims the Monte Carlo tests, each with its verdict from the numbers (never typed by hand)."""
    foilc, ioilc = laws.get("foilc"), laws.get("ioilc")
    if foilc is None or ioilc is None:
        return ["- not checkable: the document has no FOILC or IOILC run."]
    out = []
    robust = foilc.divergence_rate == 0 and foilc.monotonic_rate == 1 and foilc.reached_rate == 1
    out.append(
        f'- "FOILC converges robustly over the uncertainty set" (Theorems 1-2): diverged on '
        f"{100 * foilc.divergence_rate:.1f} % of the draws, certified monotonic on {100 * foilc.monotonic_rate:.1f} %, "
        f"within tolerance by trial {trials} on {100 * foilc.reached_rate:.1f} % -> "
        f"{'holds on these draws' if robust else 'does not hold'}."
    )
    fast = foilc.median_trials is not None and foilc.median_trials <= 3
    slow = ioilc.median_trials is None or ioilc.median_trials > 4
    out.append(
        f'- "FOILC tracks by the 3rd cycle, IOILC needs more than 4", over the draws: median trials to tolerance '
        f"{_cell(foilc.median_trials, 'g')} (FOILC) vs {_cell(ioilc.median_trials, 'g')} (IOILC) -> "
        f"{'holds' if fast and slow else 'does not hold'}."
    )
    if foilc.median_floor is not None and ioilc.median_floor is not None and foilc.median_floor > 0:
        ratio = ioilc.median_floor / foilc.median_floor
        verdict = "FOILC lower" if ratio > 1.05 else "IOILC lower" if ratio < 1 / 1.05 else "no difference beyond 5 %"
        out.append(
            f"- The fractional order lowers the noise floor (issue 11's one measured benefit): median noise floor "
            f"{foilc.median_floor:.3g} (FOILC) vs {ioilc.median_floor:.3g} (IOILC), ratio {ratio:.3g} -> {verdict}."
        )
    return out


def robustness_block(document: dict[str, Any], source: str) -> str:
    """The ``robustness`` block of the page from a ``robustness --json`` document read from ``source``."""
    try:
        laws = {law["law"]: LawSummary.from_json(law) for law in document["laws"]}
    except (KeyError, TypeError) as exc:
        raise InputError(f"--robustness: {source} is not a robustness --json document (missing {exc})") from None
    lines = [
        f"From `{source}`: {document['draws']} plants ({document['vertices']} box corners, {document['samples']} "
        f"random, seed {document['seed']}), every law {document['trials']} trials of {document['n_samples']} samples, "
        f"sensor noise {document['noise']:g}, tolerance {document['tolerance']:g} on the learnable RMSE; "
        f"{document['workers']} Dask workers, {document['seconds']:.0f} s.",
        "",
        *_table(document),
        "",
        "Verdicts on these draws:",
        "",
        *_verdicts(laws, int(document["trials"])),
    ]
    return "\n".join(lines) + "\n"



# --- the page -----------------------------------------------------------------------------------------------------


def _replace(text: str, name: str, body: str, command: str) -> str:
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    if begin not in text or end not in text:
        raise InputError(f"the page has no {begin} ... {end} markers")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    stamp = f"<!-- generated by `{command}`; do not edit by hand -->"
    return f"{head}{begin}\n{stamp}\n\n{body}\n{end}{tail}"


def update_blocks(page: Path, blocks: dict[str, str], command: str) -> None:
    """Write each ``{name: body}`` between its markers in ``page``."""
    try:
        text = page.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{page}: cannot read: {exc}") from None
    for name, body in blocks.items():
        text = _replace(text, name, body, command)
    page.write_text(text, encoding="utf-8")


#: The tolerance, as a fraction of the reference range.
TOLERANCE_FRACTION = 0.01


def _settings(config: Config, source: str, args: argparse.Namespace, trials: int | None) -> StudySettings:
    """The study of one plant from the command line and its config (exit 2 for what cannot be judged)."""
    if config.plant.disturbance.kind == "none":
        raise InputError(f"{source}: plant.disturbance.kind: the paper's claim 2 needs a disturbance, got 'none'")
    start = config.plant.disturbance.start_trial
    count = config.trials if trials is None else trials
    if count < max(start, 3):
        raise InputError(f"--trials: {source} needs at least {max(start, 3)} (disturbance from trial {start})")
    span = _reference_span(config)
    noise = config.plant.output_noise if config.plant.output_noise > 0 else args.noise_fraction * span
    return StudySettings(
        seeds=tuple(range(args.first_seed, args.first_seed + args.seeds)),
        trials=count,
        tolerance=TOLERANCE_FRACTION * span,
        noise=noise,
        disturbance_trial=start,
        laws=args.laws,
    )


def _laws(text: str) -> tuple[LawKind, ...]:
    try:
        return tuple(LawKind(name.strip()) for name in text.split(",") if name.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a comma list of {', '.join(LawKind)}") from None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.reproduction", description=__doc__)
    parser.add_argument("--paper-config", default="configs/paper_sim.yaml")
    parser.add_argument("--demo-config", default="configs/demo.yaml")
    parser.add_argument("--seeds", type=int, default=30, help=f"seeds per plant (at least {MIN_SEEDS})")
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--paper-trials", type=int, default=None, help="trials per run on paper_sim (config's)")
    parser.add_argument("--demo-trials", type=int, default=None, help="trials per run on the demo axis (config's)")
    parser.add_argument(
        "--noise-fraction", type=float, default=0.002,
        help="sensor noise std as a fraction of the reference range, where the config has no noise",
    )
    parser.add_argument("--laws", type=_laws, default=tuple(LawKind), help="comma list (default: every law)")
    parser.add_argument("--robustness", default=None, metavar="JSON", help="a `foilc-hil robustness --json` document")
    parser.add_argument("--update-doc", default=None, metavar="FILE", help="write the blocks into FILE's markers")
    parser.add_argument("--skip-tables", action="store_true", help="only the robustness block (no simulation runs)")
    return parser


def _studies(args: argparse.Namespace) -> dict[str, PlantStudy]:
    from foilc_hil.config import load_config

    if args.seeds < MIN_SEEDS:
        raise InputError(f"--seeds: must be at least {MIN_SEEDS}, got {args.seeds}")
    if not math.isfinite(args.noise_fraction) or args.noise_fraction <= 0:
        raise InputError(f"--noise-fraction: must be > 0, got {args.noise_fraction}")
    studies = {}
    for name, path, trials in (
        ("paper-table", args.paper_config, args.paper_trials),
        ("demo-table", args.demo_config, args.demo_trials),
    ):
        config = load_config(path)
        settings = _settings(config, path, args, trials)
        studies[name] = run_study(config, settings, _progress(name))
    return studies


def _progress(block: str) -> Callable[[str], None]:
    """A progress line per law on stderr (the runs take minutes)."""

    def say(line: str) -> None:
        sys.stderr.write(f"{block}: {line}\n")

    return say


def main(argv: Sequence[str] | None = None) -> int:
    """Run the seed studies (and read the robustness document), then print the blocks or update the page."""
    began = time.perf_counter()
    args = _parser().parse_args(argv)
    try:
        studies = {} if args.skip_tables else _studies(args)
        total = time.perf_counter() - began
        blocks = {name: seed_block(study, total) for name, study in studies.items()}
        if args.robustness is not None:
            try:
                document = json.loads(Path(args.robustness).read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise InputError(f"--robustness: cannot read {args.robustness}: {exc}") from None
            blocks["robustness"] = robustness_block(document, Path(args.robustness).name)
        if args.update_doc is not None:
            command = " ".join(["python -m benchmarks.reproduction", *(sys.argv[1:] if argv is None else argv)])
            update_blocks(Path(args.update_doc), blocks, command)
    except FoilcHilError as exc:
        sys.stderr.write(f"{exc}\n")
        return int(exc.exit_code)
    sys.stdout.write("\n".join(blocks.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
