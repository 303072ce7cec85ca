"""Shared helpers of the tests (imported, never collected: no ``test_*.py`` here) and the scripts tests run as
processes.
"""
