"""Geometry representations: hash-grid encoding, NeRF field, tetrahedral grid, DMTet, meshes."""
