"""The CAN bus: parsing ``--bus INTERFACE:CHANNEL``, opening it with python-can, and tapping every frame.

:func:`resolve_bus` picks the bus of a command the way python-can's tools do (``-i/--interface``, ``-c/--channel``,
``-b/--bitrate`` beside ``--bus``; python-can's environment and config file when the command line names none).

``open_bus`` is the only place the product calls ``can.Bus``; it turns python-can's open errors into one
:class:`~drivers.errors.DriveError` line that says what to do (for SocketCAN: create the interface). The
``embedded`` interface (the in-process emulator) is resolved by ``plant_emulator.embedded``, not here; the bus it
gives the master (``inprocess``, :mod:`drivers.inprocess`) is built here without python-can's interface registry.

:class:`FrameTap` lets a logger see every frame the bench sends and receives: it wraps ``bus.send`` (so frames sent
by canopen, by python-can's thread-based periodic tasks and by the cyclic path are all seen) and is a
``can.Listener`` for the receive side. Listeners are called from the sending thread ("tx") and from the Notifier
thread ("rx"), so they must be thread-safe (e.g. put the frame on a queue). On a synchronous bus (``inprocess``,
where the answers to a frame are delivered inside ``send``) the tap reports the frame before sending it, so a trace
shows a SYNC before the TPDOs that answer it.
"""

from __future__ import annotations

import configparser
import contextlib
import errno
import os
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can
from pydantic import ValidationError

from drivers.config import BusConfig
from drivers.errors import DriveError, InputError
from drivers.inprocess import INTERFACE as INPROCESS_INTERFACE
from drivers.inprocess import InProcessBus
from drivers.send_order import order_multicast_sends, order_virtual_sends

__all__ = [
    "SIMULATED_INTERFACES",
    "BusOptions",
    "FrameListener",
    "FrameTap",
    "command_line_bus",
    "is_simulated_bus",
    "known_interfaces",
    "open_bus",
    "parse_bus_spec",
    "python_can_config",
    "resolve_bus",
]

order_virtual_sends()  # one frame order, as on a wire: see drivers.send_order

SIMULATED_INTERFACES = frozenset({"virtual", "udp_multicast", "embedded", INPROCESS_INTERFACE})
"""Interfaces that cannot move real hardware (``replay`` refuses the others without ``--allow-real-bus``)."""

FrameListener = Callable[[can.Message, str], None]
"""Called with ``(message, direction)``, direction ``"tx"`` or ``"rx"``."""


def parse_bus_spec(spec: str, *, bitrate: int | None = None) -> BusConfig:
    """Parse a ``--bus`` value ``INTERFACE:CHANNEL`` (e.g. ``socketcan:vcan0``, ``virtual:bench``).

    The channel may itself contain colons (only the first one separates). Raises :class:`InputError` naming
    ``--bus`` when the spec has no interface or no channel.
    """
    interface, sep, channel = spec.partition(":")
    interface, channel = interface.strip(), channel.strip()
    if not sep or not interface or not channel:
        raise InputError(
            f"--bus: {spec!r} is not INTERFACE:CHANNEL (e.g. socketcan:vcan0, virtual:bench, "
            "udp_multicast:239.74.163.2)"
        )
    if interface == "embedded":
        raise InputError("--bus: 'embedded' is not a bus; use --emulator embedded")
    try:
        return BusConfig(interface=interface, channel=channel, bitrate=bitrate)
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        raise InputError(f"--bus: {spec!r}: {exc}") from exc


@dataclass(frozen=True)
class BusOptions:
    """The bus options of a command line: ``--bus SPEC``, ``-i/--interface``, ``-c/--channel``, ``-b/--bitrate``
    and ``--emulator embedded`` (``None``: not given)."""

    spec: str | None = None
    interface: str | None = None
    channel: str | None = None
    bitrate: int | None = None
    emulator: str | None = None

    def __post_init__(self) -> None:
        if self.bitrate is not None and self.bitrate <= 0:
            raise InputError(f"-b/--bitrate: must be > 0, got {self.bitrate}")


