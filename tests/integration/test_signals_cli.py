"""Every exit path reports the stop: repeated signals during a run's stop (through the CLI, in a process).

Before the fix a second SIGINT 1 to 80 ms after the first raised ``KeyboardInterrupt`` inside the stop: stderr said
only ``interrupted``, the ``--json`` document had ``drive_stop: null`` and ``trials: []`` though trials were in the
log. Now later signals are counted and the stop finishes: exit 130, one stderr line with the confirmed stop, and
the document lists the trials in the log.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from tests.integration.test_log_failures import _assert_confirmed_stop, _finish, _logged_trials, long_run

pytestmark = pytest.mark.slow


@pytest.mark.parametrize(("follow_up", "delay"), [(signal.SIGINT, 0.001), (signal.SIGTERM, 0.03)])
def test_a_second_signal_during_the_stop_loses_nothing(
    tmp_path: Path, follow_up: signal.Signals, delay: float
) -> None:
    with long_run(tmp_path) as (process, out):
        process.send_signal(signal.SIGINT)
        time.sleep(delay)
        process.send_signal(follow_up)
        process.send_signal(signal.SIGINT)
        result = _finish(process)
    assert result.returncode == 130, result.stderr
    assert len(result.stderr) == 1 and "interrupted by SIGINT" in result.stderr[0], result.stderr
    _assert_confirmed_stop(result)
    listed = [trial["trial"] for trial in result.document["trials"]]  # type: ignore[attr-defined]
    assert len(listed) >= 2 and listed == _logged_trials(out)
