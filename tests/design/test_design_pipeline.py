"""The one design pipeline: every law (foilc, ioilc, p-type, noilc) gets its design from
:func:`foilc_hil.design.pipeline.build_design`, certified as it runs, the same on every path (bench, simulate)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from foilc_hil.cli import main
from foilc_hil.config import Config, LawKind, load_config
from foilc_hil.design import pipeline
from foilc_hil.design.error_map import dense_input_map
from foilc_hil.design.pipeline import build_design, law_kind
from foilc_hil.design.ptype import p_type_default_gain
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.record import Design
from foilc_hil.errors import ConfigError, ConvergenceCertificateError, InputError
from foilc_hil.laws.learning import Foilc, PType, make_law
from foilc_hil.loop import rig, settings, simulation
from foilc_hil.references import trial_samples
from tests.support.bench import bench_config

pytestmark = pytest.mark.filterwarnings("ignore:Solution may be inaccurate")

SAMPLE_TIME = 0.01
#: A small first-order plant (paper eq. 48), a 0.6 s (60-sample) trial and a Q-filter. With the Q-filter in the
#: loop the LMI gain of this plant is certifiable for asymptotic convergence only (after a rescale of p2), hence
#: ``require_monotonic: false`` (see test_the_q_filter_is_certified_not_ignored).
DOCUMENT: dict[str, Any] = {
    "plant": {"model": "first_order", "a": -1.23, "b": 1.68, "c": 1.0},
    "reference": {
        "profile": "piecewise",
        "segments": [{"duration": 0.3, "start": 0.0, "end": 1.0}, {"duration": 0.3, "start": 1.0}],
    },
    "sample_time": SAMPLE_TIME,
    "trials": 3,
    "synthesis": {"require_monotonic": False},
    "law": {"q_filter": {"cutoff": 150.0, "order": 2}, "p_type_gain": 0.5},
}


def _config(**sections: Any) -> Config:
    """The small config with ``sections`` replaced (``tuning`` is absent unless given: no spec, no kp/r)."""
    document = {**DOCUMENT, **sections}
    return load_config(None, _flatten(document))


def _flatten(document: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in document.items():
        if isinstance(value, dict) and value:
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _without_timing(design: Design) -> dict[str, Any]:
    """``design.to_json()`` without the wall-clock ``certificates.seconds`` (the only part allowed to differ)."""
    document = design.to_json()
    document["certificates"].pop("seconds", None)
    return document


@pytest.mark.parametrize("kind", list(LawKind))
def test_bench_and_simulate_build_identical_designs_with_the_q_filter(kind: LawKind) -> None:
    config = _config(tuning={"kp": 0.02, "r": 0.5})
    n = trial_samples(config.reference, config.sample_time)
    delay = settings.CAN_INPUT_DELAY
    on_bench = settings.build_design(config, kind, n)
    via_law = rig.plan_axis(config, kind, n, input_delay=delay).design  # what simulate's plan calls
    certificates = via_law.certificates.to_json() if via_law.certificates is not None else {}
    assert json.dumps(_without_timing(on_bench)) == json.dumps(_without_timing(via_law))
    assert certificates["spectral_radius"] == on_bench.to_json()["certificates"]["spectral_radius"]
    # ... and the design is of the law as it runs over CAN: the Q-filter and the input delay are certified.
    assert on_bench.law == kind and on_bench.input_delay == delay
    assert on_bench.certificates is not None and on_bench.certificates.q_filter
    assert {plant.map for plant in on_bench.certificates.plants} == {"input (Q-filter)"}


@pytest.mark.parametrize("kind", list(LawKind))
def test_the_recorded_certificate_is_the_running_laws_input_map(kind: LawKind) -> None:
    """A second method: the dense input map of the gain that runs, with the Q-filter the law applies."""
    config = _config(tuning={"kp": 0.02, "r": 0.5})
    n = trial_samples(config.reference, config.sample_time)
    design = build_design(config, kind, n, input_delay=1)
    law = make_law(design, config.law, n)
    assert law.q_filter is not None and design.certificates is not None
    Q = law.q_filter.matrix(n)
    np.testing.assert_array_equal(Q, QFilter(150.0, 2, SAMPLE_TIME).matrix(n))
    if kind in (LawKind.NOILC, LawKind.GRADIENT):
        M = _lifted_input_map(design, Q, n)
    else:
        if kind is LawKind.FOILC:
            from foilc_hil.design.lifted import law_filter_matrix

            F = law_filter_matrix(design.kp, design.r, SAMPLE_TIME, n, lead=1)
        else:
            F = np.eye(n)  # IOILC and P-type learn from e itself
        M = dense_input_map(design.A, design.B, design.measured_output, design.p1, design.p2, F, Q, lead=1)
    nominal = design.certificates.plants[0]
    assert nominal.plant == "nominal"
    assert nominal.spectral_radius == pytest.approx(max(abs(np.linalg.eigvals(M))), rel=1e-9)
    assert nominal.norm_2 == pytest.approx(np.linalg.norm(M, 2), rel=1e-9)


def _impulse_responses(design: Design, n: int) -> np.ndarray:
    """``y[i] = y((i+1) Ts)`` for a unit input at each ``u[j]``, by simulating the state (not the Markov blocks)."""
    G = np.zeros((n, n))
    for j in range(n):
        z = np.zeros(design.n_states)
        for i in range(n):
            z = design.A @ z + design.B[:, 0] * (1.0 if i == j else 0.0)
            G[i, j] = float(design.measured_output[0] @ z)
    return G


def _lifted_input_map(design: Design, Q: np.ndarray, n: int) -> np.ndarray:
    """NOILC's or gradient ILC's input map with a Q-filter, ``M = Q - L_full G_y``, from the textbook formula on
    simulated responses: ``L = (q G^T G + r I)^-1 q G^T`` or ``L = G^T / ||G||^2``."""
    d = design.input_delay
    G_y = _impulse_responses(design, n)
    G = G_y[d:, : n - d]  # the inputs that move the error, to the samples they move
    if design.law is LawKind.GRADIENT:
        L = G.T / np.linalg.svd(G, compute_uv=False)[0] ** 2
    else:
        assert design.certificates is not None and design.certificates.noilc is not None
        weights = design.certificates.noilc
        L = np.linalg.inv(weights.q * G.T @ G + weights.r * np.eye(n - d)) @ (weights.q * G.T)
    full = np.zeros((n, n))
    full[: n - d, d:] = L
    return Q - full @ G_y


@pytest.mark.parametrize("kind", list(LawKind))
def test_the_law_runs_the_filter_and_gains_its_certificates_were_computed_with(
    kind: LawKind, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One home: the pipeline builds the Q-filter once; the certificates take it on the trial, the design holds that
    object and the law runs it (the same object, not one built again from the config), with the design's gains and
    ``kp``, ``r`` bit for bit."""
    structures: list[Any] = []
    certify = pipeline._design

    def recording(config: Config, law: LawKind, model: Any, uncertainty: Any, structure: Any) -> Design:
        structures.append(structure)
        return certify(config, law, model, uncertainty, structure)

    monkeypatch.setattr(pipeline, "_design", recording)
    config = _config(tuning={"kp": 0.02, "r": 0.5})
    n = trial_samples(config.reference, config.sample_time)
    design = build_design(config, kind, n, input_delay=1)
    law = make_law(design, config.law, n)
    (structure,) = structures
    assert structure.q_filter is not None and design.q_filter is not None
    assert law.q_filter is design.q_filter and design.q_filter is structure.q_filter.filter
    assert design.certificates is not None and design.certificates.q_filter
    np.testing.assert_array_equal(law._error_gain, design.p2)  # p2 (Gamma for P-type): the design's
    if isinstance(law, Foilc):  # and IOILC
        np.testing.assert_array_equal(law._p1, design.p1)
        assert (law.kp, law.r) == (design.kp, design.r) == (structure.kp, structure.r)
    # the filter and the gains survive the design's JSON (the log's foilc_hil.design record): replay runs them
    logged = Design.from_json(json.loads(json.dumps(design.to_json())))
    assert logged.q_filter is not None and logged.q_filter.to_json() == design.q_filter.to_json()
    replayed = make_law(logged, config.law, n)
    assert replayed.q_filter is logged.q_filter
    np.testing.assert_array_equal(logged.q_filter.matrix(n), design.q_filter.matrix(n))


