"""What a live view is asked for: the address to serve on and how much to send (``--live`` and its companions).

``run`` and ``replay`` take the same options (:func:`add_live_options`); :func:`live_options` checks them into one
:class:`LiveOptions` (a bad value is an :class:`~foilc_hil.errors.InputError` naming the option: exit 2).
"""

from __future__ import annotations

import argparse
import ipaddress
import math
from dataclasses import dataclass
from typing import Final

from foilc_hil.errors import InputError

__all__ = [
    "DEFAULT_ADDRESS",
    "DEFAULT_CAN_RATE",
    "DEFAULT_HOST",
    "DEFAULT_LINGER",
    "DEFAULT_PORT",
    "DEFAULT_ROWS",
    "DEFAULT_ROW_RATE",
    "LiveAddress",
    "LiveOptions",
    "add_live_options",
    "live_options",
    "parse_address",
]

DEFAULT_HOST: Final = "127.0.0.1"
"""Loopback: the live view is served to this machine only unless the command line names another address."""
DEFAULT_PORT: Final = 8765
"""Foxglove's own default WebSocket port."""
DEFAULT_ADDRESS: Final = f"{DEFAULT_HOST}:{DEFAULT_PORT}"
DEFAULT_CAN_RATE: Final = 200.0
"""``/can`` frames a second at most. Why a limit: a 1 kHz bench puts 4,000 frames a second on the bus; a viewer
wants a sample of the traffic, and every message costs the server and the viewer CPU time (tens of microseconds
each, measured: on a busy 2-core host that is the loop's time)."""
DEFAULT_ROWS: Final = 2000
"""``/ilc/sample`` rows of a trial at most (every ``k``-th row beyond it): a plot of a trial needs no more, and the
rows are the bulk of what a run publishes (the demo's trials have 6,000)."""
DEFAULT_ROW_RATE: Final = 1000.0
"""``/ilc/sample`` rows a second at most, over the run: a lockstep run ends trials faster than real time (the ``make
bench`` run: 14 trials of 400 rows a second), and its every row sent cost the loop's 2-core host a fifth of its
throughput in the server's and the viewer's work (measured); a realtime 1 kHz run offers 1,000 a second."""
DEFAULT_LINGER: Final = 2.0
"""Seconds the server stays up after the run while a viewer is still subscribed: what was published last is
delivered (stopping the server drops what its per-viewer queue still holds)."""


@dataclass(frozen=True)
class LiveAddress:
    """Where the live view listens.

    Attributes
    ----------
    host
        An IP address (``127.0.0.1`` by default; ``0.0.0.0`` or another address serves other machines too).
    port
        The TCP port; 0 lets the system pick a free one (the server reports it).
    """

    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT

    def __str__(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"

    @property
    def loopback(self) -> bool:
        """The address is this machine's loopback."""
        return ipaddress.ip_address(self.host).is_loopback


@dataclass(frozen=True)
class LiveOptions:
    """Everything ``--live`` and its companions ask for.

    Attributes
    ----------
    address
        Where to serve.
    wait
        Seconds to wait, before the run (or the replay) starts, for a viewer to subscribe; 0: start at once.
    linger
        Seconds to keep serving after the end while a viewer is subscribed (:data:`DEFAULT_LINGER`).
    can_rate
        ``/can`` frames a second at most (:data:`DEFAULT_CAN_RATE`).
    rows
        ``/ilc/sample`` rows per trial at most (``run`` only; :data:`DEFAULT_ROWS`); 0: every row.
    row_rate
        ``/ilc/sample`` rows per second at most (``run`` only; :data:`DEFAULT_ROW_RATE`); 0: no limit.
    """

    address: LiveAddress = LiveAddress()
    wait: float = 0.0
    linger: float = DEFAULT_LINGER
    can_rate: float = DEFAULT_CAN_RATE
    rows: int = DEFAULT_ROWS
    row_rate: float = DEFAULT_ROW_RATE

    def to_json(self) -> dict[str, object]:
        return {"address": str(self.address), "wait": self.wait, "linger": self.linger, "can_rate": self.can_rate,
                "rows": self.rows, "row_rate": self.row_rate}


def parse_address(text: str, option: str = "--live") -> LiveAddress:
    """``[HOST:]PORT`` (``[::1]:8765`` for an IPv6 host) as a :class:`LiveAddress`; a host name is refused (the
    server binds an address, and a name could resolve to a non-loopback one unnoticed)."""
    host, port_text = DEFAULT_HOST, text.strip()
    if port_text.startswith("["):
        inner, sep, rest = port_text[1:].partition("]")
        if not sep or not rest.startswith(":"):
            raise InputError(f"{option}: {text!r} is not [HOST:]PORT (an IPv6 host as [::1]:8765)")
        host, port_text = inner, rest[1:]
    elif ":" in port_text:
        host, _, port_text = port_text.rpartition(":")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        raise InputError(f"{option}: {host!r} is not an IP address (e.g. 127.0.0.1, 0.0.0.0 or [::1])") from None
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise InputError(f"{option}: the port must be an integer in 0..65535, got {port_text!r}")
    return LiveAddress(host, int(port_text))


def add_live_options(parser: argparse.ArgumentParser, *, rows: bool) -> None:
    """``--live [HOST:]PORT`` and its companions (``rows``: ``--live-rows`` too, for ``run``)."""
    parser.add_argument("--live", nargs="?", const=DEFAULT_ADDRESS, metavar="[HOST:]PORT",
                        help=f"serve a live view to Foxglove over its WebSocket protocol (default {DEFAULT_ADDRESS}: "
                        "loopback only); see docs/live-view.md")
    parser.add_argument("--live-wait", type=float, default=0.0, metavar="S",
                        help="with --live: wait up to S seconds for a viewer to subscribe before starting (default 0)")
    parser.add_argument("--live-linger", type=float, default=DEFAULT_LINGER, metavar="S",
                        help=f"with --live: keep serving up to S seconds after the end while a viewer is subscribed "
                        f"(default {DEFAULT_LINGER:g})")
    parser.add_argument("--live-can-rate", type=float, default=DEFAULT_CAN_RATE, metavar="F",
                        help=f"with --live: /can frames per second at most (default {DEFAULT_CAN_RATE:g})")
    if rows:
        parser.add_argument("--live-rows", type=int, default=DEFAULT_ROWS, metavar="N",
                            help=f"with --live: /ilc/sample rows per trial at most, every k-th beyond (default "
                            f"{DEFAULT_ROWS}; 0: every row)")
        parser.add_argument("--live-row-rate", type=float, default=DEFAULT_ROW_RATE, metavar="R",
                            help=f"with --live: /ilc/sample rows per second at most over the run (default "
                            f"{DEFAULT_ROW_RATE:g}; 0: no limit)")


def live_options(args: argparse.Namespace) -> LiveOptions | None:
    """The checked :class:`LiveOptions` of ``args``; ``None`` without ``--live``."""
    if args.live is None:
        return None
    for name in ("live_wait", "live_linger", "live_can_rate", "live_row_rate"):
        value = getattr(args, name, 0.0)
        if not (math.isfinite(value) and value >= 0):
            raise InputError(f"--{name.replace('_', '-')}: must be a finite number >= 0, got {value:g}")
    rows = getattr(args, "live_rows", DEFAULT_ROWS)
    if rows < 0:
        raise InputError(f"--live-rows: must be >= 0, got {rows}")
    return LiveOptions(parse_address(args.live), float(args.live_wait), float(args.live_linger),
                       float(args.live_can_rate), int(rows), float(getattr(args, "live_row_rate", DEFAULT_ROW_RATE)))
