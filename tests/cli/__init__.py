"""Tests of the command line (ffs/cli)."""
