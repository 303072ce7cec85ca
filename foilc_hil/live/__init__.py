"""The live view: a run (``run --live``) or a log (``replay --live``) served to Foxglove over its WebSocket protocol
with foxglove-sdk, one channel per topic of the MCAP layout and ``/drive/state`` (docs/live-view.md).

- :mod:`foilc_hil.live.options` -- ``--live [HOST:]PORT`` and its companions, checked (:class:`LiveOptions`);
- :mod:`foilc_hil.live.server` -- the Foxglove server and its channels (:class:`LiveServer`);
- :mod:`foilc_hil.live.messages` -- each channel's JSON payload, as the log writes it;
- :mod:`foilc_hil.live.publisher` -- a run's view, fed beside the log, never holding the loop (:class:`LivePublisher`);
- :mod:`foilc_hil.live.replay` -- a log streamed at its recorded pace, or faster (:func:`stream_log`).

This package imports foxglove-sdk only when a server is started (:class:`LiveServer`).
"""

from __future__ import annotations

__all__: list[str] = []
