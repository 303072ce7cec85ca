"""The scripts of ``examples/`` run on the embedded emulator, with short trial counts, as a user runs them (their
``__main__``, in this process: the imports are shared with the other tests), and print what they must."""

from __future__ import annotations

import re
import runpy
import sys
from pathlib import Path

import pytest

import foilc_hil as fh
from tests.support.bench import bench_config

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def run_example(name: str, *args: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``examples/<name>`` as a script with ``args``; its standard output (it must exit 0)."""
    monkeypatch.chdir(ROOT)
    monkeypatch.setattr(sys, "argv", [str(EXAMPLES / name), *args])
    with pytest.raises(SystemExit) as ended:
        runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    out = capsys.readouterr().out
    assert ended.value.code == 0, out
    return out


def test_the_commissioning_script(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    out = run_example("commission.py", "--nodes", "1-4", "--listen", "0.05", monkeypatch=monkeypatch, capsys=capsys)
    assert re.search(r"^found node 1: profile 402", out, re.MULTILINE), out
    assert "producer heartbeat time now 250 ms" in out  # written by name, read back by index
    assert re.search(r"^enabled: statusword 0x[0-9A-F]{2}37$", out, re.MULTILINE), out  # operation enabled
    assert "stop: confirmed, SWITCH_ON_DISABLED" in out


# the bench's whole run is `make test`'s; the inner loop runs the example on simulate
@pytest.mark.parametrize("where", [pytest.param((), id="simulate"),
                                   pytest.param(("--bench",), id="bench", marks=pytest.mark.slow)])
def test_comparing_two_laws_on_a_piecewise_reference(where: tuple[str, ...], monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    out = run_example("compare_laws.py", "--laws", "ioilc,p-type", "--trials", "2", *where, monkeypatch=monkeypatch,
                      capsys=capsys)
    rows = re.findall(r"^\s+(\d)\s+(\S+)\s+(\S+)$", out, re.MULTILINE)
    assert [row[0] for row in rows] == ["1", "2"], out
    # trial 1 starts from rest with no learned input: its SSE is the reference's energy, sum of (y_r)^2 over the
    # samples at 1 ms of ramps 0 -> 300 -> 0 over 0.3 s and a 0.4 s dwell at 300: 2 x 9e6 + 3.6e7
    for sse in rows[0][1:]:
        assert float(sse) == pytest.approx(5.4e7, rel=0.01)
    for k in (1, 2):
        assert float(rows[1][k]) < float(rows[0][k])  # both laws learn
    assert "lowest RMSE in the last trial:" in out


@pytest.mark.slow
def test_the_log_analysis_script(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    config = fh.load_config(bench_config(tmp_path), overrides={"law.kind": "p-type"})
    log = tmp_path / "sim.mcap"
    trials = fh.simulate(config, trials=3, out=log)
    out = run_example("analyse_log.py", str(log), monkeypatch=monkeypatch, capsys=capsys)
    table = re.findall(r"^\s+(\d)\s+(\S+)\s+(\S+)\s+\S+\s+\S+$", out, re.MULTILINE)
    assert [(int(k), float(sse)) for k, sse, _ in table] == [
        (trial.index, float(f"{trial.sse:.6g}")) for trial in trials]
    assert "law p-type" in out and "design: P =" in out
    assert re.search(r"^trial\s*$", out, re.MULTILINE)  # the DataFrame's per-trial table (pandas: the dev extra)
    monkeypatch.setitem(sys.modules, "pandas", None)  # without pandas the script says what to install
    out = run_example("analyse_log.py", str(log), monkeypatch=monkeypatch, capsys=capsys)
    assert "no DataFrame" in out and "foilc-hil[pandas]" in out


def test_the_examples_use_only_the_documented_api() -> None:
    """Each example imports the packages' tops only, and every name it takes from them is in their ``__all__`` (the
    names docs/api.md documents: tests/project/test_api_docs.py)."""
    import ast
    import importlib

    tops = {"foilc_hil", "drivers", "plant_emulator"}
    for path in sorted(EXAMPLES.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        aliases: dict[str, str] = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    assert alias.name.split(".")[0] not in tops or alias.name in tops, (path.name, alias.name)
                    aliases[alias.asname or alias.name] = alias.name
            elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in tops:
                assert node.module in tops, (path.name, node.module)
                public = importlib.import_module(node.module).__all__
                assert all(alias.name in public for alias in node.names), (path.name, node.module)
        used = [(aliases[node.value.id], node.attr) for node in ast.walk(tree) if isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name) and aliases.get(node.value.id) in tops]
        assert used, path.name
        for package, name in used:
            assert name in importlib.import_module(package).__all__, (path.name, f"{package}.{name}")
