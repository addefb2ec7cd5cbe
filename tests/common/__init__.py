"""Tests of so_transients.common."""
