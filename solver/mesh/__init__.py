"""Meshes and their geometry: topology, spanning trees, rotations, face frames, manifold
cuts, placement and alignment, the discrete fundamental forms and their derivatives,
metrics, an embedding's edge vectors, hinge angles and signed areas, rigid motions, files
(io, uv files, diagnosis) and charts and their packing. Imports only :mod:`solver.core`."""
