"""``foilc-hil report``: plots (PNG) and a summary (JSON and Markdown) of one log; the demo's comparison figure.

Plots (matplotlib, Agg, no pyplot state): ``outputs.png`` (output by trial with the reference), ``control.png``,
``error.png``, ``sse.png`` (SSE and learnable RMSE against trial, log scale) and, when the log has ``/timing``,
``timing.png`` (histograms of SYNC lateness and cycle period) and, when the log's design reads back whole,
``convergence.png`` (:func:`plot_convergence`: the law's trial-to-trial map over frequency against 1, nominal and at
the uncertainty vertices, with the logged config's Q-filter). The output drawn is ``reference - error`` -- the
output at the reference's instant, whichever ``/ilc/sample`` layout the log has. Titles name the law (from the
logged design), axes carry the units of the logged config (``drive.velocity_unit``; ``drive.torque_unit`` for a
CST command). At most :data:`MAX_TRIALS_DRAWN` trials are drawn, coloured along a sequential colormap with a
colorbar (no long legend). Trial 1 runs ``u = 0`` and the first ``input_delay`` samples of every trial are fixed by
the initial condition: neither sets the scale of the control and error plots (they are drawn, clipped; the title
says so), so the learning transient and the converged error stay visible.

:func:`write_comparison` draws several logs side by side (``comparison.png`` of ``foilc-hil demo``): outputs,
learned input and error by trial per law on shared scales, and the learnable RMSE of every law against trial with
the disturbance's first trial marked.

``summary.md`` adds notes for the reader, e.g. why the learned input oscillates at the start of a trial whose
reference starts with a step (see :func:`_notes`).

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

from foilc_hil.errors import FoilcHilError, InputError
from foilc_hil.io.schemas import TOPIC_SAMPLE, TOPIC_TIMING, TOPIC_TRIAL
from foilc_hil.progress import as_step

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from foilc_hil.config import Config
    from foilc_hil.design.frequency_picture import ConvergencePicture
    from foilc_hil.io.mcap_log import LogContents

__all__ = ["MAX_TRIALS_DRAWN", "REPORT_TOPICS", "LogContext", "ReportFiles", "draw_comparison", "frame_directions",
           "log_context", "plot_convergence", "report_of", "summarize", "write_comparison", "write_report"]

#: at most this many trials are drawn per plot (evenly spread, first and last always included)
MAX_TRIALS_DRAWN = 8
#: what a report decodes into lists
REPORT_TOPICS = (TOPIC_SAMPLE, TOPIC_TRIAL, TOPIC_TIMING)
# (the frames are only counted, by direction: read_log's count_frames)
#: the reference steps at the trial's start when the last trial's first (unlearnable) error exceeds this share of
#: the reference's peak and this multiple of the RMS of its learnable errors
STEP_SHARE = 0.1
STEP_OVER_TYPICAL = 10.0
_PERCENTILES = (50, 90, 99)


@dataclass(frozen=True)
class ReportFiles:
    """What :func:`write_report` wrote and the summary document."""

    directory: Path
    plots: list[Path]
    summary_json: Path
    summary_markdown: Path
    summary: dict[str, Any]


@dataclass(frozen=True)
class LogContext:
    """What a log says about how to label its plots: the law, the units, the unlearnable samples, the disturbance."""

    law: str  # e.g. "FOILC"; "law?" when the log has no design
    output_unit: str  # "" when the log has no config
    input_unit: str
    input_delay: int  # leading samples of every trial no input can move
    disturbance_trial: int | None  # first trial with the plant's disturbance; None: none configured


def log_context(contents: LogContents) -> LogContext:
    """The :class:`LogContext` of a log, from its ``foilc_hil.design`` and ``foilc_hil.config`` metadata."""
    design = contents.design or {}
    law = str(design.get("law", "law?")).upper()
    input_delay = int(design.get("input_delay", 0) or 0)
    output_unit = input_unit = ""
    disturbance: int | None = None
    config = _logged_config(contents)
    if config is not None:
        drive = config.drive
        output_unit = drive.velocity_unit
        input_unit = drive.torque_unit if drive.mode == "cst" else drive.velocity_unit
        if config.plant.disturbance.kind != "none":
            disturbance = config.plant.disturbance.start_trial
    return LogContext(law, output_unit, input_unit, input_delay, disturbance)


def _logged_config(contents: LogContents) -> Config | None:
    """The log's config (:func:`~foilc_hil.logtools.replay.logged_config`), or ``None`` when it has none or it
    does not validate (labels only)."""
    from foilc_hil.logtools.replay import logged_config

    try:
        return logged_config(contents)
    except (FoilcHilError, ValueError):  # a label is not worth failing a report for
        return None


def _label(name: str, unit: str) -> str:
    return f"{name} ({unit})" if unit else name


# --- data ---------------------------------------------------------------------------------------------------------


def _signal(value: Any) -> np.ndarray:
    """A logged signal (number, list or null) as a 1-D float array (null -> NaN)."""
    if value is None:
        return np.array([math.nan])
    array = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
    return array


def _column(values: Sequence[Any]) -> np.ndarray:
    """One signal of a trial's rows as an ``(N, width)`` array: one numpy conversion when every row has the same
    shape (a number each, or equal-length lists; null -> NaN), else row by row, short rows padded with NaN."""
    try:
        array = np.array(values, dtype=float)
    except (ValueError, TypeError):  # ragged: rows of different widths, or numbers mixed with lists
        array = np.empty(0)
    if array.ndim == 1 and array.size == len(values):
        return array.reshape(-1, 1)
    if array.ndim == 2 and array.shape[0] == len(values):
        return array
    columns = [_signal(value) for value in values]
    width = max(len(column) for column in columns)
    return np.array([np.pad(column, (0, width - len(column)), constant_values=math.nan) for column in columns])


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
            arrays[name] = _column([row.get(name) for row in trial_rows])
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


def frame_directions(contents: LogContents) -> dict[str, int]:
    """The frames by direction: what the reader counted, else (contents built another way) those in ``frames``."""
    from foilc_hil.io.mcap_log import count_directions

    return dict(contents.frame_directions) if contents.frame_directions else count_directions(contents.frames)


def summarize(contents: LogContents, signals: Mapping[int, Mapping[str, np.ndarray]] | None = None) -> dict[str, Any]:
    """The summary document: per-trial metrics, design certificates, timing percentiles, truncation. ``signals``:
    :func:`trial_signals` of the log's samples when the caller has them (else computed here)."""
    if signals is None:
        signals = trial_signals(contents.samples)
    completed = contents.completed_trials
    incomplete = [trial for trial in signals if trial not in completed]
    design = contents.design
    design_summary: dict[str, Any] | None = None
    if design is not None:
        keys = ("law", "kp", "r", "gamma", "tau", "theta", "input_delay", "gain_scale", "sample_time")
        design_summary = {key: design[key] for key in keys if key in design}
        design_summary["certificates"] = design.get("certificates", {})
    frames_by_dir = {"tx": 0, "rx": 0, **frame_directions(contents)}
    kept = ("trial", "sse", "rmse", "max_abs_error", "rmse_learnable", "max_abs_error_learnable")
    trials = [{key: value for key, value in record.items() if key in kept} for record in contents.trials]
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
        "notes": _notes(signals, log_context(contents)),
    }


