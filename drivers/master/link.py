"""The master's hold on one drive: :class:`MasterLink`, which every service of the master shares.

As canopen's services hold their ``RemoteNode`` and the emulator's hold their ``EmulatedNode``, each service of the
master holds this link: the drive's node id and settings, its canopen node on the network the drive is reached
through (:class:`~drivers.network.DriveNetwork`), the bus's timebase (every wait of the master runs on it: see
:mod:`drivers.cia402_master`), the life-cycle flags and the one way a frame is sent.

Thread safety: the flags are written by the control thread only; the receive callbacks read ``operational``.
"""

from __future__ import annotations

import can
import canopen

from drivers.config import DriveConfig
from drivers.errors import DriveError
from drivers.inprocess import timebase_of
from drivers.network import DriveNetwork

__all__ = ["MasterLink"]


class MasterLink:
    """One drive as the master reaches it.

    Parameters
    ----------
    cfg
        The drive's section (node id, timeouts, scales, limits).
    node
        canopen's ``RemoteNode`` of the drive (its SDO client and NMT master are the master's); ``od`` is its object
        dictionary.
    net
        The network the drive is on (a private one for a drive alone on its bus).
    owns_network
        The drive built ``net`` itself: closing the drive closes it.

    Attributes
    ----------
    closed
        :meth:`drivers.cia402_master.Cia402Drive.close` ran.
    connected
        A boot-up answered ``connect``: the drive is there to be stopped over SDO.
    operational
        The master started the drive (NMT start after ``configure``) and commands it over PDOs.
    """

    def __init__(self, cfg: DriveConfig, node: canopen.RemoteNode, net: DriveNetwork, *, owns_network: bool) -> None:
        self.cfg = cfg
        self.node_id = cfg.node_id
        self.node = node
        self.od = node.object_dictionary
        self.net = net
        self.network = net.network
        self.bus = net.bus
        self.owns_network = owns_network
        self.timebase = timebase_of(net.bus)
        self.closed = False
        self.connected = False
        self.operational = False

    def send(self, message: can.Message) -> int:
        """Send ``message`` under canopen's send lock (shared with canopen's own sends, and with every SYNC); a bus
        failure is a :class:`DriveError`. Returns the network's count of SYNCs sent before it
        (:attr:`drivers.network.DriveNetwork.syncs_sent`, read under the same lock)."""
        net = self.net
        try:
            with self.network.send_lock:
                self.bus.send(message)
                return net.syncs_sent
        except can.CanError as exc:
            raise DriveError(f"cannot send 0x{message.arbitration_id:03X} on the bus: {exc}") from exc

    def require_open(self) -> None:
        """Raise :class:`DriveError` after ``close``."""
        if self.closed:
            raise DriveError(f"drive {self.node_id} is closed")

    def require_connected(self) -> None:
        """Raise :class:`DriveError` unless open and a boot-up answered ``connect``."""
        self.require_open()
        if not self.connected:
            raise DriveError(f"node {self.node_id} is not connected; call connect() first")

    def require_operational(self) -> None:
        """Raise :class:`DriveError` unless open and started by ``configure``."""
        self.require_open()
        if not self.operational:
            raise DriveError(f"node {self.node_id} is not operational; call configure() first")
