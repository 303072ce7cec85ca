"""A trial's /ilc/sample documents built from its columns (:func:`trial_samples_documents`) are orjson's text of
each row's document, byte for byte, whatever the floats; a trial written as columns makes the same messages as its
rows written one by one, and columns of vectors still go row by row."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from foilc_hil.io.mcap_log import read_log
from foilc_hil.io.mcap_writer import McapFileWriter, trial_samples_documents
from foilc_hil.io.records import TrialSamples

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, width=64)


def _truth(trial: int, sample_time: float, row: int, values: tuple[float, ...], axis: int | None) -> bytes:
    """The independent truth: the row's document as a dict in the schema's order, encoded by orjson (non-finite
    values are null: what orjson does with them)."""
    reference, output, control, error, big_e = values
    document = {"trial": trial, "t": (row + 1) * sample_time, "reference": reference, "output": output,
                "control": control, "error": error, "E": big_e, "sample": row}
    if axis is not None:
        document["axis"] = axis
    return orjson.dumps(document)


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(
    rows=st.lists(st.tuples(ANY_FLOAT, ANY_FLOAT, ANY_FLOAT, ANY_FLOAT, ANY_FLOAT), max_size=40),
    trial=st.integers(1, 10**6),
    sample_time=st.sampled_from([0.001, 0.0025, 0.01, 1e-7, 0.3]),
    axis=st.one_of(st.none(), st.integers(1, 127)),
)
def test_documents_are_orjson_of_each_rows_document(
    rows: list[tuple[float, ...]], trial: int, sample_time: float, axis: int | None
) -> None:
    reference, output, control, error, big_e = (np.array([row[k] for row in rows], dtype=np.float64) for k in range(5))
    documents = trial_samples_documents(
        TrialSamples(trial, sample_time, reference, output, control, error, big_e, axis=axis)
    )
    assert documents == [_truth(trial, sample_time, i, row, axis) for i, row in enumerate(rows)]


def test_latched_is_written_after_E_as_the_record_writes_it() -> None:
    rng = np.random.default_rng(5)
    columns = [rng.standard_normal(20) for _ in range(6)]
    columns[5][3] = np.nan
    reference, output, control, error, big_e, latched = columns
    trial = TrialSamples(4, 0.001, reference, output, control, error, big_e, axis=2, latched=latched)
    documents = trial_samples_documents(trial)
    assert documents == [orjson.dumps(record.to_json()) for record in trial.records()]
    assert documents is not None and b'"latched":null,"sample":3,"axis":2}' in documents[3]


def test_exponents_negative_zero_and_non_finite_values_are_spelled_as_orjson_spells_them() -> None:
    awkward = np.array([1e16, 1e-5, -0.0, 5e-324, np.nan, np.inf, -np.inf, 1.5e300, 0.1, 123456789.0])
    columns = [np.roll(awkward, k) for k in range(5)]
    reference, output, control, error, big_e = columns
    documents = trial_samples_documents(TrialSamples(3, 0.001, reference, output, control, error, big_e))
    assert documents is not None and len(documents) == len(awkward)
    for i, document in enumerate(documents):
        assert document == _truth(3, 0.001, i, tuple(float(column[i]) for column in columns), None)
    assert b'"reference":1e+16' in documents[0] and b'"reference":-0.0' in documents[2]
    assert b'"reference":null' in documents[4]


def test_a_trial_as_columns_makes_the_messages_of_its_rows(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    grid = rng.standard_normal((300, 2)) * 1e-6  # strided views, small values (exponents)
    trial = TrialSamples(2, 0.001, grid[:, 0], grid[:, 1], np.arange(300), grid[:, 0] - grid[:, 1], grid[:, 1],
                         axis=4)
    as_columns, as_rows = tmp_path / "columns.mcap", tmp_path / "rows.mcap"
    with McapFileWriter(as_columns, config_yaml=None, fsync=False) as writer:
        writer.write_trial_samples(trial, 1_000)
    with McapFileWriter(as_rows, config_yaml=None, fsync=False) as writer:
        for record in trial.records():
            writer.write_sample(record, 1_000)
    assert as_columns.read_bytes() == as_rows.read_bytes()
    samples = read_log(as_columns).samples
    assert len(samples) == 300 and samples[299]["sample"] == 299 and samples[0]["axis"] == 4


def test_columns_of_vectors_are_written_row_by_row(tmp_path: Path) -> None:
    vectors = np.arange(12, dtype=np.float64).reshape(6, 2)  # two outputs: each row's values are lists
    trial = TrialSamples(1, 0.01, vectors, vectors + 0.5, np.zeros(6), vectors - 0.5, vectors * 0.0)
    assert trial_samples_documents(trial) is None
    path = tmp_path / "vectors.mcap"
    with McapFileWriter(path, config_yaml=None, fsync=False) as writer:
        writer.write_trial_samples(trial)
    samples = read_log(path).samples
    assert [row["output"] for row in samples] == [[0.5, 1.5], [2.5, 3.5], [4.5, 5.5], [6.5, 7.5], [8.5, 9.5],
                                                   [10.5, 11.5]]
