"""The bench's configuration: one YAML document, typed and validated.

Sections are owned by the modules that use them (``plant_emulator.config``, ``drivers.config``) and composed
here. Load with :func:`load_config`; command-line options override the file, which overrides defaults.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from enum import StrEnum
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, model_validator

from drivers.config import BusConfig, DriveConfig
from drivers.injection import Injection
from drivers.realtime import BenchRealtimeConfig
from foilc_hil.errors import ConfigError
from foilc_hil.schema import Section, apply_overrides, load_document, validate
from plant_emulator.config import PlantConfig
from plant_emulator.settings import EmulatorConfig


@enum.unique
class LawKind(StrEnum):
    """The learning laws, spelled once: config (``law.kind``), designs, laws and commands use these values."""

    FOILC = "foilc"
    IOILC = "ioilc"
    P_TYPE = "p-type"
    NOILC = "noilc"
    GRADIENT = "gradient"


@enum.unique
class DesignMethod(StrEnum):
    """How FOILC's ``kp``, ``r`` and learning gain are chosen (``synthesis.design``).

    ``PAPER``: the paper's method, kept and labelled -- the loop-shaping tuner picks ``kp``, ``r`` (or
    ``tuning.kp``/``tuning.r``), LMI (31) picks ``P``, the certificate rescales ``p2`` if it must.
    ``CODESIGN``: ``kp``, ``r`` and the scale of ``p2`` chosen together to minimise the worst-case certified
    convergence factor of the law as it runs (:mod:`foilc_hil.design.codesign`); ``kp = 0`` is in the search
    space, so the result is never certified worse than IOILC on the same plant.
    """

    PAPER = "paper"
    CODESIGN = "codesign"


@enum.unique
class FractionalMemory(StrEnum):
    """Where the fractional operator's memory starts (:mod:`foilc_hil.laws.learning`).

    ``CONTROLLABLE``: at the first error sample an input can move, zero history before it (the converged error is
    zero); ``TRIAL``: the paper-literal Caputo derivative over the whole trial error (leaves a Mittag-Leffler tail
    when ``e(0) != 0``), kept for comparison.
    """

    CONTROLLABLE = "controllable"
    TRIAL = "trial"


@enum.unique
class DivergentFilterPolicy(StrEnum):
    """What the certificate step does when the law as it runs is not certified (``synthesis.on_divergent_filter``).

    See :func:`foilc_hil.design.certificates.certify`.
    """

    RESCALE = "rescale"
    AUGMENT = "augment"
    REFUSE = "refuse"

    @classmethod
    def parse(cls, value: str) -> DivergentFilterPolicy:
        """The policy named by ``value``; one owner of the error both certificate steps give for an unknown name.

        Raises
        ------
        foilc_hil.errors.ConfigError
            For an unknown policy (``synthesis.on_divergent_filter``).
        """
        try:
            return cls(value)
        except ValueError:
            raise ConfigError(
                f"must be 'rescale', 'augment' or 'refuse', got {value!r}", key="synthesis.on_divergent_filter"
            ) from None


@enum.unique
class QFilterPhase(StrEnum):
    """How the Q-filter runs over a trial (``law.q_filter.phase``; :mod:`foilc_hil.design.qfilter`).

    ``ZERO``: forward then backward over the trial (zero phase, squared magnitude; the map is not causal).
    ``CAUSAL``: one forward pass (the Butterworth's own phase lag; the trial-to-trial map stays causal, so its
    spectral radius is exact from its diagonal).
    """

    ZERO = "zero"
    CAUSAL = "causal"


class Segment(Section):
    """One piece of a user-defined piecewise reference: hold or ramp from ``start`` to ``end`` over ``duration``."""

    duration: float = Field(gt=0)  # seconds
    start: float
    end: float | None = None  # None: hold ``start``


class ReferenceConfig(Section):
    """The repeated set-point profile ``y_r(t)`` of one trial."""

    profile: Literal["eq49", "eq52", "piecewise"] = "eq49"
    scale: float = 1.0  # multiplies the profile (unit conversion)
    time_scale: float = Field(default=1.0, gt=0)  # eq52 is printed in ms; 1.0 keeps 6 s per trial
    segments: list[Segment] | None = None
    # seconds of a linear ramp from rest to the profile's first value before it, and from its last value back to
    # rest after it (both part of the trial): a profile that starts or ends away from rest asks for a jump no axis
    # can make, which a learning law integrates into a command at the drive's limit at the trial's edges
    lead_in: float = Field(default=0.0, ge=0)
    lead_out: float = Field(default=0.0, ge=0)

    @model_validator(mode="after")
    def _segments_for_piecewise(self) -> ReferenceConfig:
        if self.profile == "piecewise" and not self.segments:
            raise ValueError("profile 'piecewise' needs 'segments'")
        return self


class TuningConfig(Section):
    """Loop specification for the fractional PD function, or ``kp``/``r`` given directly."""

    crossover: float | None = Field(default=None, gt=0)  # rad/s
    phase_margin_deg: float | None = Field(default=None, gt=0, lt=180)
    flat_phase: bool = False
    kp: float | None = Field(default=None, ge=0)
    r: float | None = Field(default=None, gt=0, lt=2)

    @model_validator(mode="after")
    def _spec_or_direct(self) -> TuningConfig:
        if (self.kp is None) != (self.r is None):
            raise ValueError("give both 'kp' and 'r', or neither")
        return self


class CodesignConfig(Section):
    """``synthesis.codesign``: the search of :mod:`foilc_hil.design.codesign` (used when ``design: codesign``)."""

    # objective = worst-case convergence factor + noise_weight * noise gain (stationary error variance per unit
    # white measurement-noise variance; single-input single-output plants only)
    noise_weight: float = Field(default=0.0, ge=0)
    # time-varying Delta(t) draws checked on the finalists (a sampled check on a shortened trial, not a proof)
    time_varying_samples: int = Field(default=4, ge=0, le=64)
    time_varying_horizon: int = Field(default=200, ge=8, le=1000)
    seed: int = Field(default=0, ge=0)


class SynthesisConfig(Section):
    """LMI synthesis of the learning gain (Theorem 1)."""

    tau: float = Field(default=0.868, gt=0, lt=1)
    theta: float = Field(default=0.868, gt=0, lt=1)
    discretization: Literal["zoh", "euler"] = "zoh"
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL"
    margin: float = Field(default=1e-6, gt=0)  # strictness margin of LMI (31), relative to its scaled matrix's norm
    on_divergent_filter: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE
    # Certify monotonic convergence (induced 2-norm of the lifted trial map < 1), not only asymptotic (radius < 1).
    require_monotonic: bool = True
    # false: every certificate within a bounded time (a fast bound may say "inconclusive at bound X"); true: the
    # exact values where the fast bound is not (slow on long trials, with progress; `synthesize --exact`)
    exact_certificates: bool = False
    design: DesignMethod = DesignMethod.PAPER  # FOILC only: the paper's method or the co-design
    codesign: CodesignConfig = CodesignConfig()


class QFilterConfig(Section):
    """Butterworth low-pass Q-filter applied to the feedforward between trials (zero-phase or causal)."""

    cutoff: float = Field(gt=0)  # rad/s, -3 dB of one pass
    order: int = Field(default=2, ge=1, le=8)
    # zero: forward-backward over the trial (zero phase, squared magnitude); causal: one forward pass
    phase: QFilterPhase = QFilterPhase.ZERO


class NoilcConfig(Section):
    """``law.noilc``: the weights of norm-optimal ILC, ``min ||e_{k+1}||_Q^2 + ||u_{k+1} - u_k||_R^2``.

    ``Q = q I``; ``R = r_relative ||G||_2^2 q I`` with ``G`` the lifted nominal plant, so ``r_relative`` is free of
    the plant's units: the slowest-learning frequency ``w`` contracts by ``r / (r + |G(w)|^2 / ||G||^2)`` per trial.
    """

    q: float = Field(default=1.0, gt=0)
    r_relative: float = Field(default=1e-4, gt=0)


class LawConfig(Section):
    """The learning law that runs."""

    kind: LawKind = LawKind.FOILC
    # Arimoto gain; None: the DC-deadbeat gain, shrunk only as far as a certified monotonic contraction needs
    p_type_gain: float | None = None
    q_filter: QFilterConfig | None = None
    fractional_memory: FractionalMemory = FractionalMemory.CONTROLLABLE  # see FractionalMemory
    noilc: NoilcConfig = NoilcConfig()


class BadFramePolicy(StrEnum):
    """``bench.faults.bad_frame``: what a frame from the drive that does not decode does to the run."""

    COUNT = "count"  # counted (/ilc/trial bad_frames) and ignored; an incomplete TPDO set is a lost feedback
    ABORT = "abort"  # the run aborts (BadFrameError, exit 1)


class FaultPolicyConfig(Section):
    """``bench.faults``: the bench's reaction per kind of fault (EMCY and a fault statusword always abort)."""

    bad_frame: BadFramePolicy = BadFramePolicy.COUNT
    # consecutive SYNCs without a complete TPDO set tolerated (the law holds the last good feedback); one more aborts
    lost_feedback: int = Field(default=3, ge=0)


