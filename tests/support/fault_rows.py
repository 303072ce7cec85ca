"""Rows of the fault matrix (``docs/reliability.md``) whose faults are not ``--inject`` kinds: the product's own
parts failing (its log writer, its disk, its signals), hostile input, a lost master. Each row names the test that
exercises it, and ``tests/integration/test_fault_matrix.py`` checks that the test exists, so a row cannot outlive its
test.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TESTED_ELSEWHERE", "TestedRow"]


@dataclass(frozen=True)
class TestedRow:
    """One fault of the docs' table, tested by ``test`` (``dir/file.py::function``, under ``tests/``)."""

    __test__ = False  # pytest: not a test class

    fault: str
    how: str
    test: str
    outcome: str
    after: str
    kept: str
    where: str = "through the CLI, a process of its own"

    def outcome_text(self) -> str:
        return self.outcome

    def kept_text(self) -> str:
        return self.kept


_STOPPED = "disabled, read back"
_LOG = "`--json` `trials` lists exactly the trials in the file"

TESTED_ELSEWHERE: tuple[TestedRow, ...] = (
    TestedRow("the log writer process stopped (a hung NFS or USB disk)", "`kill -STOP` the writer mid-run",
              "integration/test_log_failures.py::test_a_stopped_writer_stops_the_run_and_the_drive",
              "exit 1, one line naming the log (`stalled`), within the writer's stall timeout; the loop never "
              "blocks on it", _STOPPED, f"{_LOG}; the writer is not killed: continued, it finishes the file"),
    TestedRow("the log writer process killed", "`kill -KILL` the writer mid-run",
              "integration/test_log_failures.py::test_a_killed_writer_stops_the_run_and_the_drive",
              "exit 1, one line naming the log (`the log writer process stopped`)", _STOPPED,
              f"{_LOG} (no footer: the damage-tolerant reader reads them)"),
    TestedRow("SIGINT while the log writer process is stopped", "`kill -STOP` the writer, then SIGINT the run",
              "integration/test_log_failures.py::test_sigint_while_the_writer_is_stopped_is_honoured",
              "exit 130 (or 1 when the stall is found first), the signal honoured at the next cycle", _STOPPED,
              _LOG),
    TestedRow("the disk full", "a 384 KiB tmpfs in a private mount namespace",
              "integration/test_log_failures.py::test_a_full_disk_stops_the_run_at_the_next_trial_boundary",
              "exit 1 at the next trial boundary at the latest, one line `F: No space left on device`", _STOPPED,
              f"{_LOG}; `trials_run` at most two more"),
    TestedRow("a second SIGINT or a SIGTERM during the stop", "SIGINT, then SIGINT 1 ms or SIGTERM 30 ms later",
              "integration/test_signals_cli.py::test_a_second_signal_during_the_stop_loses_nothing",
              "exit 130, one line with the confirmed stop (later signals are counted, not raised)", _STOPPED,
              _LOG),
    TestedRow("the emulated physics diverge mid-run", "a plant whose output turns NaN in trial 2",
              "integration/test_hostile_run_inputs.py::test_physics_that_diverge_mid_run_fault_the_drive_and_the_stop_is_"
              "reported", "exit 1, one line naming EMCY 0x6100 (the drive faults, its plant restarts)",
              "FAULT, read back", "the trials before it", where="in-process, embedded emulator"),
    TestedRow("a drive fault (EMCY)", "`--inject emcy-over-current@2+20`",
              "integration/test_hostile_run_inputs.py::test_a_drive_fault_is_one_stderr_line_at_the_default_log_level",
              "exit 1, exactly one stderr line at the default log level", "FAULT, read back", "trial 1"),
    TestedRow("a hostile config: a 1e12 s segment, `sample_time: 1e-300`, a PMSM inertia of 1e-30 or 1e-9",
              "`run`, `simulate`, `synthesize` with it",
              "integration/test_hostile_run_inputs.py::test_a_hostile_config_is_refused_naming_the_field",
              "exit 2, one line naming the field, before the design", "never enabled", "no log"),
    TestedRow("`--out` a directory, in a missing directory, or on a read-only file system", "`run`, `simulate`",
              "integration/test_hostile_run_inputs.py::test_a_bad_out_is_refused_before_the_design",
              "exit 2, one line naming the path and the cause, before the design", "never enabled", "no log"),
    TestedRow("an EDS that is a device, a FIFO, a directory, or over 1 MiB", "`drive.eds: /dev/zero` and others",
              "drivers/test_od.py::test_special_files_are_refused_with_their_cause",
              "exit 2, one line naming the file and what it is", "never enabled", "no log",
              where="in-process"),
    TestedRow("the bench killed (its heartbeat and SYNCs gone) in lockstep", "no heartbeat, no SYNC, axis moving",
              "plant_emulator/test_emulator_faults.py::test_a_lost_master_in_lockstep_ends_the_quick_stop_on_the_drives_own_clock",
              "the drive's 0x6007 quick stop runs on its own clock", "SWITCH ON DISABLED, power off, read back",
              "the trials before it", where="emulator on a wall-clock bus"),
)
