"""``/ilc/sample`` layout 2: every field of a row describes one instant; logs of layout 1 still verify.

``tests/data/run_layout1.mcap`` is a ``foilc-hil run --emulator embedded`` log (FOILC, 3 trials of 30 samples)
written by the bench before layout 2 existed (commit fc0939e): it has no ``foilc_hil.layout`` metadata.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from foilc_hil.cli import main
from foilc_hil.io.mcap_log import McapLogWriter, read_log
from foilc_hil.io.schemas import METADATA_LAYOUT
from foilc_hil.logtools.replay import sample_layout, verify_log

OLD_LOG = Path(__file__).resolve().parents[1] / "data" / "run_layout1.mcap"
TS = 0.05
CONFIG = f"""
plant: {{a: -1.23, b: 1.68, c: 1.0}}
reference:
  profile: piecewise
  segments: [{{duration: 0.5, start: 0.0, end: 1.0}}, {{duration: 0.5, start: 1.0}}]
sample_time: {TS}
trials: 3
law: {{kind: p-type, p_type_gain: 0.5}}
"""


@pytest.fixture(scope="module")
def simulated_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("layout")
    config = tmp / "c.yaml"
    config.write_text(CONFIG, encoding="utf-8")
    out = tmp / "sim.mcap"
    assert main(["simulate", "--config", str(config), "--out", str(out), "--json"]) == 0
    return out


def test_every_simulated_row_is_one_instant(simulated_log: Path) -> None:
    contents = read_log(simulated_log)
    assert contents.metadata[METADATA_LAYOUT] == {"ilc_sample": "2", "closing": "1"}
    assert sample_layout(contents) == 2
    trials = {record["trial"]: record for record in contents.trials}
    for row in contents.samples:
        assert row["error"] == row["reference"] - row["output"]  # bit for bit, in the same record
        assert row["t"] == pytest.approx((row["sample"] + 1) * TS, rel=1e-12)
    for trial, record in trials.items():
        rows = [row for row in contents.samples if row["trial"] == trial]
        assert record["initial_output"] == 0.0  # every trial starts from rest
        assert rows[-1]["output"] == record["final_output"]
        # the reference of the config at t: a ramp 0 -> 1 over 0.5 s, then 1 (independent of the log's arrays)
        for row in rows:
            assert row["reference"] == pytest.approx(min(row["t"] / 0.5, 1.0), abs=1e-12)


def test_a_layout2_log_verifies_and_a_row_out_of_step_is_caught(simulated_log: Path) -> None:
    contents = read_log(simulated_log)
    verification = verify_log(contents)
    assert verification.verified and verification.trials_checked == 3 and verification.samples_checked == 60
    # a row whose output is not its own reference - error (e.g. one sample late) fails verification
    index = next(i for i, row in enumerate(contents.samples) if row["trial"] == 2 and row["sample"] == 7)
    contents.samples[index] = {**contents.samples[index], "output": contents.samples[index - 1]["output"]}
    broken = verify_log(contents)
    assert not broken.verified
    assert broken.first_divergence is not None and broken.first_divergence.trial == 2
    assert broken.first_divergence.reason == "logged error of sample 7 is not reference - output"


def test_a_log_written_before_layout2_still_verifies(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    contents = read_log(OLD_LOG)
    assert METADATA_LAYOUT not in contents.metadata and sample_layout(contents) == 1
    # layout 1 really is the old alignment: a row's error belongs to the next row's output, not its own
    rows = [row for row in contents.samples if row["trial"] == 2]
    assert any(row["error"] != row["reference"] - row["output"] for row in rows)
    assert all(rows[i]["error"] == rows[i]["reference"] - rows[i + 1]["output"] for i in range(len(rows) - 1))
    copy = tmp_path / "old.mcap"
    shutil.copy(OLD_LOG, copy)
    assert main(["replay", str(copy), "--verify", "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["verified"] is True and document["trials_checked"] == 3


def test_an_unknown_layout_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "future.mcap"
    with McapLogWriter(path, config_yaml=None, fsync=False) as writer:
        writer.add_metadata(METADATA_LAYOUT, {"ilc_sample": "9"})
        writer.log_sample(1, 0.0, 1.0, 0.0, 0.0, 1.0, None, sample=0)
    assert main(["replay", str(path), "--verify", "--json"]) == 2
    assert "layout '9'" in json.loads(capsys.readouterr().out)["error"]["message"]
