"""Tests of so_transients.significance."""
