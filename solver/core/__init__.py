"""The bottom layer: what every other part of the solver imports and nothing here imports
from above: errors, JSON-able dataclasses, input validation, time budgets, answer warnings,
the allocator setting. (Layers, bottom to top: core, linalg, mesh, linear and refine, then
the entry points in :mod:`solver`; ``tests/test_layers.py`` checks it.)"""
