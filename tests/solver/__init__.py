"""Tests of the numerical library (solver/)."""
