"""Start-up of one drive over SDO and NMT: :class:`StartUp` (identity, preflight, configure, NMT start).

Only standard objects are used, so any CiA 402 drive works. ``identify``: NMT reset communication, the boot-up, NMT
pre-operational, 0x1000 (must be a 402 device), 0x1018:1..4 and 0x6502. ``configure``: :meth:`StartUp.preflight`
first (mode in 0x6502, :func:`~drivers.master.plan.pdo_plan`); the master's heartbeat producer; for every RPDO/TPDO
1..4: disabled (COB-ID bit 31), and for those the plan uses: transmission type 1, mapping count 0, mapping entries,
count, COB-ID enabled; then the settings (:func:`~drivers.master.plan.settings_rows`). An optional object the EDS
lacks is not written (a warning and a plan note say so); one the EDS has but the drive refuses with "no object" is
skipped with a warning. All of it is read back (0x6061 must show the mode); then NMT start, and the operational
heartbeat is awaited before its loss detection is armed.
"""

from __future__ import annotations

import logging

from drivers.cia301 import RPDO_BASES, TPDO_BASES, CobIdEntry, NmtCommand, NmtState, SdoAbortCode, cob_id
from drivers.cia402 import SUPPORTED_MODE_BITS, IdentitySub, Obj, OperationMode
from drivers.drive import DeviceInfo
from drivers.errors import ConfigError, DriveError, SdoError
from drivers.master.cyclic import CyclicPath
from drivers.master.inbox import Inbox
from drivers.master.link import MasterLink
from drivers.master.nmt_client import NmtClient
from drivers.master.plan import PdoPlan, Setting, pdo_plan, settings_rows
from drivers.master.sdo_client import I8, U8, U32, SdoClient
from drivers.master.supervision import DriveSupervision
from drivers.pdo import PdoDirection, PdoLayout

__all__ = ["CIA402_PROFILE", "MASTER_HEARTBEATS_PER_CONSUMER_TIME", "StartUp"]

logger = logging.getLogger("drivers.cia402_master")  # the master's log, as before the split into services

CIA402_PROFILE = 402
"""Low 16 bits of 0x1000 for a CiA 402 drive."""

MASTER_HEARTBEATS_PER_CONSUMER_TIME = 4
"""The master beats this many times per drive consumer time (0x1016), so one lost or late frame never trips it."""