# --- plots --------------------------------------------------------------------------------------------------------


def _trials_to_draw(trials: Sequence[int]) -> list[int]:
    if len(trials) <= MAX_TRIALS_DRAWN:
        return list(trials)
    picks = np.unique(np.round(np.linspace(0, len(trials) - 1, MAX_TRIALS_DRAWN)).astype(int))
    return [trials[i] for i in picks]


def _new_figure(rows: int = 1, columns: int = 1) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(6.5 * columns + 2.5, 3.2 * rows + 0.8), layout="constrained")


def _zoomed_limits(
    signals: Mapping[int, Mapping[str, np.ndarray]], name: str, skip: int, channel: int = 0
) -> tuple[float, float] | None:
    """y limits that trial 1 (``u = 0``) and the first ``skip`` (unlearnable) samples do not set; ``None`` when
    nothing else is left to scale by. The error's limits also leave out the 0.5 % most extreme values (the
    learning transient's first samples), so the converged error is not squashed to a line."""
    trials = sorted(signals)
    later = trials[1:] if len(trials) > 1 else trials
    chunks = [signals[trial][name][skip:, channel] for trial in later if signals[trial][name].shape[1] > channel]
    values = np.concatenate(chunks) if chunks else np.array([])
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    if name == "error":
        low, high = (float(v) for v in np.percentile(values, [0.5, 99.5]))
    else:
        low, high = float(values.min()), float(values.max())
    pad = 0.08 * (high - low) or 0.08 * max(abs(high), 1e-12)
    return low - pad, high + pad