class BenchConfig(Section):
    """The trial loop over CAN: timing and safety."""

    mode: Literal["lockstep", "realtime"] = "lockstep"
    # lockstep: one SYNC's feedback may take watchdog_cycles x 0.1 s before it counts as lost
    watchdog_cycles: int = Field(default=5, ge=1)
    divergence_factor: float = Field(default=10.0, gt=1)
    settle_time: float = Field(default=0.5, ge=0)  # initial-condition reset between trials, seconds
    settle_tolerance: float = Field(default=1.0, ge=0)  # |y| below this counts as at rest
    faults: FaultPolicyConfig = FaultPolicyConfig()
    realtime: BenchRealtimeConfig = BenchRealtimeConfig()  # host settings of a realtime run (drivers.realtime)


class AxisConfig(Section):
    """One entry of ``axes:``: one CiA 402 axis on the shared bus, with its own model, reference, law and drive.

    A section given here replaces the whole top-level section of that name for this axis (it is not merged key by
    key); a section left out is the top-level one. ``node_id`` is the axis's ``drive.node_id``.
    """

    node_id: int = Field(ge=1, le=127)
    plant: PlantConfig | None = None
    reference: ReferenceConfig | None = None
    tuning: TuningConfig | None = None
    law: LawConfig | None = None
    drive: DriveConfig | None = None

    @model_validator(mode="after")
    def _one_node_id(self) -> AxisConfig:
        if self.drive is not None and "node_id" in self.drive.model_fields_set and self.drive.node_id != self.node_id:
            raise ValueError(f"drive.node_id {self.drive.node_id} differs from node_id {self.node_id}: "
                             "give node_id only")
        return self


