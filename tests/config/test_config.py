"""Config loading: key paths, did-you-mean, precedence."""

from __future__ import annotations

from pathlib import Path

import pytest

from foilc_hil.config import load_config
from foilc_hil.errors import ConfigError


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "c.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("plant:\n  bb: 1\n", "plant.bb: unknown key (did you mean 'b'?)"),
        ("plantt: {}\n", "plantt: unknown key (did you mean 'plant'?)"),
        ("plant:\n  a: [[1, 2], [3]]\n", "plant.a: row 1 has 1 entries, row 0 has 2"),
        ("sample_time: -1\n", "sample_time: Input should be greater than 0"),
        ("tuning:\n  kp: 1\n", "tuning: give both 'kp' and 'r', or neither"),
        ("plant: {saturation: {u_min: 2, u_max: 1}}\n", "plant.saturation: u_min must be below u_max"),
        ("- a\n- b\n", "the top level must be a mapping of sections"),
        ("plant: [\n", "line"),
    ],
)
def test_bad_values_name_file_and_key(tmp_path: Path, text: str, expected: str) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    assert expected in message
    assert "\n" not in message


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "absent.yaml")


def test_precedence_cli_over_file_over_default(tmp_path: Path) -> None:
    path = _write(tmp_path, "trials: 7\nsample_time: 0.002\n")
    config = load_config(path, {"trials": 3, "tuning.crossover": None})
    assert config.trials == 3  # CLI wins over file
    assert config.sample_time == 0.002  # file wins over default
    assert config.synthesis.tau == pytest.approx(0.868)  # default fills the rest
    assert config.tuning.crossover is None  # a None override leaves the file/default alone


def test_config_error_is_a_value_error() -> None:
    assert issubclass(ConfigError, ValueError)


def test_errors_found_after_loading_name_the_config_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The tuner finds the missing spec after the file loaded; the CLI still names the file, on one line."""
    from foilc_hil.cli import main

    path = _write(tmp_path, "plant: {a: -1.0, b: 2.0}\n")
    assert main(["tune", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"foilc-hil tune: {path}: tuning.crossover: ")
    assert err.count("\n") == 1