def test_a_law_is_not_given_another_filter_than_its_certificates() -> None:
    """``law.q_filter`` must be the design's filter, and the design must hold the filter its certificates were
    computed with: otherwise the certificates would not be of the law that runs."""
    config = _config()
    n = trial_samples(config.reference, config.sample_time)
    design = build_design(config, "p-type", n, input_delay=1)
    other = _config(law={"q_filter": {"cutoff": 120.0, "order": 2}, "p_type_gain": 0.5})
    with pytest.raises(ConfigError, match=r"law\.q_filter: is cutoff=120\.0"):
        make_law(design, other.law, n)
    with pytest.raises(ConfigError, match=r"law\.q_filter: is none"):
        make_law(design, _config(law={"p_type_gain": 0.5}).law, n)
    unfiltered = Design.from_json({key: value for key, value in design.to_json().items() if key != "q_filter"})
    assert unfiltered.q_filter is None  # a design logged before designs recorded their filter
    with pytest.raises(ConfigError, match=r"law\.q_filter"):
        make_law(unfiltered, config.law, n)
    with pytest.raises(InputError, match=r"design\.q_filter: the certificates were computed with a Q-filter"):
        make_law(unfiltered, _config(law={"p_type_gain": 0.5}).law, n)
    with pytest.raises(InputError, match=r"design\.q_filter: must be a QFilter at the design's sample time"):
        replace(design, q_filter=QFilter(150.0, 2, 2 * SAMPLE_TIME))


