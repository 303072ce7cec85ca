"""Unit tests of ``foilc_hil.loop`` (and ``foilc_hil.metrics``): the trial loop, scheduler, safety, rig, simulation."""
