"""``foilc-hil synthesize``: the learning gain of a law and the certificates of the law as it runs.

FOILC and IOILC: Theorem 1's LMI (robust 2D stability within the trial) and, for FOILC with
``--design codesign`` (``synthesis.design``), the co-design of ``kp``, ``r`` and the gain
(:mod:`foilc_hil.design.codesign`; ``certificates.codesign`` says how it chose). P-type, NOILC and gradient: their
gain, weights or step, no LMI (``Qb``, ``Qt``, ``gamma`` are ``null``).

JSON (``--json``): ``{"A", "B", "C", "G1", "H1", "G2", "H2", "P", "Qb", "Qt", "gamma", "tau", "theta", "kp", "r",
"sample_time", "certificates": {...}}`` plus ``law``, ``input_delay``, ``gain_scale``, ``p1``, ``p2`` and
``C_measured`` (:meth:`foilc_hil.design.record.Design.to_json`). ``kp``/``r`` come from ``tuning.kp``/``tuning.r`` when
given, else from the tuner. An infeasible LMI or an uncertifiable law exits 3. The law is ``--law``, else the
config's ``law.kind``. ``--plots DIR`` also draws ``DIR/convergence.png``
(:func:`foilc_hil.logtools.report.plot_convergence`) and adds ``plots`` and ``convergence``
(:meth:`foilc_hil.design.frequency_picture.ConvergencePicture.to_json`) to the document.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from foilc_hil.commands import CommandResult
from foilc_hil.config import DesignMethod, LawKind

if TYPE_CHECKING:
    from foilc_hil.design.frequency_picture import ConvergencePicture
    from foilc_hil.design.record import Design

HELP = "design the learning gain P (LMI of Theorem 1, co-design, or a baseline's gain) and certify it"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``synthesize``."""
    parser.add_argument("--config", required=True, help="YAML configuration file")
    parser.add_argument("--tau", type=float, default=None, help="convergence index along time, 0 < tau < 1")
    parser.add_argument("--theta", type=float, default=None, help="convergence index along trials, 0 < theta < 1")
    parser.add_argument(
        "--law",
        choices=tuple(kind.value for kind in LawKind),
        default=None,
        help="law to design (IOILC: kp = 0; p-type, noilc, gradient: baselines; default: the config's law.kind)",
    )
    parser.add_argument(
        "--design",
        choices=tuple(method.value for method in DesignMethod),
        default=None,
        help="FOILC: the paper's method (tuner + LMI) or the co-design (default: synthesis.design)",
    )
    parser.add_argument(
        "--input-delay",
        type=int,
        default=0,
        metavar="CYCLES",
        help="cycles of input delay folded into the design model (1 for the SYNC-driven CAN loop)",
    )
    parser.add_argument(
        "--plots",
        default=None,
        metavar="DIR",
        help="also draw DIR/convergence.png: the law's trial-to-trial map over frequency against 1 "
        "(docs/convergence.md)",
    )
    parser.add_argument(
        "--exact",
        action="store_true",
        default=None,
        help="compute each certificate's norm exactly (brackets to 1e-9 where the trial's edges set it, dense "
        "spectral radii of zero-phase maps up to 6000 rows) instead of the fast rigorous bound; with progress",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")


def _text(design: Design) -> str:
    certificates = design.certificates
    assert certificates is not None  # every built design is certified
    lines = [
        f"law {design.law}: kp = {design.kp:.6g}, r = {design.r:.6g}, Ts = {design.sample_time:g} s, "
        f"input delay {design.input_delay} cycle(s)",
    ]
    if certificates.lmi is not None:
        lmi = certificates.lmi
        # solve_lmi refuses a solution whose margin is within rounding: the gamma here is confirmed
        lines.append(
            f"gamma = {design.gamma:.6g} (tau = {design.tau:g}, theta = {design.theta:g}; solver {lmi.solver}; "
            f"LMI margin {lmi.relative_margin:.3g} of its scaled norm, cond(Q) {lmi.Q_condition:.3g}) -- robust 2D "
            "stability within the trial"
        )
    if certificates.noilc is not None:
        weights = certificates.noilc
        lines.append(f"norm-optimal weights: Q = {weights.q:.6g} I, R = {weights.r:.6g} I")
    if certificates.gradient is not None:
        step = certificates.gradient
        lines.append(
            f"gradient step: beta = {step.beta:.6g} = {step.step_relative:g} / ||G||^2, ||G|| = {step.plant_norm:.6g}"
        )
    codesign = certificates.codesign
    if codesign is not None:
        lines.append(
            f"co-design: objective {codesign.objective:.6g} (IOILC's design {codesign.ioilc_objective:.6g}); "
            f"p1 x {codesign.state_gain:.4g}, p2 x {codesign.gain:.4g}; time-varying draws "
            f"{codesign.time_varying_norm_2:.6g}; noise gain {_optional(codesign.noise_gain)}"
        )
    lines += [
        f"p1 = {design.p1.tolist()}",
        f"p2 = {design.p2.tolist()}" + (f"  (rescaled by {design.gain_scale:.6g})" if design.gain_scale != 1 else ""),
        f"lifted trial map ({certificates.n_samples} samples, {certificates.vertices} uncertainty vertices): "
        f"spectral radius {certificates.spectral_radius:.6g}, induced 2-norm {certificates.norm_2:.6g}"
        f" -> {'monotonic' if certificates.monotonic else 'asymptotic only'}",
        f"as designed (before any rescale): spectral radius {certificates.designed.spectral_radius:.6g}; "
        f"without the fractional filter: {certificates.naive_without_filter.spectral_radius:.6g}; "
        f"filter first weight 1 + kp h^-r = {certificates.filter_first_weight:.6g}",
    ]
    growth = certificates.growth_bound
    if growth is not None:
        lines.append(f"error growth bound over {growth.trials} trials: {growth.bound:.6g}")
    return "\n".join(lines)


def _optional(value: float | None) -> str:
    return "-" if value is None else f"{value:.6g}"


def execute(args: argparse.Namespace) -> CommandResult:
    """Load the config and build the design with the one pipeline: tune ``kp``/``r`` if needed, solve LMI (31),
    certify the law as it runs (Q-filter, fractional memory, input delay), print the design."""
    from foilc_hil.config import load_config
    from foilc_hil.design.pipeline import build_design
    from foilc_hil.errors import InputError
    from foilc_hil.references import trial_samples

    if args.input_delay < 0:
        raise InputError(f"--input-delay: must be >= 0, got {args.input_delay}")
    # the command line overrides the file, which overrides the defaults: --law, else law.kind, else foilc
    overrides = {
        "law.kind": args.law,
        "synthesis.tau": args.tau,
        "synthesis.theta": args.theta,
        "synthesis.design": args.design,
        "synthesis.exact_certificates": args.exact,
    }
    config = load_config(args.config, overrides)
    n_samples = trial_samples(config.reference, config.sample_time)
    design = build_design(config, config.law.kind, n_samples, input_delay=args.input_delay)
    document, text = design.to_json(), _text(design)
    if args.plots is not None:
        picture, path = _draw_convergence(design, args.plots)
        summary = picture.to_json()
        document = {**document, "plots": [str(path)], "convergence": summary}
        text += (
            f"\nconvergence over frequency: sup |M| = {summary['worst_peak']:.6g} ({summary['worst_plant']}, "
            f"{summary['worst_frequency']:.4g} rad/s), nominal {summary['nominal_peak']:.6g} -> {path}"
        )
    return CommandResult(document=document, text=text)


def _draw_convergence(design: Design, directory: str) -> tuple[ConvergencePicture, Path]:
    """``--plots DIR``: the picture of convergence of ``design`` with its Q-filter (the config's, built once by the
    design), as ``convergence.png``. matplotlib is imported here only (the design never needs it)."""
    from foilc_hil.design.frequency_picture import convergence_picture
    from foilc_hil.errors import InputError
    from foilc_hil.logtools.report import plot_convergence

    picture = convergence_picture(design)
    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--plots: {out}: cannot create: {exc.strerror or exc}") from None
    return picture, plot_convergence(picture, out / "convergence.png")
