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
from drivers.realtime import RealtimeConfig
from foilc_hil.schema import Section, apply_overrides, load_document, validate
from plant_emulator.config import PlantConfig
from plant_emulator.settings import EmulatorConfig


@enum.unique
class LawKind(StrEnum):
    """The learning laws, spelled once: config (``law.kind``), designs, laws and commands use these values."""

    FOILC = "foilc"
    IOILC = "ioilc"
    P_TYPE = "p-type"


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


class Segment(Section):
    """One piece of a user-defined piecewise reference: hold or ramp from ``start`` to ``end`` over ``duration``."""

    duration: float = Field(gt=0)
    start: float
    end: float | None = None  # None: hold ``start``


class ReferenceConfig(Section):
    """The repeated set-point profile ``y_r(t)`` of one trial."""

    profile: Literal["eq49", "eq52", "piecewise"] = "eq49"
    scale: float = 1.0  # multiplies the profile (unit conversion)
    time_scale: float = Field(default=1.0, gt=0)  # eq52 is printed in ms; 1.0 keeps 6 s per trial
    segments: list[Segment] | None = None

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


class SynthesisConfig(Section):
    """LMI synthesis of the learning gain (Theorem 1)."""

    tau: float = Field(default=0.868, gt=0, lt=1)
    theta: float = Field(default=0.868, gt=0, lt=1)
    discretization: Literal["zoh", "euler"] = "zoh"
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL"
    margin: float = Field(default=1e-6, gt=0)  # strictness margin of the LMIs
    on_divergent_filter: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE
    # Certify monotonic convergence (induced 2-norm of the lifted trial map < 1), not only asymptotic (radius < 1).
    require_monotonic: bool = True


class QFilterConfig(Section):
    """Zero-phase low-pass Q-filter applied to the feedforward between trials."""

    cutoff: float = Field(gt=0)  # rad/s
    order: int = Field(default=2, ge=1, le=8)


class LawConfig(Section):
    """The learning law that runs."""

    kind: LawKind = LawKind.FOILC
    p_type_gain: float | None = None  # Arimoto gain; None: 1 / (C B) scaled for monotonic convergence
    q_filter: QFilterConfig | None = None
    fractional_memory: FractionalMemory = FractionalMemory.CONTROLLABLE  # see FractionalMemory


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
    realtime: RealtimeConfig = RealtimeConfig()  # host settings of a realtime run (drivers.realtime)


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