def test_replay_runs_a_logged_designs_filter_and_audits_it() -> None:
    """``replay --verify`` runs the logged design's filter; a design logged before designs recorded theirs gets the
    one its run built from the logged config's section; the audit holds a logged filter against the config's."""
    from foilc_hil.design.record import with_logged_q_filter
    from foilc_hil.logtools.audit import check_design

    config = _config()
    n = trial_samples(config.reference, config.sample_time)
    document = build_design(config, "p-type", n, input_delay=1).to_json()
    logged = Design.from_json(document)
    assert with_logged_q_filter(logged, document, config.law.q_filter) is logged
    earlier = {key: value for key, value in document.items() if key != "q_filter"}
    restored = with_logged_q_filter(Design.from_json(earlier), earlier, config.law.q_filter)
    assert restored.q_filter is not None and restored.q_filter.is_of(config.law.q_filter)
    assert make_law(restored, config.law, n).q_filter is restored.q_filter
    assert check_design(document, document) is None and check_design(earlier, document) is None
    tampered = {**document, "q_filter": {**document["q_filter"], "cutoff": 120.0}}
    finding = check_design(tampered, document)
    assert finding is not None and "q_filter.cutoff" in finding.reason


def test_the_q_filter_is_certified_not_ignored() -> None:
    """The bench used to certify without the Q-filter the law applies over CAN; on this plant the LMI gain then
    looked monotonic, while the law as it runs (Q-filter in the loop) is not: the pipeline now refuses it."""
    monotonic = {"require_monotonic": True}
    n = trial_samples(_config().reference, SAMPLE_TIME)
    without_q = build_design(_config(synthesis=monotonic, law={}), "ioilc", n, input_delay=1)
    assert without_q.certificates is not None and without_q.certificates.monotonic
    with pytest.raises(ConvergenceCertificateError, match="monotonically"):
        build_design(_config(synthesis=monotonic), "ioilc", n, input_delay=1)


def test_p_type_is_a_design_with_the_configured_or_default_gain() -> None:
    config = _config()
    n = trial_samples(config.reference, config.sample_time)
    design = build_design(config, "p-type", n, input_delay=1)
    assert design.law is LawKind.P_TYPE and design.kp == 0.0
    np.testing.assert_array_equal(design.p1, np.zeros((1, design.n_states)))
    np.testing.assert_array_equal(design.p2, [[0.5]])  # law.p_type_gain
    assert design.gamma is None and design.Qb is None  # no LMI behind a P-type gain
    document = design.to_json()
    assert document["Qb"] is None and document["certificates"]["gain"] == [[0.5]]
    assert json.dumps(Design.from_json(json.loads(json.dumps(document))).to_json()) == json.dumps(document)
    default_config = _config(law={"p_type_gain": None})
    default = build_design(default_config, "p-type", n, input_delay=1)
    expected = p_type_default_gain(default.A, default.B, default.measured_output, 1)
    np.testing.assert_array_equal(default.p2, expected)
    # the law built from the design runs that gain (with the design's config: the other's Q-filter is refused)
    law = make_law(default, default_config.law, n)
    assert isinstance(law, PType)
    np.testing.assert_array_equal(law.gain, expected)


def test_ioilc_needs_no_tuning_spec_and_unknown_laws_name_the_key() -> None:
    config = _config(law={})
    assert config.tuning.crossover is None and config.tuning.kp is None
    design = build_design(config, "ioilc", trial_samples(config.reference, config.sample_time), input_delay=0)
    assert design.law is LawKind.IOILC and design.kp == 0.0
    assert design.certificates is not None and not design.certificates.q_filter
    with pytest.raises(ConfigError, match=r"law\.kind"):
        law_kind("pid")
    with pytest.raises(ConfigError, match="tuning"):  # FOILC does need kp/r or a spec
        build_design(config, "foilc", 50, input_delay=0)


# --- foilc-hil run --law p-type / ioilc on the embedded emulator ----------------------------------------------


def _run_config(tmp_path: Path) -> Path:
    """The end-to-end bench config without any tuning section (no spec, no kp/r)."""
    path = bench_config(tmp_path)
    document = yaml.safe_load(path.read_text(encoding="utf-8"))
    del document["tuning"]
    document["law"] = {"p_type_gain": 0.3}
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