def python_can_config() -> dict[str, str]:
    """python-can's own bus defaults: ``interface``, ``channel``, ``bitrate`` from its environment (``CAN_INTERFACE``,
    ``CAN_CHANNEL``, ``CAN_BITRATE``, ``CAN_CONFIG``) over its config file (``can.rc``: ``~/can.conf``, ``~/.canrc``,
    ... section ``[default]``), the environment winning as in :func:`can.util.load_config`.

    Read directly rather than through ``load_config``, which refuses a missing interface and does not know the
    ``inprocess`` interface of this package.
    """
    try:
        from_file = can.util.load_file_config()
    except configparser.Error as exc:
        raise InputError(f"can.rc: python-can's config file does not parse: {exc}".splitlines()[0]) from None
    try:
        from_environment = can.util.load_environment_config()
    except ValueError as exc:  # CAN_CONFIG is not JSON
        raise InputError(f"CAN_CONFIG: not a JSON object: {exc}") from None
    merged = {**from_file, **from_environment}
    return {key: str(merged[key]) for key in ("interface", "channel", "bitrate") if merged.get(key)}


def _bus_config(interface: str, channel: str, bitrate: int | str | None) -> BusConfig:
    """A :class:`BusConfig`; only a bitrate from python-can's config can be bad here (the options are checked)."""
    try:
        return BusConfig(interface=interface, channel=channel, bitrate=bitrate)
    except ValidationError as exc:
        raise InputError(f"CAN_BITRATE: {bitrate!r} (python-can's environment or can.rc): "
                         f"{exc.errors()[0]['msg']}") from None


def command_line_bus(options: BusOptions, bitrate: int | None = None) -> BusConfig | None:
    """The bus the command line names, or ``None``: ``--bus SPEC``, or ``-i``/``-c`` with the part not given taken
    from :func:`python_can_config`. ``-b`` (else ``bitrate``, the config's) sets the bitrate.

    Raises :class:`InputError` for ``--bus`` together with ``-i``/``-c``, or ``-i``/``-c`` that stay incomplete.
    """
    rate = options.bitrate if options.bitrate is not None else bitrate
    given = "-i/--interface" if options.interface is not None else "-c/--channel"
    if options.spec is not None:
        if options.interface is not None or options.channel is not None:
            raise InputError(f"{given}: give either --bus INTERFACE:CHANNEL or -i/-c, not both")
        spec = parse_bus_spec(options.spec)
        return _bus_config(spec.interface, spec.channel, rate)
    if options.interface is None and options.channel is None:
        return None
    defaults = python_can_config()
    interface = options.interface or defaults.get("interface")
    channel = options.channel or defaults.get("channel")
    if not interface or not channel:
        missing, variable = ("-i/--interface", "CAN_INTERFACE") if not interface else ("-c/--channel", "CAN_CHANNEL")
        raise InputError(f"{missing}: needed with {given} (or from python-can's {variable} / can.rc)")
    if interface == "embedded":
        raise InputError("-i/--interface: 'embedded' is not a bus; use --emulator embedded")
    return _bus_config(interface, channel, rate if rate is not None else defaults.get("bitrate"))


