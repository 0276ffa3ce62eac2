"""Benchmark scripts, run as modules from the repository's root folder
(``python -m bench.<script> [options]``); bench/README.md holds their current results."""
