"""The linear reconstruction (Eq. 5): the sparse system and its constraints, the
integrability check and tree integration, and the layout fit. Imports :mod:`solver.core`,
:mod:`solver.linalg` and :mod:`solver.mesh`."""