class StartUp:
    """Identity and configuration of one drive (module docstring).

    Attributes
    ----------
    device_modes
        The modes 0x6502 offers, read once by :meth:`identify` (None before; empty: the drive lacks 0x6502).
    """

    def __init__(self, link: MasterLink, sdo: SdoClient, nmt: NmtClient, supervision: DriveSupervision,
                 cyclic: CyclicPath, inbox: Inbox) -> None:
        self._link = link
        self._sdo = sdo
        self._nmt = nmt
        self._supervision = supervision
        self._cyclic = cyclic
        self._inbox = inbox
        self.device_modes: tuple[OperationMode, ...] | None = None

    def identify(self) -> DeviceInfo:
        """NMT reset communication, the boot-up, NMT pre-operational, the identity (0x1000, 0x1018, 0x6502)."""
        link, sdo = self._link, self._sdo
        self._nmt.reset_communication()
        link.connected = True
        self._nmt.send(NmtCommand.ENTER_PRE_OPERATIONAL)
        device_type = sdo.read(Obj.DEVICE_TYPE, 0, U32)
        if device_type & 0xFFFF != CIA402_PROFILE:
            raise DriveError(
                f"node {link.node_id} is not a CiA 402 drive: device type 0x{device_type:08X} (0x1000)"
            )
        identity = [sdo.read(Obj.IDENTITY, sub, U32) for sub in IdentitySub]
        supported = self.supported_modes()
        self.device_modes = supported
        return DeviceInfo(
            node_id=link.node_id,
            vendor_id=identity[0],
            product_code=identity[1],
            revision=identity[2],
            serial=identity[3],
            device_type=device_type,
            nmt_state=NmtState.PRE_OPERATIONAL,
            supported_modes=supported,
        )

    def supported_modes(self) -> tuple[OperationMode, ...]:
        """The modes 0x6502 offers; empty when the drive lacks the (optional) object: any mode may be tried."""
        try:
            bits = self._sdo.read(Obj.SUPPORTED_DRIVE_MODES, 0, U32)
        except SdoError as exc:
            if exc.abort_code in (SdoAbortCode.NO_OBJECT, SdoAbortCode.NO_SUBINDEX):
                return ()  # 0x6502 is optional: any mode may be tried
            raise
        return tuple(mode for mode, bit in SUPPORTED_MODE_BITS.items() if bits & bit)

    def preflight(self, mode: OperationMode) -> PdoPlan:
        """What :meth:`configure` checks before it writes anything: the mode (0x6502), the PDOs the EDS allows
        (:func:`~drivers.master.plan.pdo_plan`), the settings it can encode; raises what ``configure`` would
        raise. The plan's notes name the optional objects the drive lacks."""
        link = self._link
        mode = OperationMode(mode)
        supported = self.device_modes if self.device_modes is not None else self.supported_modes()
        if supported and mode not in supported:
            names = ", ".join(m.name for m in supported)
            raise ConfigError(f"node {link.node_id} does not support {mode.name} (0x6502 offers {names})",
                              key="drive.mode")
        plan = pdo_plan(mode, link.node_id, link.od, demand_echo=link.cfg.demand_echo)
        skipped = [f"0x{index:04X}:{sub:02X} not configured: the drive's EDS lacks it"
                   for index, sub, _, _, optional in self.settings(mode)
                   if optional and index not in link.od]
        return PdoPlan(plan.rpdos, plan.tpdos, (*plan.notes, *skipped))

    def settings(self, mode: OperationMode) -> list[Setting]:
        """The objects :meth:`configure` writes after the PDOs, in order (:func:`~drivers.master.plan.settings_rows`,
        the sample time the cyclic path's)."""
        return settings_rows(self._link.cfg, self._link.od, mode, self._cyclic.sample_time)

    def configure(self, mode: OperationMode) -> None:
        """Configure PDOs, mode, timing and heartbeats over SDO, verify by reading back, then NMT start."""
        link, sdo, monitor = self._link, self._sdo, self._supervision.monitor
        link.require_connected()
        mode = OperationMode(mode)
        plan = self.preflight(mode)
        for note in plan.notes:
            logger.warning("node %d: %s", link.node_id, note)
        monitor.disarm()
        link.operational = False
        self._nmt.send(NmtCommand.ENTER_PRE_OPERATIONAL)
        self._inbox.reset()
        self._start_master_heartbeat()
        self._write_pdos(plan)
        written = [row for row in self.settings(mode)
                   if (row[0] in link.od or not row[4]) and self._write_setting(row)]
        # read everything back: a drive may accept a write and keep another value
        for layout in (*plan.rpdos, *plan.tpdos):
            self._verify_pdo(layout)
        for index, sub, fmt, value, _ in written:
            sdo.expect(index, sub, fmt, value)
        self._wait_mode_display(mode)
        self._cyclic.install(mode, plan.rpdos, plan.tpdos)
        beats_before = monitor.beats
        self._nmt.send(NmtCommand.START)
        link.operational = True
        self._supervision.confirm_operational(beats_before)

    def _start_master_heartbeat(self) -> None:
        cfg = self._link.cfg
        if cfg.heartbeat_consumer_ms == 0:
            return
        period = cfg.heartbeat_consumer_ms / 1000 / MASTER_HEARTBEATS_PER_CONSUMER_TIME
        self._link.net.start_master_heartbeat(cfg.master_node_id, period)

    def _write_pdos(self, plan: PdoPlan) -> None:
        """Every RPDO and TPDO 1..4: the plan's written, the others disabled."""
        for layouts, bases, direction in ((plan.rpdos, RPDO_BASES, PdoDirection.RPDO),
                                          (plan.tpdos, TPDO_BASES, PdoDirection.TPDO)):
            used = {layout.number: layout for layout in layouts}
            for number in range(1, len(bases) + 1):
                if number in used:
                    self._write_pdo(used[number])
                else:
                    self._disable_pdo(direction, number, cob_id(bases[number - 1], self._link.node_id))

    def _write_pdo(self, layout: PdoLayout) -> None:
        """CiA 301 PDO reconfiguration: disable, transmission type, count 0, entries, count, enable."""
        write = self._sdo.write
        com, mapping = layout.communication_index, layout.mapping_index
        write(com, 1, U32, CobIdEntry(layout.cob_id, valid=False).encode())
        write(com, 2, U8, int(layout.transmission_type))
        write(mapping, 0, U8, 0)
        for sub, variable in enumerate(layout.variables, start=1):
            write(mapping, sub, U32, variable.mapping_entry)
        write(mapping, 0, U8, len(layout.variables))
        write(com, 1, U32, layout.cob_id)

    def _disable_pdo(self, direction: PdoDirection, number: int, default_cob: int) -> None:
        layout = PdoLayout(direction, number, default_cob, ())
        try:
            self._sdo.write(layout.communication_index, 1, U32, CobIdEntry(default_cob, valid=False).encode())
        except SdoError as exc:
            if exc.abort_code != SdoAbortCode.NO_OBJECT:
                raise  # the drive has fewer PDOs than four: nothing to disable

    def _verify_pdo(self, layout: PdoLayout) -> None:
        expect = self._sdo.expect
        com, mapping = layout.communication_index, layout.mapping_index
        expect(com, 1, U32, layout.cob_id, mask=0x9FFF_FFFF)  # bit 30 (RTR) is the drive's business
        expect(com, 2, U8, int(layout.transmission_type))
        expect(mapping, 0, U8, len(layout.variables))
        for sub, variable in enumerate(layout.variables, start=1):
            expect(mapping, sub, U32, variable.mapping_entry)

    def _write_setting(self, row: Setting) -> bool:
        """Write one setting; an optional object the drive lacks is skipped (False) with a warning."""
        index, sub, fmt, value, optional = row
        try:
            self._sdo.write(index, sub, fmt, value)
        except SdoError as exc:
            if optional and exc.abort_code in (SdoAbortCode.NO_OBJECT, SdoAbortCode.NO_SUBINDEX):
                logger.warning("node %d lacks optional object 0x%04X:%02X; not configured", self._link.node_id,
                               index, sub)
                return False
            raise
        return True

    def _wait_mode_display(self, mode: OperationMode) -> None:
        link = self._link
        deadline = link.timebase.now() + link.cfg.state_timeout
        while True:
            shown = self._sdo.read(Obj.MODES_OF_OPERATION_DISPLAY, 0, I8)
            if shown == mode:
                return
            if link.timebase.now() > deadline:
                raise DriveError(
                    f"node {link.node_id}: 0x6061 shows mode {shown}, not {int(mode)} ({mode.name}) "
                    f"{link.cfg.state_timeout} s after writing 0x6060"
                )
            link.timebase.sleep(0.01)