@pytest.mark.parametrize("kind", [LawKind.P_TYPE, LawKind.IOILC])
def test_run_law_works_without_tuning_and_the_log_verifies(
    kind: LawKind, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / f"{kind}.mcap"
    argv = ["run", "--config", str(_run_config(tmp_path)), "--law", str(kind), "--trials", "2"]
    code = main([*argv, "--emulator", "embedded", "--out", str(out), "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    document = json.loads(captured.out)
    assert document["law"] == kind
    assert [t["trial"] for t in document["trials"]] == [1, 2]
    assert document["trials"][1]["sse"] < document["trials"][0]["sse"]  # it learned something
    code = main(["replay", str(out), "--verify", "--json"])
    verified = json.loads(capsys.readouterr().out)
    assert code == 0 and verified["verified"] is True


# --- the design package's one-way order -----------------------------------------------------------------------

DESIGN_ORDER = (
    "models",
    "convolution",
    "gl_kernel",
    "fractional",
    "qfilter",
    "ptype",
    "json_fields",
    "certificate_record",
    "record",
    "lifted",
    "map_norms",
    "toeplitz_section",
    "error_map",
    "norm_test",
    "qmap",
    "certificates",
    "admission",
    "lifted_kernel",
    "trial_operator",
    "noilc",
    "gradient",
    "lmi",
    "codesign",
    "open_loop",
    "tuning",
    "pipeline",
)


def _design_imports(name: str) -> set[str]:
    """The ``foilc_hil.design.*`` modules ``name`` imports anywhere (function-local imports included)."""
    import ast

    path = Path(__file__).resolve().parents[2] / "foilc_hil" / "design" / f"{name}.py"
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("foilc_hil.design."):
            found.add(node.module.rsplit(".", 1)[1])
        elif isinstance(node, ast.Import):
            found.update(a.name.rsplit(".", 1)[1] for a in node.names if a.name.startswith("foilc_hil.design."))
    return found


@pytest.mark.slow
@pytest.mark.parametrize("name", DESIGN_ORDER)
def test_design_modules_import_only_earlier_ones(name: str) -> None:
    """models < fractional, qfilter, ptype < record < certificates < noilc < lmi < codesign < tuning < pipeline: no
    cycle (the certificates <-> lmi one used to hide behind a function-local import)."""
    earlier = set(DESIGN_ORDER[: DESIGN_ORDER.index(name)])
    assert _design_imports(name) <= earlier, f"{name} imports {_design_imports(name) - earlier}"


@pytest.mark.slow
def test_the_order_check_can_fail() -> None:
    assert "certificates" in _design_imports("lmi")
    assert "lmi" not in _design_imports("certificates")
    assert not {"certificates"} <= set(DESIGN_ORDER[: DESIGN_ORDER.index("certificates")])


@pytest.mark.parametrize("delay_samples", [0, 1, 2])
def test_the_plants_own_delay_is_folded_into_the_design(delay_samples: int) -> None:
    """``plant.delay`` (whole samples) makes the design look that much further ahead, and ``simulate`` applies it
    once (the first-order physics delays the command; the simulated drive adds only the loop's transport delay):
    IOILC then learns the delayed plant's learnable error away. A design that ignored the delay would learn from
    error samples its input never moved, and not converge."""
    config = _config(
        plant={"model": "first_order", "a": -1.23, "b": 1.68, "c": 1.0, "delay": delay_samples * SAMPLE_TIME},
        law={},
        synthesis={"require_monotonic": True},
    )
    assert pipeline.model_delay_samples(config) == delay_samples
    design = build_design(config, "ioilc", trial_samples(config.reference, SAMPLE_TIME), input_delay=1)
    assert design.input_delay == 1 + delay_samples
    result = simulation.simulate(config, law="ioilc", trials=4, design=design, input_delay=1)
    first, last = result.metrics[0].rmse_learnable, result.metrics[-1].rmse_learnable
    assert last < 1e-3 * first, (first, last)


def test_the_design_reports_its_steps_on_a_terminal_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """Progress lines on stderr when it is a terminal (the steps in order, the last one "done"); nothing otherwise."""
    import io

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    for stream, expected in ((Terminal(), 3), (io.StringIO(), 0)):
        monkeypatch.setattr("sys.stderr", stream)
        build_design(_config(law={}), "ioilc", 20, input_delay=0)
        lines = stream.getvalue().splitlines()
        assert len(lines) == expected, lines
        assert all(line.startswith("foilc-hil: design ioilc (N = 20): ") for line in lines)
        if expected:
            assert "tuning" in lines[0] and "certificates" in lines[1] and "done" in lines[2]
