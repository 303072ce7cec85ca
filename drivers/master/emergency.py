"""The master's EMCY consumer: the drive's emergency frames as typed errors (:class:`EmcyConsumer`).

canopen's ``EmcyConsumer`` unpacks without a length check and would stop the Notifier's callbacks on a short frame;
this one decodes with :func:`drivers.emcy.decode_emcy` (a frame of the wrong length is a bad frame), ignores the
"error reset" codes, flags the heartbeat fault for EMCY 0x8130 (the drive lost the master's heartbeat) and posts the
:class:`~drivers.errors.EmergencyError` for the next wait for feedback.
"""

from __future__ import annotations

import logging
import time

from drivers.cia301 import EmcyCode
from drivers.emcy import decode_emcy
from drivers.errors import ProtocolError
from drivers.master.inbox import Inbox

__all__ = ["EmcyConsumer"]

logger = logging.getLogger("drivers.cia402_master")  # the master's log, as before the split into services


class EmcyConsumer:
    """EMCY frames of drive ``node_id`` into ``inbox``; ``frames`` counts them (guarded by ``inbox.cv``)."""

    def __init__(self, node_id: int, inbox: Inbox) -> None:
        self._node_id = node_id
        self._inbox = inbox
        self.frames = 0

    def on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """The Notifier thread's callback for the drive's EMCY COB-ID."""
        inbox = self._inbox
        try:
            emergency = decode_emcy(data, time.monotonic())
        except ProtocolError as exc:
            inbox.post(exc, bad_frame=True)
            return
        with inbox.cv:
            self.frames += 1
            if emergency.is_reset:
                return
            if emergency.code == EmcyCode.HEARTBEAT_LOSS:
                inbox.heartbeat_fault = True
            inbox.errors.append(emergency.error())
            inbox.cv.notify_all()
        # info, not warning: the EMCY is raised to whoever waits on the drive, and the command's one line says it
        logger.info("node %d: %s", self._node_id, emergency.error())
