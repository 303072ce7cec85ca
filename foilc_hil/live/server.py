"""The Foxglove WebSocket server of a live view (foxglove-sdk), with one channel per topic of the MCAP layout.

:class:`LiveServer` starts ``foxglove.start_server`` on its own :class:`foxglove.Context` (nothing else a process
logs through foxglove-sdk's global context reaches the viewer, and nothing of the view reaches another sink) and
advertises the channels of :data:`~foilc_hil.io.schemas.LIVE_TOPICS`, each with the JSON schema the log registers
(the same schema name and text: :func:`~foilc_hil.io.schemas.schema_bytes`) and the log's channel metadata (units).

The server runs in foxglove-sdk's own threads (Rust): :meth:`LiveServer.log` copies the payload into each subscribed
viewer's queue and returns; a viewer that reads too slowly loses the oldest messages of its queue
(``message_backlog_size``), and a channel nobody subscribed to costs nothing (:meth:`LiveServer.wanted` is checked
before a payload is even built). So a slow or absent viewer never holds the caller.

foxglove-sdk is imported here only (``pip install 'foilc-hil[live]'``; the dev extra has it): a command without
``--live`` never loads it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from types import TracebackType
from typing import Any, Final, Self

from foilc_hil.errors import InputError
from foilc_hil.io.schemas import (
    LIVE_TOPICS,
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    TOPIC_DRIVE_STATE,
    TOPIC_SAMPLE,
    channel_metadata,
    schema_bytes,
)
from foilc_hil.live.options import LiveAddress

__all__ = ["BACKLOG", "LiveServer", "live_channel_metadata"]

BACKLOG: Final = 65536
"""Messages each viewer's queue holds before its oldest is dropped: a trial's rows arrive at once, and foxglove-sdk's
default (1024) dropped most of a trial of 6,000 rows before a viewer on the same machine had read them."""
_POLL: Final = 0.02


def live_channel_metadata(config_yaml: str | None) -> dict[str, dict[str, str]]:
    """Each live channel's metadata: the log's (:func:`~foilc_hil.io.schemas.channel_metadata`: units) and, for
    ``/drive/state``, the velocity in the unit of ``/ilc/sample``'s output."""
    metadata = channel_metadata(config_yaml)
    output = json.loads(metadata[TOPIC_SAMPLE]["units"]).get("output")
    metadata[TOPIC_DRIVE_STATE] = {"units": json.dumps({"velocity": output} if output else {}, sort_keys=True)}
    return metadata


class LiveServer:
    """A running Foxglove WebSocket server with the live view's channels (a context manager: :meth:`close`).

    Parameters
    ----------
    address
        Where to listen (:class:`~foilc_hil.live.options.LiveAddress`; port 0: any free one, see :attr:`port`).
    name
        The server's name, shown by Foxglove.
    config_yaml
        The run's config as YAML (the channels' units); ``None``: time units only.

    Raises
    ------
    InputError
        foxglove-sdk is not installed, or the address cannot be listened on (in use, not this machine's).
    """

    def __init__(self, address: LiveAddress, *, name: str = "foilc-hil", config_yaml: str | None = None) -> None:
        try:
            import foxglove
        except ImportError:
            raise InputError("--live: needs foxglove-sdk (pip install 'foilc-hil[live]')") from None
        self.address = address
        self._context = foxglove.Context()
        metadata = live_channel_metadata(config_yaml)
        # the channels before the server: a viewer then gets them in its first advertisement. Created after it, a
        # viewer connecting meanwhile was advertised a channel the server then called unknown when it subscribed
        # (foxglove-sdk 0.30.3: "attempted to subscribe to unknown channel"), and never got its messages
        self._channels: dict[str, Any] = {
            topic: foxglove.Channel(
                topic,
                schema=foxglove.Schema(name=schema_name, encoding=SCHEMA_ENCODING, data=schema_bytes(schema)),
                message_encoding=MESSAGE_ENCODING, context=self._context, metadata=dict(metadata[topic]),
            )
            for topic, (schema_name, schema) in LIVE_TOPICS.items()
        }
        try:
            self._server = foxglove.start_server(name=name, host=address.host, port=address.port,
                                                 context=self._context, message_backlog_size=BACKLOG)
        except Exception as exc:  # foxglove-sdk raises its own RuntimeError/OSError kinds for a bind failure
            for channel in self._channels.values():
                channel.close()
            raise InputError(f"--live: cannot serve on {address}: {exc}") from None
        self._closed = False

    @property
    def port(self) -> int:
        """The port the server listens on (the one the system picked for port 0)."""
        return int(self._server.port)

    def wanted(self, topic: str) -> bool:
        """A viewer is subscribed to ``topic``: only then is anything built for it."""
        return bool(self._channels[topic].has_sinks())

    def viewers(self) -> bool:
        """Some viewer is subscribed to some channel."""
        return any(channel.has_sinks() for channel in self._channels.values())

    def log(self, topic: str, payload: bytes, log_time_ns: int) -> None:
        """Send one JSON payload on ``topic`` at ``log_time_ns`` (the message's timestamp); never waits."""
        self._channels[topic].log(payload, log_time=log_time_ns)

    def log_all(self, topic: str, payloads: Iterable[bytes], log_time_ns: int) -> int:
        """Send payloads on ``topic``, all at one timestamp; returns how many."""
        log = self._channels[topic].log
        count = 0
        for payload in payloads:
            log(payload, log_time=log_time_ns)
            count += 1
        return count

    def wait_for_viewer(self, timeout: float) -> bool:
        """Block until a viewer subscribes to some channel, at most ``timeout`` seconds; ``True`` if one did."""
        deadline = time.monotonic() + timeout
        while not self.viewers():
            if time.monotonic() >= deadline:
                return False
            time.sleep(_POLL)
        return True

    def close(self, linger: float = 0.0) -> None:
        """Stop serving (idempotent), after up to ``linger`` seconds in which a viewer is still subscribed: stopping
        drops what the viewers' queues still hold, so a viewer that unsubscribes (or leaves) when it has what it
        wants ends the wait."""
        if self._closed:
            return
        self._closed = True
        deadline = time.monotonic() + linger
        while linger > 0 and self.viewers() and time.monotonic() < deadline:
            time.sleep(_POLL)
        for channel in self._channels.values():
            channel.close()
        self._server.stop()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None) -> None:
        self.close()
