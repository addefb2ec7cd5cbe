"""Tests of so_transients.site."""
