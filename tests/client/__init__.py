"""Tests of the Python client (ffs/client.py)."""