class Config(Section):
    """The whole document."""

    plant: PlantConfig = PlantConfig()
    reference: ReferenceConfig = ReferenceConfig()
    sample_time: float = Field(default=0.01, gt=0)  # seconds; also the CAN cycle period
    trials: int = Field(default=10, ge=1)
    tuning: TuningConfig = TuningConfig()
    synthesis: SynthesisConfig = SynthesisConfig()
    law: LawConfig = LawConfig()
    bus: BusConfig = BusConfig()
    drive: DriveConfig = DriveConfig()
    bench: BenchConfig = BenchConfig()
    emulator: EmulatorConfig = EmulatorConfig()
    # faults to inject into a run (drivers.faults; docs/reliability.md); `run --inject` adds to the list
    inject: tuple[Injection, ...] = ()
    # several axes on the one bus (one SYNC, one trial loop); empty: the single axis of the sections above
    axes: tuple[AxisConfig, ...] = ()

    @model_validator(mode="after")
    def _distinct_axes(self) -> Config:
        seen: dict[int, int] = {}
        for k, axis in enumerate(self.axes):
            if axis.node_id in seen:
                raise ValueError(f"axes.{k}.node_id: {axis.node_id} is already the node id of "
                                 f"axes.{seen[axis.node_id]}")
            seen[axis.node_id] = k
        masters = {(axis.drive or self.drive).master_node_id for axis in self.axes}
        if len(masters) > 1:
            raise ValueError(f"axes: drive.master_node_id must be the same on every axis of one bus, "
                             f"got {sorted(masters)}")
        return self


def axis_configs(config: Config) -> tuple[Config, ...]:
    """One single-axis :class:`Config` per axis (``axes:``), or ``(config,)`` for a single-axis document.

    Each is the whole document with the axis's sections in place of the top-level ones, its node id in
    ``drive.node_id`` and no ``axes``: everything built from one axis's config (its design, law, limits, PDO plan,
    emulated drive) is built exactly as for a single-axis run.
    """
    if not config.axes:
        return (config,)
    return tuple(
        config.model_copy(update={
            "plant": axis.plant or config.plant,
            "reference": axis.reference or config.reference,
            "tuning": axis.tuning or config.tuning,
            "law": axis.law or config.law,
            "drive": (axis.drive or config.drive).model_copy(update={"node_id": axis.node_id}),
            "axes": (),
        })
        for axis in config.axes
    )


def load_config(path: str | Path | None, overrides: Mapping[str, Any] | None = None) -> Config:
    """Load and validate a config file (``None``: defaults only), with dotted-key ``overrides`` on top.

    Raises
    ------
    foilc_hil.errors.ConfigError
        For the first bad value, naming the file and the key path.
    """
    document = load_document(path) if path is not None else {}
    document = apply_overrides(document, overrides or {})
    return validate(Config, document, source=str(path) if path is not None else "")


def dump_config(config: Config) -> str:
    """The resolved config as YAML text (the MCAP ``foilc_hil.config`` metadata record)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
