"""The one design pipeline: config -> :class:`~foilc_hil.design.record.Design`, for every law.

The bench (``run``), ``simulate``, ``synthesize``, the demo and ``replay`` all call :func:`build_design`, so the
design a log records is the design of the law that ran: tuned when the law needs it (FOILC without
``tuning.kp``/``tuning.r``; IOILC, P-type, NOILC and gradient ILC never need tuning; under
``synthesis.design: codesign`` the tuned pair is only the search's initial guess), synthesised (FOILC, IOILC; FOILC
co-designed when configured), given its Arimoto gain (P-type), its norm-optimal weights (NOILC) or its step
(gradient), and certified exactly as it will run (Q-filter from ``law.q_filter``, fractional memory from
``law.fractional_memory``, input delay).

Module order: in :mod:`foilc_hil.design`, models < fractional, qfilter, ptype < record < certificates < noilc
< gradient < lmi < codesign < tuning < pipeline < robustness (which certifies the designs built here on drawn plants).
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

from foilc_hil.config import Config, DesignMethod, LawKind
from foilc_hil.design.admission import admit
from foilc_hil.design.certificate_record import Bounds, CertificateAction, PlantCertificate
from foilc_hil.design.certificates import PTypeScales, ScaledVerdict
from foilc_hil.design.codesign import codesign
from foilc_hil.design.gradient import certify_gradient
from foilc_hil.design.lifted import LawStructure
from foilc_hil.design.lmi import solve_lmi, synthesize
from foilc_hil.design.models import (
    DiscreteModel,
    Uncertainty,
    augment_input_delay,
    discretize,
    uncertainty_from_config,
    uncertainty_vertices,
)
from foilc_hil.design.noilc import certify_noilc
from foilc_hil.design.ptype import p_type_gain
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.record import Design
from foilc_hil.design.tuning import tune
from foilc_hil.errors import ConfigError
from foilc_hil.progress import step
from plant_emulator.linear import continuous_model

__all__ = ["build_design", "design_model", "law_kind", "law_structure", "model_delay_samples"]

#: ``r`` recorded by designs whose law has no fractional term and no tuned ``r`` (IOILC, P-type): unused.
UNUSED_ORDER = 1.0


def law_kind(law: str) -> LawKind:
    """``law`` as a :class:`~foilc_hil.config.LawKind`; a :class:`~foilc_hil.errors.ConfigError` names
    ``law.kind`` otherwise."""
    try:
        return LawKind(law)
    except ValueError:
        raise ConfigError(f"unknown law {law!r}; choose {', '.join(LawKind)}", key="law.kind") from None


class DesignSteps:
    """Progress of one design on stderr: a line per step with the time since the design began.

    Printed only when stderr is a terminal (as the bench's progress view), so ``--json`` output, pipes and CI logs
    stay clean; the design of a long trial (the certificates at N = 6000) then never looks hung.
    """

    def __init__(self, law: str, n_samples: int) -> None:
        self.prefix = f"foilc-hil: design {law} (N = {n_samples})"
        self.started = time.perf_counter()
        self.enabled = sys.stderr.isatty()

    def step(self, what: str) -> None:
        """Report that ``what`` starts (or, for the last step, is done)."""
        if self.enabled:
            print(f"{self.prefix}: {what} [{time.perf_counter() - self.started:.1f} s]", file=sys.stderr, flush=True)


def model_delay_samples(config: Config) -> int:
    """Whole samples of the plant's own input delay (``plant.delay``), which the design folds into its state.

    For a first-order plant ``plant.delay`` is a transport delay of the physics; for a PMSM it describes the
    drive's lag (current loop, velocity-loop filter, the speed measured as an angle difference over one period:
    about 1 ms on the demo's axis, one whole sample at ``Ts = 1 ms``). Either way the learning law must look that
    many samples further ahead, or its in-trial feedback ``p1`` acts on a first Markov parameter the plant does
    not have (the 1 ms demo's learned command then swings at the Nyquist frequency into the torque limit).
    Rounded to whole samples: the design model is discrete.
    """
    return round(config.plant.delay / config.sample_time)


def design_model(config: Config, *, input_delay: int = 0) -> tuple[DiscreteModel, Uncertainty]:
    """The discrete (optionally delay-augmented) design model and uncertainty of ``config``."""
    continuous = continuous_model(config.plant)
    discrete = discretize(continuous, config.sample_time, config.synthesis.discretization)
    uncertainty = uncertainty_from_config(config.plant.uncertainty, discrete.n_states, discrete.n_inputs)
    return augment_input_delay(discrete, input_delay, uncertainty)


def _fractional_parameters(config: Config, law: LawKind) -> tuple[float, float]:
    """``kp, r``: given in ``tuning:``, else tuned (FOILC only); IOILC and P-type run ``kp = 0`` (``r`` is
    recorded, unused: the configured one, or :data:`UNUSED_ORDER`)."""
    kp, r = config.tuning.kp, config.tuning.r
    if law is not LawKind.FOILC:
        return 0.0, UNUSED_ORDER if r is None else float(r)
    if config.synthesis.design is DesignMethod.CODESIGN and kp is None and config.tuning.crossover is None:
        return 0.0, UNUSED_ORDER  # no initial guess to tune: the co-design searches from its grid alone
    if kp is None or r is None:
        tuned = tune(config, python_control=False)  # only kp, r are used: no python-control cross-check
        kp, r = tuned.kp, tuned.r
    return float(kp), float(r)


def law_structure(config: Config, law: LawKind, n_samples: int, *, input_delay: int) -> LawStructure:
    """How ``law`` runs for ``config`` (the certificates' :class:`LawStructure`), tuning FOILC if needed."""
    kp, r = _fractional_parameters(config, law)
    q_filter = None
    if config.law.q_filter is not None:  # built once: the design holds this object and the law runs it
        q_filter = QFilter.of(config.law.q_filter, config.sample_time).on(n_samples)
    return LawStructure(
        kp=kp,
        r=r,
        sample_time=config.sample_time,
        n_samples=n_samples,
        lead=input_delay,
        fractional_memory=config.law.fractional_memory,
        q_filter=q_filter,
        exact=config.synthesis.exact_certificates,
    )


def _codesign(config: Config, model: DiscreteModel, uncertainty: Uncertainty, structure: LawStructure) -> Design:
    """``synthesis.design: codesign``: the LMI for ``p1`` (and the reference ``p2``), then the co-design search
    from the tuner's (or the given) ``kp``, ``r`` as the initial guess."""
    settings = config.synthesis
    solution = solve_lmi(
        model, uncertainty, tau=settings.tau, theta=settings.theta, solver=settings.solver, margin=settings.margin
    )
    guess = (structure.kp, structure.r) if structure.kp > 0 else None
    return codesign(
        model,
        uncertainty,
        solution,
        structure,
        settings.codesign,
        rates=(settings.tau, settings.theta),
        initial_guess=guess,
        policy=settings.on_divergent_filter,
        require_monotonic=settings.require_monotonic,
        growth_horizon=config.trials,
    )


def _p_type(config: Config, model: DiscreteModel, uncertainty: Uncertainty, structure: LawStructure) -> Design:
    """P-type's gain (``law.p_type_gain`` or its default) and certificates, under the one rule of
    :mod:`foilc_hil.design.admission`: a gain not certified as required is rescaled (``Gamma`` scaled, the scaled
    gain recorded) or refused."""
    settings = config.synthesis
    vertices = list(uncertainty_vertices(uncertainty))
    gain = p_type_gain(
        config.law.p_type_gain, model.A, model.B, model.measured_output, model.input_delay, vertices=vertices
    )
    designs: dict[float, Design] = {}
    scales = PTypeScales(model, uncertainty, gain, structure, require_monotonic=settings.require_monotonic)

    def evaluate(scale: float) -> ScaledVerdict:
        if scale not in designs:
            designs[scale] = scales.design(scale)
        certificates = designs[scale].certificates
        assert certificates is not None
        return ScaledVerdict(scale, certificates.plants)

    def estimate(scale: float) -> ScaledVerdict:  # the search's cheap numbers (certificates.PTypeScales)
        bounds = scales.estimate(scale)
        entry = PlantCertificate("worst case", "estimate", bounds.spectral_radius, bounds.norm_2, "search estimate")
        return ScaledVerdict(scale, (entry,))

    with step("certificates of the P-type law"):  # the design and, where the rule needs it, the rescale
        admission = admit(
            evaluate,
            law=str(LawKind.P_TYPE),
            policy=settings.on_divergent_filter,
            require_monotonic=settings.require_monotonic,
            growth_horizon=config.trials,
            estimate=estimate,
        )
    chosen = designs[admission.verdict.scale]
    if admission.action is CertificateAction.NONE:
        return chosen
    assert chosen.certificates is not None
    designed = designs[1.0].certificates
    assert designed is not None
    certificates = replace(
        chosen.certificates,
        designed=Bounds(designed.spectral_radius, designed.norm_2),
        action=admission.action,
        gain_scale=admission.verdict.scale,
        rescale_criterion=admission.criterion,
        growth_bound=admission.growth_bound,
    )
    return replace(chosen, gain_scale=admission.verdict.scale, certificates=certificates)


def build_design(config: Config, law: str, n_samples: int, *, input_delay: int) -> Design:
    """The design of ``law`` for ``config``'s plant, certified as the law will run: the gains, ``kp``, ``r`` and the
    Q-filter (:attr:`~foilc_hil.design.record.Design.q_filter`) the law takes from it are the ones certified.

    Parameters
    ----------
    config
        The whole configuration.
    law
        ``foilc``, ``ioilc``, ``p-type``, ``noilc`` or ``gradient`` (:class:`~foilc_hil.config.LawKind`). FOILC follows
        ``synthesis.design``: ``paper`` (tuner, LMI, certificate) or ``codesign``
        (:mod:`foilc_hil.design.codesign`).
    n_samples
        Samples per trial (the certificates are for this trial length; so is the Q-filter).
    input_delay
        Cycles between computing a command and the plant applying it: 1 for the SYNC-driven CAN loop, and for
        ``simulate`` that stands in for it; 0 for an ideal offline loop. The plant's own delay
        (:func:`model_delay_samples`) is added: the design's ``input_delay`` is the sum.

    Raises
    ------
    foilc_hil.errors.ConfigError
        An unknown law, or a configuration the design cannot use (named key).
    foilc_hil.errors.InfeasibleDesignError
        Tuning, the LMI or the certificate fails (exit 3).
    """
    kind = law_kind(law)
    steps = DesignSteps(kind, n_samples)
    input_delay += model_delay_samples(config)
    model, uncertainty = design_model(config, input_delay=input_delay)
    steps.step("model and law structure (tuning kp, r where needed)")
    structure = law_structure(config, kind, n_samples, input_delay=input_delay)
    steps.step("gain and certificates of the law as it runs")
    design = _design(config, kind, model, uncertainty, structure)
    steps.step("done")
    # the filter the certificates were computed with, for the law to run: one object, built once
    return replace(design, q_filter=None if structure.q_filter is None else structure.q_filter.filter)


def _design(
    config: Config, kind: LawKind, model: DiscreteModel, uncertainty: Uncertainty, structure: LawStructure
) -> Design:
    """The gain of ``kind`` on ``model`` and its certificates (the step after tuning of :func:`build_design`)."""
    settings = config.synthesis
    monotonic, policy, horizon = settings.require_monotonic, settings.on_divergent_filter, config.trials
    if kind is LawKind.GRADIENT:
        return certify_gradient(
            model, uncertainty, structure, require_monotonic=monotonic, policy=policy, growth_horizon=horizon
        )
    if kind is LawKind.NOILC:
        return certify_noilc(
            model,
            uncertainty,
            config.law.noilc,
            structure,
            require_monotonic=monotonic,
            policy=policy,
            growth_horizon=horizon,
        )
    if kind is LawKind.FOILC and settings.design is DesignMethod.CODESIGN:
        return _codesign(config, model, uncertainty, structure)
    if kind is LawKind.P_TYPE:
        return _p_type(config, model, uncertainty, structure)
    return synthesize(
        model,
        uncertainty,
        structure,
        kind=kind,
        tau=settings.tau,
        theta=settings.theta,
        solver=settings.solver,
        margin=settings.margin,
        policy=settings.on_divergent_filter,
        require_monotonic=settings.require_monotonic,
        growth_horizon=config.trials,
    )
