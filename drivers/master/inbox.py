"""What the receive side hands the master's control thread: :class:`Inbox`.

The Notifier thread (EMCY, heartbeat, TPDO callbacks), the heartbeat watchdog thread and, with a cyclic receiver, the
control thread itself post here; the control thread raises what was posted from its next wait for feedback. One
condition (``cv``, over a reentrant lock) guards the inbox *and* the cyclic path's feedback
(:class:`~drivers.master.cyclic.CyclicPath`): a wait looks at both at once, and a TPDO callback that finds a bad
frame posts it while holding the lock.
"""

from __future__ import annotations

import collections
import threading

from drivers.errors import BadFrameError, DriveNmtStateError, ProductError

__all__ = ["Inbox"]


class Inbox:
    """Errors to raise, the heartbeat-fault flag, the NMT departure and the count of bad frames.

    Attributes
    ----------
    cv, lock
        The condition, and its lock for the per-cycle paths (``with lock`` skips ``Condition``'s Python wrappers).
    errors
        Errors not yet raised, oldest first (the control thread reads it only under ``lock``).
    heartbeat_fault
        The drive's heartbeat supervision failed (the master lost it, or the drive reported losing the master's):
        ``fault_reset`` restores communication first.
    nmt_departure
        The drive left NMT OPERATIONAL and the error was not yet raised to the caller: the final stop reports it even
        when another error ended the run first.
    bad_frames
        Frames from the drive that did not decode.
    fatal_bad_frames
        A frame that does not decode is raised (:class:`BadFrameError`); False: only counted (the bench's
        ``bench.faults.bad_frame: count``).
    """

    def __init__(self) -> None:
        self.cv = threading.Condition(threading.RLock())
        self.lock = self.cv._lock  # type: ignore[attr-defined]  # the per-cycle paths take the lock itself
        self.errors: collections.deque[ProductError] = collections.deque()
        self.heartbeat_fault = False
        self.nmt_departure: DriveNmtStateError | None = None
        self.bad_frames = 0
        self.fatal_bad_frames = True

    def post(self, error: ProductError, *, bad_frame: bool = False) -> None:
        """Queue ``error`` for the control thread and wake a waiter; a bad frame is counted, and raised as a
        :class:`BadFrameError` only when :attr:`fatal_bad_frames`."""
        with self.cv:
            if bad_frame:
                self.bad_frames += 1
                if not self.fatal_bad_frames:
                    return
                error = BadFrameError(str(error))
            self.errors.append(error)
            self.cv.notify_all()

    def post_departure(self, error: DriveNmtStateError) -> None:
        """The drive left NMT OPERATIONAL: remember it for the stop report and queue it."""
        with self.cv:
            self.nmt_departure = error
        self.post(error)

    def post_heartbeat_fault(self, error: ProductError) -> None:
        """Queue ``error`` and flag the heartbeat fault (communication is restored before a fault reset)."""
        self.post(error)
        with self.cv:
            self.heartbeat_fault = True

    def delivered(self, error: BaseException) -> None:
        """``error`` reached the caller: if it is the NMT departure, the stop report no longer needs to say it."""
        with self.cv:
            if error is self.nmt_departure:
                self.nmt_departure = None

    def reset(self) -> None:
        """Forget everything pending (a fresh ``configure``)."""
        with self.cv:
            self.errors.clear()
            self.heartbeat_fault = False
            self.nmt_departure = None

    def take_heartbeat_fault(self) -> bool:
        """Drop the pending errors (a fault reset answers them); whether the heartbeat fault is set."""
        with self.cv:
            self.errors.clear()
            return self.heartbeat_fault

    def clear_fault(self) -> None:
        """The fault is reset: drop the errors of the way there and the heartbeat-fault flag."""
        with self.cv:
            self.errors.clear()
            self.heartbeat_fault = False

    def pending_faults(self) -> tuple[str, ...]:
        """Errors the drive reported that nobody raised yet (e.g. an EMCY during the final stop), emptied."""
        with self.cv:
            errors: list[BaseException] = list(self.errors)
            if self.nmt_departure is not None and self.nmt_departure not in errors:
                errors.append(self.nmt_departure)  # raised by a stop attempt, never to the caller: say it
            self.errors.clear()
            self.nmt_departure = None
        return tuple(str(error) for error in errors)
