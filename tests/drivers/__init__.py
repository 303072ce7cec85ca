"""Unit tests of ``drivers/`` (rank 0): codecs, the object dictionary, buses, the CiA 402 master, on in-process or
``virtual`` buses.
"""