def _draw_trials(ax: Any, signals: Mapping[int, Mapping[str, np.ndarray]], name: str, trials: Sequence[int],
                 channel: int = 0) -> Any:
    """The trials along the viridis ramp (early dark, late yellow); returns the colour mapping for a colorbar."""
    from matplotlib import cm, colormaps
    from matplotlib.colors import Normalize

    norm = Normalize(vmin=min(trials), vmax=max(max(trials), min(trials) + 1))
    cmap = colormaps["viridis"]
    for trial in trials:
        data = signals[trial]
        if channel < data[name].shape[1]:
            ax.plot(data["t"], data[name][:, channel], color=cmap(norm(trial)), linewidth=1.0)
    return cm.ScalarMappable(norm=norm, cmap=cmap)


def _plot_by_trial(signals: dict[int, dict[str, np.ndarray]], name: str, ylabel: str, path: Path, title: str,
                   *, with_reference: bool = False, zoom_skip: int | None = None) -> Path:
    """One signal by trial; ``zoom_skip``: scale without trial 1 and the first ``zoom_skip`` samples."""
    trials = _trials_to_draw(sorted(signals))
    width = max(signals[trial][name].shape[1] for trial in trials)
    figure = _new_figure(width)
    axes = figure.subplots(width, 1, squeeze=False)[:, 0]
    mappable = None
    for channel, ax in enumerate(axes):
        mappable = _draw_trials(ax, signals, name, trials, channel)
        if with_reference:
            last = signals[trials[-1]]
            ax.plot(last["t"], last["reference"][:, channel], "k--", linewidth=1.2, label="reference")
            ax.legend(fontsize="small", loc="best")
        limits = _zoomed_limits(signals, name, zoom_skip, channel) if zoom_skip is not None else None
        if limits is not None:
            ax.set_ylim(*limits)
        ax.set_ylabel(ylabel if width == 1 else f"{ylabel} [{channel}]")
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("t (s)")
    zoomed = zoom_skip is not None and len(signals) > 1
    axes[0].set_title(title + (" (scale without trial 1 and the unlearnable first samples)" if zoomed else ""))
    _trial_colorbar(figure, mappable, list(axes))
    figure.savefig(path, dpi=110)
    return path


def _integer_ticks(ax: Any) -> None:
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def _trial_colorbar(figure: Figure, mappable: Any, axes: list[Any]) -> None:
    from matplotlib.ticker import MaxNLocator

    bar = figure.colorbar(mappable, ax=axes, label="trial", shrink=0.8)
    bar.locator = MaxNLocator(integer=True)
    bar.update_ticks()


def _plot_sse(trials: Sequence[Mapping[str, Any]], path: Path, truncated: bool, context: LogContext) -> Path:
    figure = _new_figure()
    ax = figure.subplots()
    for key, label, style in (("sse", "SSE", "o-"), ("rmse_learnable", "learnable RMSE", "s--")):
        points = [(int(r["trial"]), float(r[key])) for r in trials if key in r and math.isfinite(float(r[key]))
                  and float(r[key]) > 0]
        if points:
            ax.semilogy([p[0] for p in points], [p[1] for p in points], style, label=label)
    if context.disturbance_trial is not None:
        ax.axvline(context.disturbance_trial - 0.5, color="0.4", linestyle=":", label="disturbance from here")
    _integer_ticks(ax)
    ax.set_xlabel("trial")
    ax.set_ylabel(_label("SSE, RMSE", context.output_unit + "^2, " + context.output_unit if context.output_unit
                         else ""))
    ax.set_title(f"{context.law}: error by trial" + (" (log truncated)" if truncated else ""))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    figure.savefig(path, dpi=110)
    return path


