"""Tests of so_transients.events."""
