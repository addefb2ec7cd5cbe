"""Tests of so_transients.coherent."""
