"""Tests of so_transients.detect."""