def resolve_bus(options: BusOptions, configured: BusConfig) -> BusConfig:
    """The bus of a command, in this order (first that applies):

    1. ``--emulator embedded``: the in-process emulator (``interface: embedded``);
    2. the command line (:func:`command_line_bus`);
    3. the config file's ``bus:`` block when it names an ``interface``;
    4. python-can's environment, then its config file (:func:`python_can_config`), when they name an interface;
    5. ``configured`` as it is (by default the embedded emulator).

    ``-b/--bitrate`` overrides the bitrate of whichever bus is chosen.
    """
    if options.emulator == "embedded":
        if options.interface is not None or options.channel is not None:
            raise InputError("--emulator: the embedded emulator has its own bus; drop -i/-c")
        return BusConfig(interface="embedded", channel=configured.channel)
    named = command_line_bus(options, configured.bitrate)
    if named is not None:
        return named
    rate = options.bitrate if options.bitrate is not None else configured.bitrate
    defaults = python_can_config()
    if "interface" not in configured.model_fields_set and "interface" in defaults:
        if "channel" not in defaults:
            raise InputError(f"CAN_CHANNEL: python-can's config names interface {defaults['interface']!r} "
                             "but no channel (set CAN_CHANNEL, or channel in can.rc)")
        return _bus_config(defaults["interface"], defaults["channel"],
                           rate if options.bitrate is not None else defaults.get("bitrate", rate))
    return configured.model_copy(update={"bitrate": rate})


def known_interfaces() -> frozenset[str]:
    """Interfaces ``open_bus`` can open: python-can's registry and ``inprocess`` (built here without it)."""
    return frozenset(can.interfaces.VALID_INTERFACES) | {INPROCESS_INTERFACE}


def is_simulated_bus(interface: str) -> bool:
    """True for interfaces that reach no hardware (``virtual``, ``udp_multicast``, ``embedded``, ``inprocess``)."""
    return interface in SIMULATED_INTERFACES


def open_bus(cfg: BusConfig) -> can.BusABC:
    """Open the python-can bus ``cfg`` describes.

    Parameters
    ----------
    cfg
        The ``bus:`` section: python-can's interface and channel, bitrate, options.

    Returns
    -------
    can.BusABC
        The open bus (the caller shuts it down; it is a context manager).

    Raises
    ------
    DriveError
        When python-can cannot open it; the message names the interface and channel and, for SocketCAN, how to
        create a virtual interface.
    InputError
        For ``interface: embedded`` (the emulator opens that one) or an interface python-can does not know.
    """
    if cfg.interface == "embedded":
        raise InputError("bus.interface: 'embedded' is opened by plant_emulator.embedded, not drivers.bus")
    kwargs: dict[str, Any] = {"interface": cfg.interface, "channel": cfg.channel}
    if cfg.bitrate is not None:
        kwargs["bitrate"] = cfg.bitrate
    if cfg.receive_own_messages:
        kwargs["receive_own_messages"] = True
    where = f"{cfg.interface}:{cfg.channel}"
    if cfg.interface == INPROCESS_INTERFACE:  # in this process: no registry needed (see drivers.inprocess)
        return InProcessBus(cfg.channel, receive_own_messages=cfg.receive_own_messages)
    try:
        bus = can.Bus(**kwargs)
        if cfg.interface == "udp_multicast":
            _enlarge_receive_buffer(bus)
            order_multicast_sends(bus)  # every receiver sees one order, as on a wire (drivers.send_order)
        return bus
    except can.CanInterfaceNotImplementedError as exc:
        raise InputError(f"--bus: interface {cfg.interface!r} is not available in python-can: {exc}") from exc
    except (can.CanError, OSError, ValueError) as exc:
        hint = ""
        if cfg.interface == "socketcan":
            hint = (
                f"; create it with `sudo ip link add dev {cfg.channel} type vcan && sudo ip link set up "
                f"{cfg.channel}` (virtual) or bring the adapter up with `ip link set {cfg.channel} up type can "
                "bitrate ...`"
            )
            if isinstance(exc, OSError) and exc.errno == errno.EAFNOSUPPORT:  # no AF_CAN in this kernel/namespace
                then = hint.replace(";", ", then", 1)
                hint = f"; this kernel has no SocketCAN: load it with `sudo modprobe can-raw vcan`{then}"
        raise DriveError(f"cannot open CAN bus {where}: {exc}{hint}") from exc


