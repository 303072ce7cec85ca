"""A Foxglove WebSocket client for the live view's tests (``python -m tests.support.live_client``), run by the tests
inside the private network namespace they create (``unshare --net``), beside the ``foilc-hil`` command it watches.

It speaks the protocol with the ``websockets`` package, not with foxglove-sdk: it connects with the subprotocol
``foxglove.sdk.v1`` (what foxglove-sdk 0.30's server accepts; it refuses the older ``foxglove.websocket.v1`` with
HTTP 400), reads ``serverInfo`` and ``advertise``, subscribes to every advertised channel under subscription ids of
its own, decodes each binary ``messageData`` frame (opcode 1, subscription id u32, timestamp u64 ns, payload, all
little-endian) and writes what it got as one JSON document: the server's info, the advertised channels, and each
message as ``[topic, timestamp, payload text]``. It leaves (unsubscribe, close) once it has the ``/ilc/trial``
message of trial ``--until-trial``, or when the server closes.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import struct
import time
from pathlib import Path
from typing import Any

import websockets

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 1
SUBSCRIPTION_BASE = 100  # subscription ids differ from channel ids: a server mixing them up is caught
_HEADER = struct.Struct("<BIQ")


async def _connect(url: str, timeout: float) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return await websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None)  # type: ignore[list-item]
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)


async def watch(url: str, until_trial: int, timeout: float) -> dict[str, Any]:
    """Connect, subscribe to everything, collect messages until trial ``until_trial``'s ``/ilc/trial``."""
    ws = await _connect(url, timeout)
    got: dict[str, Any] = {"subprotocol": ws.subprotocol, "server_info": None, "channels": [], "messages": []}
    topics: dict[int, str] = {}
    try:
        async for frame in ws:
            if isinstance(frame, str):
                document = json.loads(frame)
                if document["op"] == "serverInfo":
                    got["server_info"] = document
                elif document["op"] == "advertise":
                    got["channels"].extend(document["channels"])
                    subscriptions = [{"id": SUBSCRIPTION_BASE + c["id"], "channelId": c["id"]}
                                     for c in document["channels"]]
                    topics.update({s["id"]: c["topic"] for s, c in zip(subscriptions, document["channels"],
                                                                       strict=True)})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
                continue
            opcode, subscription, stamp = _HEADER.unpack_from(frame)
            if opcode != MESSAGE_DATA:
                continue
            topic, payload = topics[subscription], bytes(frame[_HEADER.size:]).decode("utf-8")
            got["messages"].append([topic, stamp, payload])
            if topic == "/ilc/trial" and json.loads(payload)["trial"] >= until_trial:
                await ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": sorted(topics)}))
                break
    except websockets.ConnectionClosed:
        pass
    await ws.close()
    return got


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--url", default="ws://127.0.0.1:8765")
    parser.add_argument("--until-trial", type=int, required=True)
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds to keep trying to connect")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    document = asyncio.run(watch(args.url, args.until_trial, args.timeout))
    args.out.write_text(json.dumps(document), encoding="utf-8")


if __name__ == "__main__":
    main()