def plot_convergence(picture: ConvergencePicture, path: str | Path) -> Path:
    """``convergence.png``: ``|M(e^jw)|`` of the law's trial-to-trial map over frequency against 1 (the nominal plant
    and every uncertainty vertex), the Q-filter's cutoff and the certificate's 2-norm marked
    (:mod:`foilc_hil.design.frequency_picture`; ``docs/convergence.md`` says how to read it)."""
    target = Path(path)
    figure = _new_figure()
    ax = figure.subplots()
    f = picture.frequency
    for k, curve in enumerate(picture.vertices):
        ax.semilogx(f, curve.magnitude, color="0.55", linewidth=0.9,
                    label=f"uncertainty vertices ({len(picture.vertices)})" if k == 0 else None)
    ax.semilogx(f, picture.nominal.magnitude, color="tab:blue", linewidth=2.0, label="nominal plant")
    ax.axhline(1.0, color="black", linestyle="--", linewidth=1.2, label="1: monotone convergence limit")
    if picture.certified_norm_2 is not None:
        method = f"\n{picture.norm_2_method}" if picture.norm_2_method else ""
        ax.axhline(picture.certified_norm_2, color="tab:red", linestyle=":", linewidth=1.5,
                   label=f"certificate's ||map||_2: {picture.certified_norm_2:.4g} at N = {picture.n_samples}{method}")
    if picture.q_filter is not None:
        from foilc_hil.config import QFilterPhase

        q = picture.q_filter
        phase = "zero-phase" if q.phase is QFilterPhase.ZERO else "causal"
        ax.axvline(q.cutoff, color="tab:green", linestyle="-.", linewidth=1.2,
                   label=f"Q-filter cutoff {q.cutoff:.4g} rad/s (order {q.order}, {phase})")
    worst = picture.worst
    at = float(f[int(np.argmax(worst.magnitude))])
    ax.plot([at], [worst.peak], "o", color="tab:red" if worst.peak >= 1 else "tab:blue", markersize=5,
            label=f"sup = {worst.peak:.4g} at {at:.4g} rad/s ({worst.plant})")
    top = max(1.15, min(1.08 * worst.peak, 4.0))  # a divergent curve is clipped, its peak says how far it goes
    ax.set_ylim(0.0, top)
    ax.set_xlim(float(f[0]), float(f[-1]))
    ax.set_xlabel(f"frequency (rad/s); Nyquist {math.pi / picture.sample_time:.4g} rad/s")
    ax.set_ylabel("|M(e^jw)|: per-trial contraction")
    ax.set_title(f"{str(picture.law).upper()}: trial-to-trial map over frequency (long trials)\n{picture.formula}",
                 fontsize="medium")
    ax.grid(True, which="both", alpha=0.3)
    # below the axes: inside, it hid the curves' peaks or the line at 1, which are what the picture is read for
    figure.set_figheight(figure.get_figheight() + 1.1)
    figure.legend(loc="outside lower center", ncol=2, fontsize="x-small", frameon=False)
    figure.savefig(target, dpi=110)
    return target


def _convergence(contents: LogContents, directory: Path) -> tuple[Path, dict[str, Any]] | None:
    """The picture of convergence of the logged design (with the Q-filter its run built:
    :func:`~foilc_hil.design.record.with_logged_q_filter`), or ``None`` when the log has no design that reads back as
    a whole (a synthetic or a damaged record: the rest of the report stands)."""
    from foilc_hil.design.frequency_picture import convergence_picture
    from foilc_hil.design.record import Design, with_logged_q_filter

    if contents.design is None:
        return None
    try:
        config = _logged_config(contents)
        settings = None if config is None else config.law.q_filter
        design = with_logged_q_filter(Design.from_json(contents.design), contents.design, settings)
        picture = convergence_picture(design)
    except (FoilcHilError, np.linalg.LinAlgError):
        return None
    return plot_convergence(picture, directory / "convergence.png"), picture.to_json()


def _union(limits: Sequence[tuple[float, float] | None]) -> tuple[float, float] | None:
    found = [limit for limit in limits if limit is not None]
    return (min(low for low, _ in found), max(high for _, high in found)) if found else None


