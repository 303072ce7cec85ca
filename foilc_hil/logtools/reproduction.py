"""``docs/paper-reproduction.md`` regenerated from fresh runs: the generated blocks of the page, never typed by hand.

``python -m foilc_hil.logtools.reproduction --robustness DIR/robustness.json --update-doc docs/paper-reproduction.md``

- ``paper-table``: every law (co-designed FOILC, IOILC, the fair P-type, NOILC) on ``configs/paper_sim.yaml``
  (:func:`foilc_hil.loop.simulation.paper_table`: trials to tolerance, the disturbance trial, certificates, and the
  paper's two comparative claims checked on the runs);
- ``demo-table``: the same on the demo axis, ``configs/demo.yaml`` (the PMSM with its drive's loops);
- ``robustness``: the distributions of a ``foilc-hil robustness --json`` document (quantiles per law and figure) and
  a verdict on each claim the Monte Carlo can test, whichever way it falls.

Each block sits between ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``; the prose around them is kept.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from foilc_hil.errors import FoilcHilError, InputError

__all__ = ["robustness_block", "update_blocks"]

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


def main(argv: Sequence[str] | None = None) -> int:
    """Run the tables (and read the robustness document), then print them or update the page."""
    from foilc_hil.config import load_config
    from foilc_hil.loop.simulation import paper_table

    parser = argparse.ArgumentParser(prog="python -m foilc_hil.logtools.reproduction", description=__doc__)
    parser.add_argument("--paper-config", default="configs/paper_sim.yaml")
    parser.add_argument("--demo-config", default="configs/demo.yaml")
    parser.add_argument("--robustness", default=None, metavar="JSON", help="a `foilc-hil robustness --json` document")
    parser.add_argument("--update-doc", default=None, metavar="FILE", help="write the blocks into FILE's markers")
    parser.add_argument("--skip-tables", action="store_true", help="only the robustness block (no simulation runs)")
    args = parser.parse_args(argv)
    try:
        blocks: dict[str, str] = {}
        if not args.skip_tables:
            blocks["paper-table"] = paper_table(load_config(args.paper_config))
            blocks["demo-table"] = paper_table(load_config(args.demo_config))
        if args.robustness is not None:
            try:
                document = json.loads(Path(args.robustness).read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise InputError(f"--robustness: cannot read {args.robustness}: {exc}") from None
            blocks["robustness"] = robustness_block(document, Path(args.robustness).name)
        if args.update_doc is not None:
            command = " ".join(["python -m foilc_hil.logtools.reproduction", *(argv or sys.argv[1:])])
            update_blocks(Path(args.update_doc), blocks, command)
    except FoilcHilError as exc:
        sys.stderr.write(f"{exc}\n")
        return int(exc.exit_code)
    sys.stdout.write("\n".join(blocks.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
