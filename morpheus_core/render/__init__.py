"""Renderers in pure PyTorch: volume rendering for the NeRF, rasterisation for meshes."""
