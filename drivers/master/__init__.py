"""The CiA 402 master's service objects, composed by :class:`drivers.cia402_master.Cia402Drive`.

As canopen composes a ``RemoteNode`` from ``sdo``, ``nmt``, ``emcy`` and ``pdo`` services, and the emulator its
``VirtualDrive`` from an SDO guard, a PDO engine, supervision and a 402 application, the master is composed of:

==========================================================  ==========================================================
service                                                     job
==========================================================  ==========================================================
:class:`~drivers.master.link.MasterLink`                    the drive's node on its network, the bus's timebase, the
                                                            life-cycle flags, sending a frame
:class:`~drivers.master.inbox.Inbox`                        what the receive threads hand the control thread: errors,
                                                            the heartbeat fault, an NMT departure, bad frames
:class:`~drivers.master.sdo_client.SdoClient`               SDO transfers with typed errors, typed integer objects
:class:`~drivers.master.nmt_client.NmtClient`               NMT commands, reset communication and boot-up, NMT tracking
:class:`~drivers.master.supervision.DriveSupervision`       the drive's heartbeat: loss, NMT departure, the watchdog
:class:`~drivers.master.emergency.EmcyConsumer`             EMCY frames into typed errors
:class:`~drivers.master.cyclic.CyclicPath`                  RPDO (controlword + target), SYNC, TPDO feedback and its
                                                            wait
:class:`~drivers.master.startup.StartUp`                    identity, preflight, configure over SDO, NMT start
:class:`~drivers.master.state402.PowerStateCommands`        the 402 state and its commands: enable, disable, quick
                                                            stop, fault reset
:class:`~drivers.master.safe_stop.SafeStop`                 the confirmed stop along the paths of ``StopPath``
==========================================================  ==========================================================

:mod:`drivers.master.plan` holds the pure part of start-up: the PDO plan for a mode and the settings it writes.
"""
