"""Generalised winding number of a triangle mesh (Jacobson et al. 2013): inside/outside for any mesh.

w(p) = Σ_faces Ω_f(p) / 4π with Ω the signed solid angle of the triangle seen from p (Van Oosterom
& Strackee). It is 1 inside and 0 outside a closed, consistently wound (outward) surface and
degrades gracefully for the holes and self-intersections of real assets, which makes it the
right way to turn an existing mesh into a DMTet SDF sign.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from morpheus_core.geometry.mesh import Mesh


def winding_number(mesh: Mesh, points: Tensor, chunk_pairs: int = 1 << 22) -> Tensor:
    """w at ``points`` (N, 3); work is chunked so that ``chunk_pairs`` point–face pairs run at once."""
    if mesh.num_faces == 0:
        return points.new_zeros(points.shape[0])
    # float32 is plenty away from the surface (w is 0 or 1 to ~1e-4); the sign is what DMTet uses.
    tri = mesh.face_vertices().to(torch.float32)  # (F, 3, 3)
    pts = points.to(torch.float32)
    per = max(1, chunk_pairs // mesh.num_faces)
    out = []
    for chunk in pts.split(per):
        d = tri[None] - chunk[:, None, None]  # (n, F, 3, 3)
        a, b, c = d[:, :, 0], d[:, :, 1], d[:, :, 2]
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        det = (a * torch.cross(b, c, dim=-1)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out.append(2.0 * torch.atan2(det, den).sum(-1) / (4.0 * math.pi))
    return torch.cat(out).to(points.dtype)
