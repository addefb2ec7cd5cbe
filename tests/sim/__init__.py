"""Tests of so_transients.sim."""
