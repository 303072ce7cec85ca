"""Tests that start other processes on a bus: emulator processes, the SYNC producer, ``udp_multicast`` in private
network namespaces.
"""