def write_comparison(logs: Mapping[str, str | Path], path: str | Path) -> Path:
    """Laws side by side (``comparison.png``): one column per log -- output by trial with the reference, learned
    input, tracking error (shared scales per row, trial 1 and the unlearnable first samples left out of them) --
    and one panel of every law's learnable RMSE against trial, the disturbance's first trial marked."""
    from foilc_hil.io.mcap_log import read_log

    # the figure needs the samples and the trial metrics (and the metadata): the frames are not decoded
    return draw_comparison({name: read_log(log, (TOPIC_SAMPLE, TOPIC_TRIAL)) for name, log in logs.items()}, path,
                           [str(log) for log in logs.values()])


@as_step("report: comparison figure")
def draw_comparison(runs: Mapping[str, LogContents], path: str | Path, sources: Sequence[str] = ()) -> Path:
    """:func:`write_comparison` of logs already read (the demo reads each log once for its report and this
    figure); ``sources`` names them in the error raised when none has samples (default: their paths)."""
    signals = {name: trial_signals(contents.samples) for name, contents in runs.items()}
    contexts = {name: log_context(contents) for name, contents in runs.items()}
    names = [name for name in runs if signals[name]]
    if not names:
        raise InputError("comparison: no /ilc/sample messages in "
                         + ", ".join(sources or [contents.path for contents in runs.values()]))
    figure = _new_figure(4, len(names))
    mosaic: list[Any] = [[f"{row}:{name}" for name in names] for row in ("y", "u", "e")] + [["rmse"] * len(names)]
    axes = figure.subplot_mosaic(mosaic)
    limits = {
        row: _union([_zoomed_limits(signals[name], row_signal, contexts[name].input_delay) for name in names])
        for row, row_signal in (("u", "control"), ("e", "error"))
    }
    mappable = None
    for name in names:
        data, context = signals[name], contexts[name]
        trials = _trials_to_draw(sorted(data))
        tracked = {trial: {**d, "tracked": d["reference"] - d["error"]} for trial, d in data.items()}
        for row, signal, label in (("y", "tracked", "output y"), ("u", "control", "learned input u"),
                                   ("e", "error", "error e")):
            ax = axes[f"{row}:{name}"]
            mappable = _draw_trials(ax, tracked, signal, trials)
            unit = context.input_unit if row == "u" else context.output_unit
            ax.set_ylabel(_label(label, unit))
            ax.grid(True, alpha=0.3)
            if row in limits and limits[row] is not None:
                ax.set_ylim(*limits[row])  # type: ignore[misc]
        last = data[trials[-1]]
        axes[f"y:{name}"].plot(last["t"], last["reference"][:, 0], "k--", linewidth=1.2, label="reference")
        axes[f"y:{name}"].legend(fontsize="small", loc="lower right")
        axes[f"y:{name}"].set_title(f"{context.law}: output, learned input and error by trial")
        axes[f"e:{name}"].set_xlabel("t (s)")
    _trial_colorbar(figure, mappable, [axes[f"{row}:{name}"] for row in "yue" for name in names])
    for name in names:
        if _notes(signals[name], contexts[name]):  # the reference starts with a step: say what the swing is
            axes[f"u:{name}"].annotate(
                "early swing: the learned inverse of the start step\n(not a divergence; see the report's notes)",
                xy=(0.02, 0.95), xycoords="axes fraction", va="top", fontsize="small",
                bbox={"boxstyle": "round", "facecolor": "white", "alpha": 0.8})
    _rmse_panel(axes["rmse"], runs, contexts)
    target = Path(path)
    figure.savefig(target, dpi=100)
    return target


def _rmse_panel(ax: Any, runs: Mapping[str, LogContents], contexts: Mapping[str, LogContext]) -> None:
    for name, contents in runs.items():
        points = [(int(r["trial"]), float(r.get("rmse_learnable", r["rmse"]))) for r in contents.trials]
        points = [(k, value) for k, value in points if value > 0 and math.isfinite(value)]
        if points:
            ax.semilogy([k for k, _ in points], [v for _, v in points], "o-", label=contexts[name].law)
    starts = {context.disturbance_trial for context in contexts.values() if context.disturbance_trial is not None}
    for start in sorted(starts):
        ax.axvline(start - 0.5, color="0.4", linestyle=":", label=f"disturbance from trial {start}")
    unit = next((context.output_unit for context in contexts.values() if context.output_unit), "")
    _integer_ticks(ax)
    ax.set_xlabel("trial")
    ax.set_ylabel(_label("learnable RMSE", unit))
    ax.set_title("learnable RMSE by trial (first samples, fixed by the initial condition, left out)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")


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


