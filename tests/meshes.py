"""Mesh helpers shared by the DMTet and marching-tets tests: a DMTet on a cached grid, a trimesh view of
a ``Mesh``, its signed volume, an analytic sphere SDF."""

from __future__ import annotations

from pathlib import Path

import torch
import trimesh

from morpheus_core.geometry.mesh import Mesh
from morpheus_core.geometry.tet_surface import DMTet, DMTetConfig


def make_dmtet(res: int, cache_dir: Path, device="cpu", dtype=torch.float32, **kw) -> DMTet:
    return DMTet(DMTetConfig(resolution=res, **kw), device=device, dtype=dtype, cache_dir=cache_dir)


def to_trimesh(mesh: Mesh) -> trimesh.Trimesh:
    # process=False: trimesh must judge our connectivity, not a re-merged copy of it.
    return trimesh.Trimesh(mesh.vertices.detach().cpu().double().numpy(), mesh.faces.cpu().numpy(), process=False)


def signed_volume(mesh: Mesh) -> float:
    v = mesh.face_vertices().detach().double()
    return float((v[:, 0] * torch.linalg.cross(v[:, 1], v[:, 2], dim=-1)).sum() / 6)


def sphere(r: float):
    return lambda p: p.norm(dim=-1) - r
