"""QA part checks: silhouette components and the NeRF-against-GLB comparison on random blobs, and
``run_qa`` end to end on a NeRF file and GLBs built here with the pipeline's own writers.

The end-to-end NeRF is a real ``NerfField`` whose log-density is written into a one-level dense
hash grid (the density MLP passes the first feature through), so its shape is known exactly:
spheres of radius R where log σ = 100·(1 − d/R): opaque inside, empty outside, the edge sharp.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from morpheus_core.cameras import reference_camera
from morpheus_core.export.gltf import export_glb
from morpheus_core.export.uv_bake import BakeConfig, bake_uv
from morpheus_core.geometry.hashgrid import HashGridConfig
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.geometry.nerf import NerfConfig, NerfField
from morpheus_core.render.textured import load_textured, render_textured
from morpheus_core.render.volume import OccupancyGrid, OccupancyGridConfig
from morpheus_core.segmentation.part_silhouettes import compare_part_silhouettes, count_parts, mask_components
from ops.engine.artifacts import save_module
from ops.engine.checks import read_report
from ops.stages.nerf import NERF_FILE
from ops.stages.qa import QAConfig, run_qa
from tests.seeds import fresh_seed

FRESH = fresh_seed()
SEEDS = [0, FRESH]


def _discs(shape: tuple[int, int], discs: list[tuple[float, float, float]]) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(shape[0]), torch.arange(shape[1]), indexing="ij")
    out = torch.zeros(shape, dtype=torch.bool)
    for cy, cx, r in discs:
        out |= (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
    return out


def _separate_discs(rng: np.random.Generator, n: int, size: int, r_lo: float, r_hi: float) -> list[tuple]:
    """``n`` random discs at least two pixels apart (rejection sampling)."""
    out: list[tuple[float, float, float]] = []
    while len(out) < n:
        r = rng.uniform(r_lo, r_hi)
        cy, cx = rng.uniform(r + 1, size - r - 1, 2)
        if all((cy - y) ** 2 + (cx - x) ** 2 > (r + q + 3) ** 2 for y, x, q in out):
            out.append((cy, cx, r))
    return out


# -- silhouette components ------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_mask_components_match_opencv(seed: int) -> None:
    rng = np.random.default_rng(seed)
    mask = torch.from_numpy(rng.uniform(size=(40, 50)) < rng.uniform(0.2, 0.6))
    labels, sizes = mask_components(mask)
    count, want = cv2.connectedComponents(mask.numpy().astype(np.uint8), connectivity=8)
    assert len(sizes) == count - 1, f"seed {seed}"
    assert sorted(sizes.tolist(), reverse=True) == sizes.tolist()  # label 0 is the largest
    assert sorted(sizes.tolist()) == sorted(np.bincount(want[want > 0]).tolist()[1:])
    assert bool(((labels >= 0) == mask).all())
    # Same partition: each of our components is exactly one of OpenCV's.
    for k in range(len(sizes)):
        theirs = np.unique(want[labels.numpy() == k])
        assert len(theirs) == 1 and int((want == theirs[0]).sum()) == int(sizes[k]), f"seed {seed}"


@pytest.mark.parametrize("seed", SEEDS)
def test_count_parts_ignores_specks(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 4))
    mask = _discs((80, 80), _separate_discs(rng, n, 80, 6, 12))
    # Specks in the corners, one pixel each: below 1 % of the mask's area.
    mask[0, 0] = mask[0, 79] = mask[79, 0] = True
    assert count_parts(mask, 0.01) == n, f"seed {seed}"
    assert count_parts(mask, 0.0) == n + 3
    assert count_parts(torch.zeros(8, 8, dtype=torch.bool)) == 0


# -- the NeRF-against-mesh comparison ---------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_a_lost_blob_is_found_and_an_outline_ring_is_not(seed: int) -> None:
    rng = np.random.default_rng(seed)
    views, size = int(rng.integers(2, 5)), 64
    two = [_separate_discs(rng, 2, size, 8, 14) for _ in range(views)]
    reference = torch.stack([_discs((size, size), d) for d in two])
    kept = torch.stack([_discs((size, size), d[:1]) for d in two])

    same = compare_part_silhouettes(reference, reference.clone())
    assert same.iou == (1.0,) * views and same.missing_share == (0.0,) * views

    lost = compare_part_silhouettes(reference, kept)
    for v, d in enumerate(two):
        area = int(reference[v].sum())
        lost_area = int(_discs((size, size), d[1:]).sum())
        # The opening trims the lost disc's rim a little, nothing more.
        assert lost_area * 0.8 <= round(lost.missing_share[v] * area) <= lost_area, f"seed {seed}, view {v}"
        assert lost.iou[v] == pytest.approx(int(kept[v].sum()) / area)
    assert lost.missing_share_max > 0.1 and lost.iou_min == min(lost.iou)

    # The candidate one pixel smaller all around: a connected ring, but not a part.
    shrunk = torch.stack([_discs((size, size), [(y, x, r - 1) for y, x, r in d]) for d in two])
    ring = compare_part_silhouettes(reference, shrunk)
    assert ring.missing_share_max == 0.0 and ring.iou_min > 0.7, f"seed {seed}"
    assert compare_part_silhouettes(reference, shrunk, opening=0).missing_share_max > 0.0

    # Thinner by three pixels all around: a thick shell, which only a margin of 3 px forgives;
    # the margin forgives no lost disc (it lies further than that from what was kept). How much of
    # the shell is found depends on the discs: the 3×3 opening breaks a digital 3-px ring into pieces
    # whose largest was as little as 5.5 % of the silhouette over 400 seeds, so only "found" is asserted.
    thinner = torch.stack([_discs((size, size), [(y, x, r - 3) for y, x, r in d]) for d in two])
    assert compare_part_silhouettes(reference, thinner).missing_share_max > 0.0, f"seed {seed}"
    assert compare_part_silhouettes(reference, thinner, margin=3).missing_share_max == 0.0, f"seed {seed}"
    assert compare_part_silhouettes(reference, kept, margin=3).missing_share_max > 0.1, f"seed {seed}"


def test_part_comparison_edge_cases() -> None:
    empty = torch.zeros(2, 1, 16, 16)
    assert compare_part_silhouettes(empty, empty).iou == (1.0, 1.0)
    something = empty.clone()
    something[:, :, 4:8, 4:8] = 1.0
    extra = compare_part_silhouettes(empty, something)
    assert extra.iou == (0.0, 0.0) and extra.missing_share == (0.0, 0.0)
    with pytest.raises(ValueError, match="differ in shape"):
        compare_part_silhouettes(empty, empty[:1])
    with pytest.raises(ValueError, match="at least one view"):
        compare_part_silhouettes(empty[:0], empty[:0])


# -- run_qa end to end ----------------------------------------------------------------------------

RES = 64
QA = QAConfig(eval_resolution=RES, turntable_views=4, turntable_resolution=RES, weighted_metrics=False,
              part_views=6, part_resolution=48, part_samples=48, strip_views=2, preview_size=32)


def _nerf_of_spheres(path: Path, spheres: list[tuple[tuple[float, float, float], float]]) -> Path:
    """A ``nerf.safetensors`` as the NeRF stage writes it (field + refreshed occupancy grid) whose
    density is the given spheres."""
    grid = HashGridConfig(n_levels=1, n_features_per_level=2, log2_table_size=15, base_resolution=32)
    config = NerfConfig(grid=grid, hidden=2, n_hidden_layers=1, blob_density=0.0)
    field = NerfField(config)
    scale, res = grid.level_layout()[0][:2]
    axis = (torch.arange(res, dtype=torch.float64) - 0.5) / scale * 2 - 1  # the world point of each vertex
    zz, yy, xx = torch.meshgrid(axis, axis, axis, indexing="ij")  # row = x + y·res + z·res²
    points = torch.stack([xx, yy, zz], -1).reshape(-1, 3)
    log_density = torch.stack([100 * (1 - (points - torch.tensor(c, dtype=torch.float64)).norm(dim=-1) / r)
                               for c, r in spheres]).amax(0).clamp(-30, 20)
    with torch.no_grad():
        field.encoding.table.zero_()
        field.encoding.table[:, 0] = log_density.float()
        first, last = field.density_mlp[0], field.density_mlp[2]
        first.weight.copy_(torch.tensor([[1.0, 0.0], [0.0, 0.0]]))
        first.bias.copy_(torch.tensor([100.0, 0.0]))  # keeps the ReLU open: raw = feature − 0
        last.weight.copy_(torch.tensor([[1.0, 0.0]]))
        last.bias.fill_(-100.0)
    occupancy = OccupancyGrid(OccupancyGridConfig(resolution=16), config.bbox_radius)
    generator = torch.Generator().manual_seed(0)
    for _ in range(8):  # a decayed max over many jittered probes, as after a fit
        occupancy.refresh(field, generator)
    return save_module(path / NERF_FILE, field, config, {"occupancy": occupancy.density})


def _colour(points: torch.Tensor) -> torch.Tensor:
    return (0.5 + 0.35 * torch.sin(9 * points + torch.tensor([0.0, 2.0, 4.0]))).clamp(0, 1)


def _glb_of_spheres(path: Path, spheres: list[tuple[tuple[float, float, float], float]]) -> Path:
    parts = [trimesh.creation.icosphere(subdivisions=3, radius=r).apply_translation(c) for c, r in spheres]
    both = trimesh.util.concatenate(parts)
    mesh = Mesh(torch.tensor(both.vertices, dtype=torch.float32), torch.tensor(both.faces, dtype=torch.int64))
    return export_glb(bake_uv(mesh, _colour, BakeConfig(texture_size=128)), path)


def _photo_of(glb: Path, reference_dir: Path) -> Path:
    """The reference folder's RGBA as the asset itself looks from the photo's camera."""
    out = render_textured(load_textured(glb), reference_camera(), RES, RES)
    rgba = torch.cat([out.rgb[0], out.opacity[0]], -1).clamp(0, 1).numpy()
    reference_dir.mkdir(parents=True, exist_ok=True)
    Image.fromarray((rgba * 255 + 0.5).astype(np.uint8), "RGBA").save(reference_dir / f"rgba_{RES}.png")
    return reference_dir


def _qa(tmp: Path, nerf: list | None, glb: list, photo: list) -> tuple[dict, dict]:
    nerf_dir = None
    if nerf is not None:
        nerf_dir = tmp / "nerf"
        nerf_dir.mkdir()
        _nerf_of_spheres(nerf_dir, nerf)
    asset = _glb_of_spheres(tmp / "asset.glb", glb)
    reference = _photo_of(asset if photo == glb else _glb_of_spheres(tmp / "photo.glb", photo), tmp / "reference")
    (tmp / "qa").mkdir()
    result, written = run_qa(reference, asset, tmp / "qa", QA, {}, device="cpu", nerf_dir=nerf_dir)
    report = read_report(tmp / "qa")
    assert written == report  # what the stage passes on is what qa.json holds
    checks = {c["name"]: c for c in report.checks["qa"]}
    assert result.metrics["verdict"] == report.verdict
    return report.__dict__, checks


SIDE_BY_SIDE = [((-0.45, 0.0, 0.0), 0.3), ((0.45, 0.0, 0.0), 0.3)]
# From the photo's camera (on +z) the back sphere hides behind the front one.
FRONT, BACK = ((0.0, 0.0, 0.25), 0.35), ((0.0, 0.0, -0.45), 0.25)


def test_a_mesh_matching_its_nerf_passes(tmp_path: Path) -> None:
    report, checks = _qa(tmp_path, SIDE_BY_SIDE, SIDE_BY_SIDE, SIDE_BY_SIDE)
    assert checks["parts_kept"]["passed"] and checks["part_count"]["passed"], checks
    assert report["metrics"]["mask_parts"] == 2 and report["metrics"]["components"] == 2
    assert report["metrics"]["part_iou_min"] > 0.9 and report["metrics"]["missing_part_share_max"] < 0.02
    assert report["verdict"] == "pass", report["reasons"]


def test_a_mesh_that_lost_a_part_fails(tmp_path: Path) -> None:
    # The photo shows only the front sphere, so its mask agrees with the mesh; the NeRF has both.
    report, checks = _qa(tmp_path, [FRONT, BACK], [FRONT], [FRONT])
    assert checks["mask_iou"]["passed"] and checks["part_count"]["passed"], checks
    assert not checks["parts_kept"]["passed"] and checks["parts_kept"]["severity"] == "error"
    assert "lost a part" in checks["parts_kept"]["message"]
    assert report["metrics"]["missing_part_share_max"] > QA.max_missing_part_share
    assert report["verdict"] == "fail"
    assert [r.split(":")[0] for r in report["reasons"]] == ["parts_kept"]


def test_an_extra_floater_warns_on_part_count(tmp_path: Path) -> None:
    floater = ((0.3, 0.45, 0.0), 0.05)
    report, checks = _qa(tmp_path, [FRONT], [FRONT, floater], [FRONT])
    assert not checks["part_count"]["passed"] and checks["part_count"]["severity"] == "warn"
    assert checks["part_count"]["message"] == ("the GLB has 2 connected component(s), the photo's mask 1 "
                                               "silhouette part(s)")
    assert checks["parts_kept"]["passed"], checks["parts_kept"]  # extra is not missing
    assert report["verdict"] == "warn" and [r.split(":")[0] for r in report["reasons"]] == ["part_count"]


def test_without_a_nerf_stage_parts_kept_is_not_measured(tmp_path: Path) -> None:
    report, checks = _qa(tmp_path, None, [FRONT], [FRONT])
    assert checks["parts_kept"]["passed"] and checks["parts_kept"]["message"] == "not measured: no NeRF stage output"
    assert "part_iou_min" not in report["metrics"] and report["verdict"] == "pass", report["reasons"]
