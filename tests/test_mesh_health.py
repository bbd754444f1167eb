"""Mesh health: topology counts, degenerate faces, UV coverage and texel density, UV-seam leakage."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from morpheus_core.metrics.image import MetricInputError
from morpheus_core.metrics.mesh_health import mesh_health


def _random_rigid(seed: int) -> tuple[np.ndarray, float, np.ndarray]:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q, float(rng.uniform(0.5, 3.0)), rng.normal(size=3)


def _cube(seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    rot, scale, shift = _random_rigid(seed)
    box = trimesh.creation.box()
    return (box.vertices * scale) @ rot.T + shift, np.asarray(box.faces, dtype=np.int64), scale


@pytest.mark.parametrize("seed", [0, 1])
def test_mesh_health_cube(seed: int) -> None:
    v, f, scale = _cube(seed)
    h = mesh_health(v, f)
    assert (h["faces"], h["vertices"], h["components"], h["euler_number"], h["degenerate_faces"]) == (12, 8, 1, 2, 0)
    assert h["watertight"] is True and h["winding_consistent"] is True
    assert h["surface_area"] == pytest.approx(6 * scale**2)
    assert h["uv_coverage"] is None and h["seam_leakage"] is None
    assert mesh_health(torch.from_numpy(v), torch.from_numpy(f)) == h


def test_mesh_health_open_disjoint_and_degenerate() -> None:
    v, f, _ = _cube(2)
    # Remove the two triangles of one side: the diagonal edge goes too, V − E + F = 8 − 17 + 10 = 1.
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    open_faces = f[~np.all(np.isclose(normals, normals[0]), axis=1)]
    assert len(open_faces) == 10
    h = mesh_health(v, open_faces)
    assert h["watertight"] is False and h["euler_number"] == 1 and h["components"] == 1

    two = mesh_health(np.concatenate([v, v + 10.0]), np.concatenate([f, f + 8]))
    assert two["components"] == 2 and two["euler_number"] == 4 and two["watertight"] is True

    # A duplicated vertex at the position of vertex 0 makes the extra triangle (0, dup, 1) zero-area.
    v_dup = np.concatenate([v, v[:1]])
    f_dup = np.concatenate([f, [[0, 8, 1]]])
    assert mesh_health(v_dup, f_dup)["degenerate_faces"] == 1
    assert mesh_health(v, np.concatenate([f, [[2, 2, 3]]]))["degenerate_faces"] == 1


def test_mesh_health_zero_faces_and_bad_input() -> None:
    h = mesh_health(np.zeros((4, 3)), np.zeros((0, 3), dtype=np.int64))
    assert h["faces"] == 0 and h["vertices"] == 4 and h["watertight"] is False
    assert all(h[k] is None for k in h if k not in ("faces", "vertices", "watertight"))
    v, f, _ = _cube(3)
    nan_v = v.copy()
    nan_v[2, 1] = np.nan
    with pytest.raises(ValueError, match="vertices holds NaN"):
        mesh_health(nan_v, f)
    with pytest.raises(MetricInputError, match="faces index vertices outside"):
        mesh_health(v, f + 1)
    with pytest.raises(MetricInputError, match="one row per vertex"):
        mesh_health(v, f, uvs=np.zeros((3, 2)))
    tex = np.zeros((4, 4, 3))
    tex[1, 1, 0] = np.inf
    with pytest.raises(ValueError, match="texture holds NaN"):
        mesh_health(v, f, uvs=np.zeros((8, 2)), texture=tex)


@pytest.mark.parametrize("size", [32, 64])
def test_uv_coverage_and_texel_density(size: int) -> None:
    rot, _, shift = _random_rigid(4)
    side = 2.0
    quad = np.array([[0, 0, 0], [side, 0, 0], [side, side, 0], [0, side, 0]], dtype=np.float64) @ rot.T + shift
    uv_full = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
    half = mesh_health(quad, np.array([[0, 1, 3]]), uvs=uv_full, texture=np.full((size, size, 3), 0.5))
    # Texel centres inside the half square, edge included: N(N+1)/2 of N².
    assert half["uv_coverage"] == pytest.approx(0.5, abs=1.0 / size)
    full = mesh_health(quad, np.array([[0, 1, 2], [0, 2, 3]]), uvs=uv_full, texture=np.full((size, size, 3), 0.5))
    assert full["uv_coverage"] == pytest.approx(1.0)
    # All N² texels over side² of surface: N / side texels per world unit.
    assert full["texel_density"] == pytest.approx(size / side)
    # Stacked triangles share texels: coverage counts them once.
    stacked = mesh_health(quad, np.array([[0, 1, 3], [0, 1, 3]]), uvs=uv_full, texture=np.zeros((size, size, 3)))
    assert stacked["uv_coverage"] == half["uv_coverage"]
    # Without a texture, coverage uses uv_resolution and there is no density or leakage to measure.
    bare = mesh_health(quad, np.array([[0, 1, 3]]), uvs=uv_full, uv_resolution=size)
    assert bare["uv_coverage"] == half["uv_coverage"] and bare["texel_density"] is None
    assert bare["seam_leakage"] == 0.0


def _seam_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two triangles sharing the 3-D edge x = 0, split at it: face A maps to the left half of the
    texture, face B to the right half, so the shared edge is a UV seam."""
    v = np.array([[0, 0, 0], [0, 1, 0], [-1, 0.5, 0], [0, 0, 0], [0, 1, 0], [1, 0.5, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [4, 3, 5]], dtype=np.int64)
    uv = np.array([[0.4, 0.2], [0.4, 0.8], [0.1, 0.5], [0.6, 0.2], [0.6, 0.8], [0.9, 0.5]], dtype=np.float64)
    return v, f, uv


def test_seam_leakage() -> None:
    v, f, uv = _seam_pair()
    rng = np.random.default_rng(5)
    constant = np.broadcast_to(rng.uniform(size=3), (32, 32, 3)).copy()
    h = mesh_health(v, f, uvs=uv, texture=constant)
    assert h["seam_edges"] == 1 and h["seam_leakage"] == pytest.approx(0.0, abs=1e-12)
    assert h["watertight"] is False and h["components"] == 1 and h["euler_number"] == 1
    left, right = rng.uniform(size=3), rng.uniform(size=3)
    split = np.zeros((32, 32, 3))
    split[:, :16], split[:, 16:] = left, right
    h = mesh_health(v, f, uvs=uv, texture=split)
    assert h["seam_leakage"] == pytest.approx(float(np.abs(left - right).mean()), abs=1e-12)
    # The same faces sharing one UV per vertex have no seam at all.
    shared_uv = uv.copy()
    shared_uv[3:5] = uv[0:2]
    assert mesh_health(v, f, uvs=shared_uv, texture=split)["seam_edges"] == 0
    assert mesh_health(v, f, uvs=shared_uv, texture=split)["seam_leakage"] == 0.0


def test_seam_leakage_cube_with_face_charts() -> None:
    """A cube whose six sides each own four vertices and a UV chart: 12 seam edges, still closed."""
    v, f, _ = _cube(6)
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normals = np.round(normals / np.linalg.norm(normals, axis=1, keepdims=True), 6)
    _, side_of = np.unique(normals, axis=0, return_inverse=True)
    verts, faces, uvs = [], [], []
    for s in range(6):
        tris = f[side_of.ravel() == s]
        ids = np.unique(tris)
        local = {int(i): k + len(verts) for k, i in enumerate(ids)}
        # Each side's chart sits inside its own cell of a 3×2 grid; plane coords give the UV layout.
        pts = v[ids]
        e1, e2 = pts[1] - pts[0], np.cross(normals[side_of.ravel() == s][0], pts[1] - pts[0])
        coords = np.stack([(pts - pts[0]) @ e1, (pts - pts[0]) @ e2], axis=1)
        coords = (coords - coords.min(0)) / np.ptp(coords, axis=0)
        cell = np.array([s % 3, s // 3], dtype=np.float64)
        uvs.extend((cell + 0.2 + 0.6 * coords) / np.array([3.0, 2.0]))
        verts.extend(pts)
        faces.extend([[local[int(a)] for a in tri] for tri in tris])
    verts, faces, uvs = np.array(verts), np.array(faces, dtype=np.int64), np.array(uvs)
    h = mesh_health(verts, faces, uvs=uvs, texture=np.full((60, 90, 3), 0.25))
    assert (h["vertices"], h["watertight"], h["euler_number"], h["seam_edges"]) == (24, True, 2, 12)
    assert h["seam_leakage"] == pytest.approx(0.0, abs=1e-12)
    assert h["uv_coverage"] == pytest.approx(0.36, abs=0.03)  # six charts of 0.6² of their cell
    # One colour per cell: every seam compares two cells' colours (bilinear stays inside each cell).
    colours = np.random.default_rng(7).uniform(size=(6, 3))
    tex = np.zeros((60, 90, 3))
    for s in range(6):
        col, row = s % 3, 1 - s // 3  # row 0 of the texture is v = 1
        tex[row * 30 : (row + 1) * 30, col * 30 : (col + 1) * 30] = colours[s]
    leak = mesh_health(verts, faces, uvs=uvs, texture=tex)["seam_leakage"]
    pairs = [(a, b) for a in range(6) for b in range(a + 1, 6) if not np.allclose(
        np.unique(normals, axis=0)[a], -np.unique(normals, axis=0)[b])]
    assert len(pairs) == 12  # adjacent sides: every pair but the 3 opposite ones
    want = np.mean([np.abs(colours[a] - colours[b]).mean() for a, b in pairs])
    assert leak == pytest.approx(want, abs=1e-9)  # all cube edges have the same length
