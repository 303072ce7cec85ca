"""Which law a command runs: the command line overrides the config file, which overrides the default (foilc).

Each command is run through the CLI entry point (``foilc_hil.cli.main``) on a config whose ``law.kind`` is not
the default, once without ``--law`` (the file's law) and once naming another (the command line's). ``replay`` and
``report`` take the law from the log they read (the law that ran), ``demo`` compares its two fixed laws, and
``tune`` tunes the fractional PD whatever the law: none of them has a law to choose.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
import yaml

from foilc_hil.cli import main
from foilc_hil.config import LawKind
from foilc_hil.errors import InfeasibleDesignError
from foilc_hil.io.mcap_log import read_log

pytestmark = pytest.mark.filterwarnings("ignore:Solution may be inaccurate")

#: a first-order axis, 20 samples a trial: each design and trial is quick
DOCUMENT: dict[str, Any] = {
    "plant": {"a": -1.23, "b": 1.68, "c": 1.0},
    "reference": {"profile": "piecewise", "segments": [{"duration": 1.0, "start": 1.0}]},
    "sample_time": 0.05,
    "trials": 2,
    "tuning": {"kp": 0.05, "r": 0.8},
    "synthesis": {"design": "paper"},
}


def _config(tmp_path: Path, law: dict[str, Any] | None, **sections: Any) -> Path:
    document = {**DOCUMENT, **sections}
    if law is not None:
        document["law"] = law
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def _json(capsys: pytest.CaptureFixture[str], argv: Sequence[str]) -> dict[str, Any]:
    code = main(list(argv))
    captured = capsys.readouterr()
    assert code == 0, captured.err
    document: dict[str, Any] = json.loads(captured.out)
    return document


P_TYPE = {"kind": "p-type", "p_type_gain": 0.5}


@pytest.mark.parametrize(
    ("law", "option", "expected"),
    [(P_TYPE, [], "p-type"), (P_TYPE, ["--law", "ioilc"], "ioilc"), (None, [], "foilc")],
    ids=["file", "command-line", "default"],
)
def test_synthesize(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], law: dict[str, Any] | None, option: list[str], expected: str
) -> None:
    document = _json(capsys, ["synthesize", "--config", str(_config(tmp_path, law)), "--json", *option])
    assert document["law"] == expected


@pytest.mark.parametrize(
    ("option", "expected"), [([], "p-type"), (["--law", "ioilc"], "ioilc")], ids=["file", "command-line"]
)
def test_simulate(tmp_path: Path, capsys: pytest.CaptureFixture[str], option: list[str], expected: str) -> None:
    document = _json(capsys, ["simulate", "--config", str(_config(tmp_path, P_TYPE)), "--json", *option])
    assert document["law"] == expected


#: the bench's drive for a 20-sample trial on the embedded emulator (generous supervision: a shared machine)
DRIVE = {
    "drive": {"node_id": 1, "mode": "csv", "velocity_scale": 1000.0, "velocity_limit": 500.0,
              "heartbeat_timeout_factor": 10.0, "heartbeat_consumer_ms": 2000},
    "bench": {"settle_time": 0.02, "settle_tolerance": 0.05},
}  # fmt: skip


@pytest.mark.parametrize(
    ("option", "expected"), [([], "ioilc"), (["--law", "p-type"], "p-type")], ids=["file", "command-line"]
)
def test_run(tmp_path: Path, capsys: pytest.CaptureFixture[str], option: list[str], expected: str) -> None:
    """The run's document, its logged design and its logged config all name the law that ran."""
    config = _config(tmp_path, {"kind": "ioilc"}, **DRIVE)
    out = tmp_path / "run.mcap"
    argv = ["run", "--config", str(config), "--emulator", "embedded", "--trials", "1", "--out", str(out), "--json"]
    document = _json(capsys, [*argv, *option])
    assert document["law"] == expected
    log = read_log(out)
    assert log.design is not None and log.design["law"] == expected
    assert log.config_yaml is not None and yaml.safe_load(log.config_yaml)["law"]["kind"] == expected


class _LawsChosenError(InfeasibleDesignError):
    """Stands in for the Monte Carlo: stops the command (exit 3) with the laws it was asked to run."""


@pytest.fixture
def robustness_laws(monkeypatch: pytest.MonkeyPatch) -> None:
    """No cluster and no draws: the command's laws are all these tests read."""

    @contextlib.contextmanager
    def no_client(address: str | None, workers: int) -> Iterator[None]:
        yield None

    def report_laws(config: Any, laws: Sequence[LawKind], *args: Any, **kwargs: Any) -> None:
        raise _LawsChosenError(",".join(laws))

    monkeypatch.setattr("foilc_hil.commands.robustness._client", no_client)
    monkeypatch.setattr("foilc_hil.loop.robustness.run_robustness", report_laws)


@pytest.mark.usefixtures("robustness_laws")
@pytest.mark.parametrize(
    ("law", "option", "expected"),
    [
        ({"kind": "gradient"}, [], "gradient,foilc,ioilc,noilc"),
        ({"kind": "ioilc"}, [], "ioilc,foilc,noilc"),
        (None, [], "foilc,ioilc,noilc"),
        ({"kind": "gradient"}, ["--laws", "p-type,noilc"], "p-type,noilc"),
    ],
    ids=["file-first", "file-not-repeated", "default", "command-line"],
)
def test_robustness(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], law: dict[str, Any] | None, option: list[str], expected: str
) -> None:
    """Without ``--laws`` the config's law is run first, then the others it is compared with; ``--laws`` decides
    alone."""
    config = _config(tmp_path, law)
    code = main(["robustness", "--config", str(config), "--scheduler", "inprocess", "--json", *option])
    captured = capsys.readouterr()
    assert code == 3
    assert json.loads(captured.out)["error"]["message"] == expected
