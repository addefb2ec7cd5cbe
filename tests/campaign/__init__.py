"""Tests of so_transients.campaign."""
