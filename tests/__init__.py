"""The test suite: a package so that its helpers import as ``tests.helpers.<module>``
(pytest's ``pythonpath = ["."]`` puts the repository root on the path)."""