#: bytes of socket receive buffer asked for a ``udp_multicast`` bus: the default (about 208 KiB) holds some 0.05 s of
#: a 1 kHz bench's traffic (every datagram costs about 900 bytes of buffer), so a stall of the receiving process
#: longer than that dropped frames on the floor of its socket
UDP_RECEIVE_BUFFER = 1 << 23
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux's; Python names it from 3.12 on


def _enlarge_receive_buffer(bus: can.BusABC) -> None:
    """Best effort: :data:`UDP_RECEIVE_BUFFER` for the bus's socket (past ``net.core.rmem_max`` where privileged)."""
    with contextlib.suppress(OSError, AttributeError, ValueError), \
            socket.socket(fileno=os.dup(bus.fileno())) as sock:
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, UDP_RECEIVE_BUFFER)
        except OSError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)


class FrameTap(can.Listener):
    """Shows every frame sent on and received from one bus to registered listeners.

    ``attach`` replaces the bus object's ``send`` with a wrapper that reports the frame as ``"tx"`` after it was
    sent; add the tap to the Notifier (``notifier.add_listener(tap)``) for ``"rx"``. ``detach`` restores ``send``.
    Frames sent by a kernel-side periodic task (SocketCAN's broadcast manager) bypass ``bus.send`` and are not
    seen as ``tx``.

    Thread safety: listeners may be added from any thread; they are called on the sending thread (``tx``) and the
    Notifier thread (``rx``). An exception in a listener is counted in :attr:`listener_errors`, never propagated
    to the CAN path.
    """

    def __init__(self) -> None:
        self._listeners: tuple[FrameListener, ...] = ()
        self._lock = threading.Lock()
        self._bus: can.BusABC | None = None
        self._restore: Callable[..., None] | None = None
        self.listener_errors = 0

    def add_listener(self, listener: FrameListener) -> None:
        """Call ``listener(message, direction)`` for every frame from now on."""
        with self._lock:
            self._listeners = (*self._listeners, listener)

    def remove_listener(self, listener: FrameListener) -> None:
        """Stop calling ``listener``."""
        with self._lock:
            self._listeners = tuple(item for item in self._listeners if item is not listener)

    def attach(self, bus: can.BusABC) -> None:
        """Wrap ``bus.send`` so every sent frame reaches the listeners as ``"tx"``."""
        if self._bus is not None:
            raise DriveError("frame tap is already attached to a bus")
        original_send = bus.send
        self._restore = vars(bus).get("send")  # a wrapper of open_bus's own (drivers.send_order), kept on detach

        def tapped_send(msg: can.Message, timeout: float | None = None) -> None:
            original_send(msg, timeout)
            if self._listeners:  # no call at all while nobody listens (logging off): the cyclic path sends 2 a cycle
                self._emit(msg, "tx")

        def tapped_send_first(msg: can.Message, timeout: float | None = None) -> None:
            if self._listeners:
                self._emit(msg, "tx")  # the answers arrive inside send: report the cause first
            original_send(msg, timeout)

        bus.send = tapped_send_first if isinstance(bus, InProcessBus) else tapped_send  # type: ignore[method-assign]
        self._bus = bus

    def detach(self) -> None:
        """Restore the bus's own ``send``."""
        if self._bus is not None:
            if self._restore is not None:
                self._bus.send = self._restore  # type: ignore[method-assign]
            elif "send" in vars(self._bus):
                del self._bus.send
            self._bus = None

    def on_message_received(self, msg: can.Message) -> None:
        """``can.Listener`` hook: report a received frame as ``"rx"``."""
        if self._listeners:
            self._emit(msg, "rx")

    def _emit(self, msg: can.Message, direction: str) -> None:
        for listener in self._listeners:  # the tuple is replaced, never mutated: no lock needed to iterate
            try:
                listener(msg, direction)
            except Exception:  # a logger's failure must not break the control path; counted instead
                self.listener_errors += 1