# --- notes and markdown -------------------------------------------------------------------------------------------


def _notes(signals: Mapping[int, Mapping[str, np.ndarray]], context: LogContext) -> list[str]:
    """Explanations a control engineer needs to read the plots; today: a reference that starts with a step."""
    if not signals:
        return []
    last = signals[max(signals)]
    reference, error, control = last["reference"][:, 0], last["error"][:, 0], last["control"][:, 0]
    peak = float(np.nanmax(np.abs(reference))) if reference.size else 0.0
    skip = max(context.input_delay, 1)
    rest = error[skip:]
    typical = float(np.sqrt(np.nanmean(rest * rest))) if rest.size else 0.0
    first = abs(float(error[0]))
    if not (peak > 0 and first > STEP_SHARE * peak and first > STEP_OVER_TYPICAL * typical):
        return []
    early = control[: max(3, len(control) // 20)]
    unit = f" {context.output_unit}" if context.output_unit else ""
    t_early = float(last["t"][len(early) - 1])
    return [
        f"The reference starts with a step: the output is {float(reference[0] - error[0]):.4g}{unit} (at rest) "
        f"where the reference is {float(reference[0]):.4g}{unit}. The first {skip} sample(s) of every trial are "
        "fixed by the initial condition (no input reaches them through the loop's delay), so `max_abs_error` "
        "stays at that step in every trial; `max_abs_error_learnable` and `rmse_learnable` leave them out.",
        f"The learned input swings from {float(np.nanmin(early)):.4g} to {float(np.nanmax(early)):.4g}"
        f"{' ' + context.input_unit if context.input_unit else ''} in the first {t_early:.3g} s: to follow the step "
        "as soon as it can, the law learns a large first command (up to the drive's limit) and a damped ringing "
        "correction after it -- the inverse of the axis's dynamics at a jump it cannot make, not a divergence. "
        "Where the jump is beyond the drive's torque (the demo at 1 ms: the first milliseconds of eq. (52)'s 400 rpm "
        "from rest), that error stays (`max_abs_error_learnable`) and the learned command stays at "
        "the drive's limit, where the law's command limits stop it from growing (anti-windup). A reference that "
        "starts at the axis's initial value (e.g. a short `piecewise` ramp) or a Q-filter (`law.q_filter.cutoff`) "
        "removes it.",
    ]


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _certificate_tables(certificates: Mapping[str, Any]) -> list[str]:
    """Scalars as one key/value table, the per-plant certificates as a table of their own."""
    scalars = [(key, value) for key, value in certificates.items() if not isinstance(value, (dict, list))]
    for key, value in certificates.items():
        if isinstance(value, dict):
            scalars += [(f"{key}.{sub}", item) for sub, item in value.items() if not isinstance(item, (dict, list))]
    lines = ["| certificate | value |", "|---|---:|"] + [f"| {key} | {_fmt(value)} |" for key, value in scalars]
    plants = [row for row in certificates.get("plants", []) if isinstance(row, dict)]
    if plants:
        columns = list(dict.fromkeys(key for row in plants for key in row))
        lines += ["", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        lines += ["| " + " | ".join(_fmt(row.get(column, "")) for column in columns) + " |" for row in plants]
    return lines


def _trial_table(trials: Sequence[Mapping[str, Any]]) -> list[str]:
    lines = ["## Trials", "", "| trial | SSE | RMSE | max abs error | learnable RMSE | learnable max abs error |",
             "|---:|---:|---:|---:|---:|---:|"]
    for t in trials:
        cells = [t.get(key, "") for key in ("trial", "sse", "rmse", "max_abs_error", "rmse_learnable",
                                             "max_abs_error_learnable")]
        lines.append("| " + " | ".join(_fmt(cell) for cell in cells) + " |")
    return [*lines, "", "(learnable: over the samples an input of the trial can move; see the notes.)", ""]


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
        lines += _trial_table(summary["trials"])
    design = summary["design"]
    if design:
        lines += ["## Design", "", "| parameter | value |", "|---|---:|"]
        lines += [f"| {key} | {_fmt(value)} |" for key, value in design.items() if key != "certificates"]
        certificates = design.get("certificates") or {}
        if certificates:
            lines += ["", "### Certificates", "", *_certificate_tables(certificates)]
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
    if summary.get("notes"):
        lines += ["## Notes", "", *[f"- {note}" for note in summary["notes"]], ""]
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

    return report_of(read_log(log, REPORT_TOPICS, count_frames=True), out_dir)


@as_step("report: figures and summary")
def report_of(contents: LogContents, out_dir: str | Path) -> ReportFiles:
    """:func:`write_report` of a log already read."""
    from foilc_hil.logtools.axes import log_axes

    axes = log_axes(contents)
    if axes:
        return _write_axes_report(contents, axes, Path(out_dir))
    return _write_report(contents, Path(out_dir))


def _write_axes_report(contents: LogContents, axes: Sequence[int], directory: Path) -> ReportFiles:
    """A log of several axes: one report per axis in ``axis-<node id>/`` and an index of them in ``directory``."""
    from foilc_hil.logtools.axes import axis_view

    reports = [_write_report(axis_view(contents, node), directory / f"axis-{node}") for node in axes]
    summary: dict[str, Any] = {
        "log": contents.path,
        "truncated": contents.truncated,
        "damage": contents.damage or None,
        "partial": contents.truncated,
        "completed_trials": min(report.summary["completed_trials"] for report in reports),
        "samples": len(contents.samples),
        "plots": [],
        "axes": [{"node_id": node, "out": str(report.directory), **report.summary}
                 for node, report in zip(axes, reports, strict=True)],
    }
    summary_json = directory / "summary.json"
    summary_md = directory / "summary.md"
    summary_json.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    lines = [f"# {contents.path}: {len(axes)} axes", "", "| axis | trials | first SSE | last SSE | report |",
             "|---|---|---|---|---|"]
    for node, report in zip(axes, reports, strict=True):
        trials = report.summary["trials"]
        first, last = (_fmt(trials[0]["sse"]), _fmt(trials[-1]["sse"])) if trials else ("-", "-")
        lines.append(f"| {node} | {len(trials)} | {first} | {last} | [axis-{node}](axis-{node}/summary.md) |")
    summary_md.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return ReportFiles(directory, [], summary_json, summary_md, summary)


def _write_report(contents: LogContents, directory: Path) -> ReportFiles:
    """The report of one axis's log into ``directory``."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out: {directory}: cannot create: {exc.strerror or exc}") from None
    signals = trial_signals(contents.samples)
    summary = summarize(contents, signals)
    context = log_context(contents)
    y, u = _label("y", context.output_unit), _label("u", context.input_unit)
    plots: list[Path] = []
    if signals:
        tracked = {trial: {**data, "tracked": data["reference"] - data["error"]} for trial, data in signals.items()}
        plots.append(_plot_by_trial(tracked, "tracked", y, directory / "outputs.png",
                                    f"{context.law}: output by trial", with_reference=True))
        plots.append(_plot_by_trial(signals, "control", u, directory / "control.png",
                                    f"{context.law}: learned input by trial", zoom_skip=context.input_delay))
        plots.append(_plot_by_trial(signals, "error", _label("e", context.output_unit), directory / "error.png",
                                    f"{context.law}: tracking error by trial", zoom_skip=context.input_delay))
    if contents.trials:
        plots.append(_plot_sse(contents.trials, directory / "sse.png", contents.truncated, context))
    if contents.timing:
        plots.append(_plot_timing(contents.timing, directory / "timing.png"))
    convergence = _convergence(contents, directory)
    summary["convergence"] = None if convergence is None else convergence[1]
    if convergence is not None:
        plots.append(convergence[0])
    summary["plots"] = [path.name for path in plots]
    summary_json = directory / "summary.json"
    summary_md = directory / "summary.md"
    summary_json.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    summary_md.write_text(_markdown(summary, plots), encoding="utf-8")
    return ReportFiles(directory, plots, summary_json, summary_md, summary)
