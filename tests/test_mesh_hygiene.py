"""Mesh hygiene: components, floater removal with vertex compaction, Euler number, genus, holes and
non-manifold edges, on meshes built here (random sizes and placements from a fresh seed each run,
named in the failure message, plus fixed seeds); and the bake stage recording what it dropped."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from morpheus_core.export.uv_bake import BakeConfig
from morpheus_core.geometry.hashgrid import HashGridConfig
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.geometry.mesh_hygiene import (
    connected_labels,
    drop_floaters,
    mesh_components,
    topology_report,
)
from morpheus_core.render.textured import load_textured
from morpheus_core.texture import TextureField, TextureFieldConfig
from ops.engine.artifacts import save_module
from ops.stages.bake import ASSET_GLB, BakeStageConfig, bake_asset
from ops.stages.dmtet import MESH_FILE, TEXTURE_FILE, save_mesh
from tests.seeds import fresh_seed

FRESH = fresh_seed()
SEEDS = [0, 1, FRESH]


def _mesh(vertices: np.ndarray, faces: np.ndarray) -> Mesh:
    return Mesh(torch.as_tensor(vertices, dtype=torch.float32), torch.as_tensor(faces, dtype=torch.int64))


def _sphere(rng: np.random.Generator, subdivisions: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(ico.vertices) + rng.uniform(-1, 1, 3), np.asarray(ico.faces)


def _grid_surface(u: int, v: int, wrap_v: bool, point) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """Quads of a (u × v) parameter grid split in two triangles; u always wraps, v when ``wrap_v``
    (torus) or not (open cylinder: two boundary loops)."""
    rows = v if wrap_v else v + 1
    ii, jj = np.meshgrid(np.arange(u), np.arange(rows), indexing="ij")
    verts = point(2 * np.pi * ii.ravel() / u, jj.ravel() / v)

    def idx(i: int, j: int) -> int:
        return (i % u) * rows + (j % rows)

    faces = []
    for i in range(u):
        for j in range(v):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            faces += [(a, b, c), (a, c, d)]
    return verts, np.array(faces)


def _report_seed(seed: int) -> str:
    return f"seed {seed} (FRESH={FRESH})"


@pytest.mark.parametrize("seed", SEEDS)
def test_tiny_separate_sphere_is_dropped_and_the_rest_compacted(seed: int) -> None:
    rng = np.random.default_rng(seed)
    big_v, big_f = _sphere(rng, 3, rng.uniform(0.3, 0.9))
    tiny_r = rng.uniform(0.01, 0.05)
    tiny_v, tiny_f = _sphere(rng, 1, tiny_r)
    tiny_v += np.array([3.0, 0.0, 0.0])  # well clear of the big one
    # The tiny sphere's vertices come first, so every index of the big one shifts on compaction,
    # and the faces are shuffled together.
    verts = np.concatenate([tiny_v, big_v])
    faces = np.concatenate([tiny_f, big_f + len(tiny_v)])
    faces = faces[rng.permutation(len(faces))]
    mesh = _mesh(verts, faces)

    labels, areas = mesh_components(mesh)
    assert labels.shape == (len(faces),) and areas.shape == (2,), _report_seed(seed)
    assert float(areas[0]) > float(areas[1])  # label 0 is the largest
    assert int((labels == 1).sum()) == len(tiny_f)

    # The tiny sphere's share is at most (0.05 / 0.3)² · area(ico1) / area(ico3) ≈ 0.026, so 0.05 always drops it.
    share = float(areas[1] / areas.sum())
    assert share < 0.05, _report_seed(seed)
    clean, report = drop_floaters(mesh, 0.05)
    assert report == {"components_before": 2, "components": 1, "floaters_dropped": 1,
                      "floater_area_share": pytest.approx(share, abs=1e-6)}, _report_seed(seed)
    assert clean.num_faces == len(big_f) and clean.num_vertices == len(big_v), _report_seed(seed)
    assert int(clean.faces.min()) == 0 and int(clean.faces.max()) == len(big_v) - 1
    # Same triangles as the big sphere, as sets of corner positions (indices were renumbered).
    got = {tuple(map(tuple, np.round(t, 5))) for t in clean.vertices.double().numpy()[clean.faces.numpy()]}
    want = {tuple(map(tuple, np.round(t, 5))) for t in torch.tensor(big_v, dtype=torch.float32).double().numpy()[
        big_f]}
    assert got == want, _report_seed(seed)
    assert topology_report(clean)["genus"] == 0 and topology_report(clean)["euler_number"] == 2


@pytest.mark.parametrize("seed", SEEDS)
def test_share_threshold_and_the_largest_component_always_stays(seed: int) -> None:
    rng = np.random.default_rng(seed)
    parts = [_sphere(rng, 1, r) for r in rng.uniform(0.1, 0.2, 4)]
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    mesh = _mesh(np.concatenate([v + 3 * k for k, (v, _) in enumerate(parts)]),
                 np.concatenate([f + o for (_, f), o in zip(parts, offsets, strict=True)]))
    _, areas = mesh_components(mesh)
    untouched, report = drop_floaters(mesh, 0.0)
    assert untouched is mesh and report["floaters_dropped"] == 0 and report["floater_area_share"] == 0.0
    # Every part is below 90 % of the total: only the largest is kept.
    clean, report = drop_floaters(mesh, 0.9)
    assert report["components"] == 1 and report["floaters_dropped"] == 3, _report_seed(seed)
    assert report["floater_area_share"] == pytest.approx(float(areas[1:].sum() / areas.sum()), abs=1e-6)
    assert float(mesh_components(clean)[1][0]) == pytest.approx(float(areas[0]), rel=1e-5)
    with pytest.raises(ValueError, match="min_share"):
        drop_floaters(mesh, 1.0)


@pytest.mark.parametrize("seed", SEEDS)
def test_torus_has_genus_one_and_euler_number_zero(seed: int) -> None:
    rng = np.random.default_rng(seed)
    big, small = rng.uniform(0.5, 1.0), rng.uniform(0.05, 0.3)
    u, v = int(rng.integers(8, 24)), int(rng.integers(5, 12))

    def point(a: np.ndarray, t: np.ndarray) -> np.ndarray:
        b = 2 * np.pi * t
        return np.stack([(big + small * np.cos(b)) * np.cos(a), (big + small * np.cos(b)) * np.sin(a),
                         small * np.sin(b)], -1)

    verts, faces = _grid_surface(u, v, True, point)
    report = topology_report(_mesh(verts, faces))
    assert report == {"components": 1, "euler_number": 0, "genus": 1, "non_manifold_edges": 0,
                      "boundary_edges": 0, "holes": 0}, _report_seed(seed)
    # A torus and a sphere far apart: genus adds up (1 + 0), χ = 0 + 2.
    sv, sf = _sphere(rng, 2, 0.2)
    both = _mesh(np.concatenate([verts, sv + 5.0]), np.concatenate([faces, sf + len(verts)]))
    report = topology_report(both)
    assert (report["components"], report["euler_number"], report["genus"]) == (2, 2, 1), _report_seed(seed)


@pytest.mark.parametrize("seed", SEEDS)
def test_open_cylinder_has_two_holes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    radius, height = rng.uniform(0.1, 1.0), rng.uniform(0.2, 2.0)
    u, v = int(rng.integers(6, 30)), int(rng.integers(1, 6))
    verts, faces = _grid_surface(u, v, False, lambda a, t: np.stack(
        [radius * np.cos(a), radius * np.sin(a), height * t], -1))
    report = topology_report(_mesh(verts + rng.uniform(-1, 1, 3), faces))
    assert report == {"components": 1, "euler_number": 0, "genus": None, "non_manifold_edges": 0,
                      "boundary_edges": 2 * u, "holes": 2}, _report_seed(seed)


def test_three_triangles_on_one_edge_make_one_non_manifold_edge() -> None:
    verts = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=float)
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    report = topology_report(_mesh(verts, faces))
    # 5 vertices, 7 edges (one shared by all three), 3 faces; 6 open edges forming one loop
    # through both ends of the shared edge.
    assert report == {"components": 1, "euler_number": 1, "genus": None, "non_manifold_edges": 1,
                      "boundary_edges": 6, "holes": 1}


def test_zero_faces_give_an_empty_report_not_an_error() -> None:
    mesh = _mesh(np.random.default_rng(FRESH).uniform(size=(4, 3)), np.zeros((0, 3), dtype=np.int64))
    labels, areas = mesh_components(mesh)
    assert labels.shape == (0,) and areas.shape == (0,)
    assert topology_report(mesh) == {"components": 0, "euler_number": 0, "genus": None, "non_manifold_edges": 0,
                                     "boundary_edges": 0, "holes": 0}
    same, report = drop_floaters(mesh, 0.01)
    assert same is mesh
    assert report == {"components_before": 0, "components": 0, "floaters_dropped": 0, "floater_area_share": 0.0}


@pytest.mark.parametrize("seed", SEEDS)
def test_connected_labels_match_a_breadth_first_search(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    pairs = rng.integers(0, n, size=(int(rng.integers(0, n)), 2))
    labels = connected_labels(n, pairs)
    neighbours: list[list[int]] = [[] for _ in range(n)]
    for a, b in pairs:
        neighbours[a].append(int(b))
        neighbours[b].append(int(a))
    want = np.full(n, -1)
    count = 0
    for start in range(n):
        if want[start] >= 0:
            continue
        want[start], stack = count, [start]
        while stack:
            for nxt in neighbours[stack.pop()]:
                if want[nxt] < 0:
                    want[nxt] = count
                    stack.append(nxt)
        count += 1
    # Both number components by their smallest node, so the labels agree exactly.
    assert np.array_equal(labels, want), _report_seed(seed)


# -- the bake stage ---------------------------------------------------------------------------------


@pytest.mark.parametrize("share", [0.01, 0.0])
def test_bake_stage_drops_floaters_and_records_its_decisions(tmp_path: Path, share: float) -> None:
    rng = np.random.default_rng(FRESH)
    big_v, big_f = _sphere(rng, 2, 0.5)
    tiny_v, tiny_f = _sphere(rng, 1, 0.03)
    mesh = _mesh(np.concatenate([big_v * 0.5, tiny_v * 0.5 + 0.6]), np.concatenate([big_f, tiny_f + len(big_v)]))
    dmtet_dir, reference = tmp_path / "dmtet", tmp_path / "reference"
    for d in (dmtet_dir, reference, tmp_path / "out"):
        d.mkdir()
    save_mesh(dmtet_dir / MESH_FILE, mesh)
    tcfg = TextureFieldConfig(hashgrid=HashGridConfig(n_levels=2, log2_table_size=8), hidden_dim=8)
    save_module(dmtet_dir / TEXTURE_FILE, TextureField(tcfg, generator=torch.Generator().manual_seed(0)), tcfg)
    Image.new("RGBA", (32, 32), (200, 100, 50, 255)).save(reference / "rgba_32.png")

    cfg = BakeStageConfig(map=BakeConfig(texture_size=64), write_obj=False, turntable_views=2, preview_size=32,
                       eval_resolution=32, min_component_share=share)
    result = bake_asset(reference, dmtet_dir, dmtet_dir, tmp_path / "out", cfg, device="cpu")
    m = result.metrics
    dropped = share > 0
    assert (m["components_before"], m["components"], m["floaters_dropped"]) == ((2, 1, 1) if dropped else (2, 2, 0))
    assert (m["floater_area_share"] > 0) == dropped and m["floater_area_share"] < 0.01
    assert (m["euler_number"], m["genus"], m["non_manifold_edges"], m["boundary_edges"], m["holes"]) == \
        ((2 if dropped else 4), 0, 0, 0, 0)
    assert m["source_faces"] == len(big_f) + len(tiny_f) and m["watertight"] is True
    assert m["faces"] == (len(big_f) if dropped else len(big_f) + len(tiny_f))
    assert len(load_textured(tmp_path / "out" / ASSET_GLB).faces) == m["faces"]
    assert any("dropped 1 floating component" in n for n in result.notes) == dropped
    with pytest.raises(ValueError, match="min_component_share"):
        BakeStageConfig(min_component_share=1.0)
