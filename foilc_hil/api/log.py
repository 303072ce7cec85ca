"""Logs as arrays: :func:`open_log` and :class:`Log` (the run's config, its design, its trials, its CAN frames)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from foilc_hil.api.results import ARRAYS, TrialResult
from foilc_hil.errors import InputError, LogFormatError

if TYPE_CHECKING:
    import can
    import pandas

    from foilc_hil.config import Config
    from foilc_hil.design.record import Design
    from foilc_hil.io.mcap_log import LogContents

__all__ = ["Log", "open_log"]


def open_log(path: str | Path) -> Log:
    """Open a log written by ``foilc-hil run``, ``simulate``, :class:`~foilc_hil.Bench` or
    :func:`~foilc_hil.simulate`, and read its trials (the CAN frames are read by :meth:`Log.frames`, when asked).

    Parameters
    ----------
    path
        The MCAP file.

    Returns
    -------
    Log
        Everything readable: a log cut short (a crash, a full disk) gives the trials it holds complete
        (:attr:`Log.damage` says where it ends).

    Raises
    ------
    LogFormatError
        The file does not exist, cannot be read or is not MCAP.
    """
    from foilc_hil.io.mcap_log import read_log
    from foilc_hil.io.schemas import TOPIC_SAMPLE, TOPIC_TRIAL

    return Log(Path(path), read_log(path, (TOPIC_SAMPLE, TOPIC_TRIAL)))


class Log:
    """A log's contents (:func:`open_log` makes it).

    Parameters
    ----------
    path
        The file.
    contents
        What :func:`foilc_hil.io.mcap_log.read_log` read of it (the samples and trial records).

    Attributes
    ----------
    path
        The file.
    damage
        ``""``, or where and how the file ends before its footer (it was cut or damaged: what precedes is read).
    """

    def __init__(self, path: Path, contents: LogContents) -> None:
        self.path = path
        self.damage = contents.damage
        self._contents = contents

    @property
    def config(self) -> Config:
        """The run's resolved configuration (the ``foilc_hil.config`` record).

        Raises
        ------
        LogFormatError
            The log has none, or it does not load.
        """
        from foilc_hil.logtools.replay import logged_config

        return logged_config(self._contents)

    @property
    def design(self) -> Design | None:
        """The design the run's law ran with (the ``foilc_hil.design`` record); ``None``: the log has none.

        Raises
        ------
        LogFormatError
            The record does not load.
        """
        from foilc_hil.design.record import Design

        document = self._contents.design
        if document is None:
            return None
        try:
            return Design.from_json(document)
        except InputError as exc:
            raise LogFormatError(f"{self.path}: metadata foilc_hil.design: {exc}") from None

    @property
    def axes(self) -> tuple[int, ...]:
        """The node ids of a run of several axes (``axes:``); ``()`` for one axis."""
        from foilc_hil.logtools.axes import log_axes

        return log_axes(self._contents)

    def trials(self, axis: int | None = None) -> list[TrialResult]:
        """The completed trials (those with an ``/ilc/trial`` record), in order.

        Parameters
        ----------
        axis
            A run of several axes: the node id whose trials to read (required there); ``None`` for one axis.

        Returns
        -------
        list of TrialResult
            Equal to those the run yielded (every array bit for bit).

        Raises
        ------
        InputError
            ``axis`` missing for a log of several axes, or naming none of them.
        LogFormatError
            A trial's rows or record are malformed, or the log has no config (its sample time).
        """
        axes = self.axes
        if axes and axis not in axes:
            raise InputError(f"axis: this log has axes {list(axes)}; name one" + (f", not {axis}" if axis else ""))
        if not axes and axis is not None:
            raise InputError(f"axis: this log is of one axis, not of axes (got {axis})")
        rows: dict[int, list[Mapping[str, Any]]] = {}
        for sample in self._contents.samples:
            if sample.get("axis") == axis:
                rows.setdefault(int(sample["trial"]), []).append(sample)
        sample_time = float(self.config.sample_time)
        return [TrialResult.from_log(record, _in_order(rows.get(int(record["trial"]), [])), sample_time)
                for record in self._contents.trials if record.get("axis") == axis]

    def frames(self) -> Iterator[can.Message]:
        """The ``/can`` frames in file order, as python-can messages (``is_rx`` tells the direction; read lazily).

        Raises
        ------
        LogFormatError
            A frame record is malformed.
        """
        from foilc_hil.io.mcap_log import McapLogReader, frame_to_message
        from foilc_hil.io.schemas import TOPIC_CAN

        with McapLogReader(self.path) as reader:
            for message in reader.iter_messages((TOPIC_CAN,)):
                yield frame_to_message(message.data)

    def to_pandas(self) -> pandas.DataFrame:
        """Every ``/ilc/sample`` row as a pandas ``DataFrame``: columns ``trial``, ``sample``, ``t``, ``reference``,
        ``output``, ``control``, ``error``, ``E`` (and ``axis`` in a log of several axes).

        Raises
        ------
        ImportError
            pandas is not installed: ``pip install 'foilc-hil[pandas]'``.
        """
        try:
            import pandas
        except ImportError as exc:
            raise ImportError("Log.to_pandas needs pandas: install the optional extra, "
                              "pip install 'foilc-hil[pandas]'") from exc
        columns = ["trial", "sample", "t", *ARRAYS, *(["axis"] if self.axes else [])]
        return pandas.DataFrame.from_records(
            [[row.get(name) for name in columns] for row in self._contents.samples], columns=columns)

def _in_order(rows: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """A trial's rows by their ``sample`` index (as written: in order, unless another tool wrote the log)."""
    if all("sample" in row for row in rows):
        return sorted(rows, key=lambda row: int(row["sample"]))
    return list(rows)
