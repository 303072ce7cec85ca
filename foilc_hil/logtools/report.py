"""``foilc-hil report``: plots (PNG) and a summary (JSON and Markdown) of one log.

Plots (matplotlib, Agg, no pyplot state): ``outputs.png`` (output by trial with the reference), ``control.png``,
``error.png``, ``sse.png`` (SSE against trial, log scale) and, when the log has ``/timing``, ``timing.png``
(histograms of SYNC lateness and cycle period). The output drawn is ``reference - error`` -- the output at the
reference's instant, whichever sample convention the writer used for ``output`` (the feedback the law saw).

A truncated log is reported as far as it goes; the summary says it is truncated and where.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from foilc_hil.errors import InputError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from foilc_hil.io.mcap_log import LogContents

__all__ = ["MAX_TRIALS_DRAWN", "ReportFiles", "summarize", "write_report"]

#: at most this many trials are drawn per plot (evenly spread, first and last always included)
MAX_TRIALS_DRAWN = 12
_PERCENTILES = (50, 90, 99)


@dataclass(frozen=True)
class ReportFiles:
    """What :func:`write_report` wrote and the summary document."""

    directory: Path
    plots: list[Path]
    summary_json: Path
    summary_markdown: Path
    summary: dict[str, Any]


# --- data ---------------------------------------------------------------------------------------------------------


def _signal(value: Any) -> np.ndarray:
    """A logged signal (number, list or null) as a 1-D float array (null -> NaN)."""
    if value is None:
        return np.array([math.nan])
    array = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
    return array


def trial_signals(samples: Sequence[Mapping[str, Any]]) -> dict[int, dict[str, np.ndarray]]:
    """Per trial, ``t`` ``(N,)`` and ``reference``/``output``/``control``/``error`` ``(N, width)`` arrays."""
    rows: dict[int, list[Mapping[str, Any]]] = {}
    for sample in samples:
        rows.setdefault(int(sample["trial"]), []).append(sample)
    signals: dict[int, dict[str, np.ndarray]] = {}
    for trial, trial_rows in sorted(rows.items()):
        if all("sample" in row for row in trial_rows):
            trial_rows = sorted(trial_rows, key=lambda row: int(row["sample"]))
        arrays: dict[str, np.ndarray] = {"t": np.array([float(row["t"]) for row in trial_rows])}
        for name in ("reference", "output", "control", "error"):
            columns = [_signal(row.get(name)) for row in trial_rows]
            width = max(len(column) for column in columns)
            arrays[name] = np.array(
                [np.pad(column, (0, width - len(column)), constant_values=math.nan) for column in columns]
            )
        signals[trial] = arrays
    return signals


def _percentiles(values: Sequence[float | None]) -> dict[str, float] | None:
    finite = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if finite.size == 0:
        return None
    stats = {f"p{p}": float(np.percentile(finite, p)) for p in _PERCENTILES}
    stats["max"] = float(finite.max())
    stats["mean"] = float(finite.mean())
    return stats


def _timing_summary(timing: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    if not timing:
        return None
    return {
        "cycles": len(timing),
        "missed_deadlines": sum(1 for record in timing if record.get("missed")),
        "lateness_us": _percentiles([record.get("lateness_us") for record in timing]),
        "period_us": _percentiles([record.get("period_us") for record in timing if record.get("period_us")]),
        "feedback_latency_us": _percentiles([record.get("feedback_latency_us") for record in timing]),
    }


def summarize(contents: LogContents) -> dict[str, Any]:
    """The summary document: per-trial metrics, design certificates, timing percentiles, truncation."""
    signals = trial_signals(contents.samples)
    completed = contents.completed_trials
    incomplete = [trial for trial in signals if trial not in completed]
    design = contents.design
    design_summary: dict[str, Any] | None = None
    if design is not None:
        keys = ("law", "kp", "r", "gamma", "tau", "theta", "input_delay", "gain_scale", "sample_time")
        design_summary = {key: design[key] for key in keys if key in design}
        design_summary["certificates"] = design.get("certificates", {})
    frames_by_dir = {"tx": 0, "rx": 0}
    for frame in contents.frames:
        frames_by_dir[str(frame.get("dir"))] = frames_by_dir.get(str(frame.get("dir")), 0) + 1
    trials = [
        {key: value for key, value in record.items() if key in ("trial", "sse", "rmse", "max_abs_error")}
        for record in contents.trials
    ]
    return {
        "log": contents.path,
        "truncated": contents.truncated,
        "damage": contents.damage or None,
        "partial": contents.truncated,  # the report covers only what was read before the damage
        "trials": trials,
        "completed_trials": len(completed),
        "incomplete_trials": incomplete,
        "samples": len(contents.samples),
        "frames": frames_by_dir,
        "design": design_summary,
        "timing": _timing_summary(contents.timing),
        "has_config": contents.config_yaml is not None,
    }


# --- plots --------------------------------------------------------------------------------------------------------


def _trials_to_draw(trials: Sequence[int]) -> list[int]:
    if len(trials) <= MAX_TRIALS_DRAWN:
        return list(trials)
    picks = np.unique(np.round(np.linspace(0, len(trials) - 1, MAX_TRIALS_DRAWN)).astype(int))
    return [trials[i] for i in picks]


def _new_figure(rows: int = 1) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(9.0, 3.2 * rows + 0.8), layout="constrained")


def _plot_by_trial(
    signals: dict[int, dict[str, np.ndarray]],
    name: str,
    ylabel: str,
    path: Path,
    title: str,
    with_reference: bool = False,
) -> Path:
    from matplotlib import colormaps

    trials = _trials_to_draw(sorted(signals))
    width = max(signals[trial][name].shape[1] for trial in trials)
    figure = _new_figure(width)
    axes = figure.subplots(width, 1, squeeze=False)[:, 0]
    colors = colormaps["viridis"](np.linspace(0.0, 0.9, len(trials)))
    for channel, ax in enumerate(axes):
        for color, trial in zip(colors, trials, strict=True):
            data = signals[trial]
            if channel < data[name].shape[1]:
                ax.plot(data["t"], data[name][:, channel], color=color, linewidth=1.0, label=f"trial {trial}")
        if with_reference:
            last = signals[trials[-1]]
            ax.plot(last["t"], last["reference"][:, channel], "k--", linewidth=1.2, label="reference")
        ax.set_ylabel(ylabel if width == 1 else f"{ylabel} [{channel}]")
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("t (s)")
    axes[0].set_title(title)
    axes[0].legend(fontsize="small", ncol=2, loc="best")
    figure.savefig(path, dpi=110)
    return path


def _plot_sse(trials: Sequence[Mapping[str, Any]], path: Path, truncated: bool) -> Path:
    figure = _new_figure()
    ax = figure.subplots()
    k = [int(record["trial"]) for record in trials]
    sse = [float(record["sse"]) for record in trials]
    positive = [(trial, value) for trial, value in zip(k, sse, strict=True) if value > 0 and math.isfinite(value)]
    if positive:
        ax.semilogy([p[0] for p in positive], [p[1] for p in positive], "o-")
    ax.set_xlabel("trial")
    ax.set_ylabel("SSE")
    ax.set_title("sum of squared errors by trial" + (" (log truncated)" if truncated else ""))
    ax.grid(True, which="both", alpha=0.3)
    figure.savefig(path, dpi=110)
    return path


def _plot_timing(timing: Sequence[Mapping[str, Any]], path: Path) -> Path:
    figure = _new_figure(2)
    top, bottom = figure.subplots(2, 1)
    lateness = [float(r["lateness_us"]) for r in timing if r.get("lateness_us") is not None]
    periods = [float(r["period_us"]) for r in timing if r.get("period_us")]
    top.hist(lateness, bins=60)
    top.set_xlabel("SYNC lateness (us)")
    top.set_ylabel("cycles")
    top.set_title(f"cycle timing ({len(timing)} cycles, {sum(1 for r in timing if r.get('missed'))} missed)")
    bottom.hist(periods, bins=60)
    bottom.set_xlabel("cycle period (us)")
    bottom.set_ylabel("cycles")
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
    figure.savefig(path, dpi=110)
    return path


# --- markdown -----------------------------------------------------------------------------------------------------


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _markdown(summary: dict[str, Any], plots: Sequence[Path]) -> str:
    lines = [f"# Report: `{summary['log']}`", ""]
    if summary["truncated"]:
        lines += [f"**Truncated log**: {summary['damage']}. Everything before the damage is reported.", ""]
    lines += [
        f"- completed trials: {summary['completed_trials']}",
        f"- samples: {summary['samples']}",
        f"- CAN frames: {summary['frames'].get('tx', 0)} sent, {summary['frames'].get('rx', 0)} received",
    ]
    if summary["incomplete_trials"]:
        lines.append(f"- incomplete trials (no metrics): {', '.join(map(str, summary['incomplete_trials']))}")
    lines.append("")
    if summary["trials"]:
        lines += ["## Trials", "", "| trial | SSE | RMSE | max abs error |", "|---:|---:|---:|---:|"]
        lines += [
            f"| {t['trial']} | {_fmt(t['sse'])} | {_fmt(t['rmse'])} | {_fmt(t['max_abs_error'])} |"
            for t in summary["trials"]
        ]
        lines.append("")
    design = summary["design"]
    if design:
        lines += ["## Design", ""]
        lines += [f"- {key}: {_fmt(value)}" for key, value in design.items() if key != "certificates"]
        certificates = design.get("certificates") or {}
        if certificates:
            lines += ["", "Certificates:", ""]
            lines += [f"- {key}: {_fmt(value)}" for key, value in certificates.items()]
        lines.append("")
    timing = summary["timing"]
    if timing:
        lines += ["## Timing", "", f"{timing['cycles']} cycles, {timing['missed_deadlines']} missed deadlines.", ""]
        lines += ["| quantity | p50 | p90 | p99 | max |", "|---|---:|---:|---:|---:|"]
        for key in ("lateness_us", "period_us", "feedback_latency_us"):
            stats = timing.get(key)
            if stats:
                lines.append(
                    f"| {key} | {_fmt(stats['p50'])} | {_fmt(stats['p90'])} | {_fmt(stats['p99'])} | "
                    f"{_fmt(stats['max'])} |"
                )
        lines.append("")
    if plots:
        lines += ["## Plots", ""] + [f"![{path.stem}]({path.name})" for path in plots] + [""]
    return "\n".join(lines)


# --- entry point --------------------------------------------------------------------------------------------------


def write_report(log: str | Path, out_dir: str | Path) -> ReportFiles:
    """Read ``log`` and write the plots, ``summary.json`` and ``summary.md`` into ``out_dir``.

    Raises
    ------
    foilc_hil.errors.LogFormatError
        ``log`` is missing or not MCAP.
    foilc_hil.errors.InputError
        ``out_dir`` cannot be created.
    """
    from foilc_hil.io.mcap_log import read_log

    contents = read_log(log)
    directory = Path(out_dir)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out: {directory}: cannot create: {exc.strerror or exc}") from None
    summary = summarize(contents)
    signals = trial_signals(contents.samples)
    plots: list[Path] = []
    if signals:
        tracked = {trial: {**data, "tracked": data["reference"] - data["error"]} for trial, data in signals.items()}
        plots.append(
            _plot_by_trial(tracked, "tracked", "y", directory / "outputs.png", "output by trial", with_reference=True)
        )
        plots.append(_plot_by_trial(signals, "control", "u", directory / "control.png", "control by trial"))
        plots.append(_plot_by_trial(signals, "error", "e", directory / "error.png", "tracking error by trial"))
    if contents.trials:
        plots.append(_plot_sse(contents.trials, directory / "sse.png", contents.truncated))
    if contents.timing:
        plots.append(_plot_timing(contents.timing, directory / "timing.png"))
    summary["plots"] = [path.name for path in plots]
    summary_json = directory / "summary.json"
    summary_md = directory / "summary.md"
    summary_json.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    summary_md.write_text(_markdown(summary, plots), encoding="utf-8")
    return ReportFiles(directory, plots, summary_json, summary_md, summary)
