"""benchmarks.scenes: closed, normalised, textured procedural products and their product photos."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from benchmarks.scenes import (
    ATLAS_COLUMNS,
    FRAME_FILL,
    MARGIN,
    MAX_EXTENT,
    SCENE_NAMES,
    SHADOW_DARKEST,
    TILE,
    Scene,
    make_scene,
    make_scenes,
)
from morpheus_core.cameras import reference_camera
from morpheus_core.imaging import bbox, object_high_frequency_ratio
from morpheus_core.render.textured import TexturedMesh, render_textured
from ops.intake.prepare import prepare_reference

SIZE = 256
HF_CUTOFF = 0.25
# Measured (seed 0): HF ratio ≥ 0.053 (mug; box 0.27, chair 0.43), blurred colour spread ≥ 0.09 (vase).
HF_FLOOR = 0.03
LF_FLOOR = 0.05


@pytest.fixture(scope="module")
def scenes() -> dict[str, Scene]:
    built = {}
    for name in SCENE_NAMES:
        start = time.perf_counter()
        built[name] = make_scene(name)
        print(f"{name}: built in {time.perf_counter() - start:.2f} s, {built[name].mesh.faces.shape[0]} faces")
    return built


@pytest.fixture(scope="module")
def references(scenes: dict[str, Scene]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each scene's reference view at 256 px: rgb (H, W, 3) and opacity (H, W)."""
    out = {}
    for name, scene in scenes.items():
        render = scene.render(reference_camera(), SIZE)
        out[name] = render.rgb[0].numpy(), render.opacity[0, ..., 0].numpy()
    return out


def _interior(alpha: np.ndarray, px: int = 3) -> np.ndarray:
    return cv2.erode((alpha >= 0.5).astype(np.uint8), np.ones((2 * px + 1,) * 2, np.uint8)).astype(bool)


def _low_frequency_spread(rgb: np.ndarray, alpha: np.ndarray) -> float:
    """Colour spread across the object after a heavy blur (normalised by the blurred mask, so the white
    background does not leak in): large uniform regions of different colours."""
    inside = _interior(alpha)
    weight = inside.astype(np.float32)
    blurred = cv2.GaussianBlur(rgb * weight[..., None], (0, 0), 6.0)
    blurred /= np.maximum(cv2.GaussianBlur(weight, (0, 0), 6.0), 1e-6)[..., None]
    return float(blurred[inside].std(axis=0).mean())


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_mesh_is_closed_outward_and_inside_the_grid(scenes: dict[str, Scene], name: str) -> None:
    mesh = scenes[name].mesh
    assert mesh.vertices.dtype == torch.float32 and mesh.faces.dtype == torch.int64
    assert mesh.texture.dtype == torch.float32 and mesh.uvs.dtype == torch.float32
    assert torch.isfinite(mesh.vertices).all() and torch.isfinite(mesh.uvs).all()
    assert mesh.uvs.min() >= 0.0 and mesh.uvs.max() <= 1.0
    assert mesh.texture.min() >= 0.0 and mesh.texture.max() <= 1.0
    assert mesh.vertices.abs().max() < MAX_EXTENT

    welded, _ = mesh.welded()
    counts = welded.topology.edge_counts
    assert (counts == 2).all(), f"{name}: {(counts != 2).sum().item()} edges not shared by exactly two faces"
    faces = welded.faces
    # Consistent winding: each directed edge once (its reverse belongs to the neighbour).
    directed = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert torch.unique(directed, dim=0).shape[0] == directed.shape[0]
    corners = welded.vertices.double()[faces]
    cross = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1)
    assert cross.norm(dim=-1).min() > 1e-10, f"{name}: degenerate faces"
    # Outward: the divergence theorem gives a positive enclosed volume.
    volume = float((corners[:, 0] * cross).sum() / 6.0)
    assert volume > 0.01, f"{name}: volume {volume}"


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_uvs_stay_inside_one_atlas_tile(scenes: dict[str, Scene], name: str) -> None:
    """Every face samples a single tile, away from its padded margin: no bleeding between parts."""
    mesh = scenes[name].mesh
    height, width = mesh.texture.shape[:2]
    assert width == ATLAS_COLUMNS * TILE and height % TILE == 0
    uv = mesh.uvs.double()[mesh.faces]  # (F, 3, 2)
    col = uv[..., 0] * width
    row = (1.0 - uv[..., 1]) * height
    for coord in (col, row):
        cell = torch.floor(coord.mean(-1, keepdim=True) / TILE)
        local = coord - cell * TILE
        assert (local >= MARGIN - 1e-3).all() and (local <= TILE - MARGIN + 1e-3).all()


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_reference_silhouette_is_normalised(references: dict[str, tuple[np.ndarray, np.ndarray]],
                                            name: str) -> None:
    x0, y0, x1, y1 = bbox(references[name][1] >= 0.5)
    print(f"{name}: bbox {(x0, y0, x1, y1)}")
    assert abs((x0 + x1) / 2 - SIZE / 2) <= 1.5 and abs((y0 + y1) / 2 - SIZE / 2) <= 1.5
    assert abs(max(x1 - x0, y1 - y0) - FRAME_FILL * SIZE) <= 2.0


def test_textures_have_large_regions_and_fine_detail(scenes: dict[str, Scene],
                                                     references: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    for name, (rgb, alpha) in references.items():
        hf = object_high_frequency_ratio(rgb, alpha, HF_CUTOFF)
        lf = _low_frequency_spread(rgb, alpha)
        print(f"{name}: high-frequency ratio {hf:.4f}, blurred colour spread {lf:.3f}")
        assert hf > HF_FLOOR, name
        assert lf > LF_FLOOR, name
    # The floors discriminate: the same mug painted in its mean colour fails both.
    mug = scenes["mug"].mesh
    flat = TexturedMesh(mug.vertices, mug.faces, mug.uvs, mug.texture.mean((0, 1), keepdim=True).expand(8, 8, 3))
    render = render_textured(flat, reference_camera(), SIZE, SIZE)
    rgb, alpha = render.rgb[0].numpy(), render.opacity[0, ..., 0].numpy()
    assert object_high_frequency_ratio(rgb, alpha, HF_CUTOFF) < HF_FLOOR / 3
    assert _low_frequency_spread(rgb, alpha) < LF_FLOOR / 5


def test_colours_vary_across_scenes(references: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    means = np.stack([rgb[_interior(alpha)].mean(axis=0) for rgb, alpha in references.values()])
    saturation = means.max(axis=1) - means.min(axis=1)
    assert np.median(saturation) > 0.1  # not all grey
    distances = np.linalg.norm(means[:, None] - means[None], axis=-1)[np.triu_indices(len(means), 1)]
    assert distances.min() > 0.03


def test_same_seed_reproduces_and_another_seed_changes_the_texture(scenes: dict[str, Scene], tmp_path: Path) -> None:
    again = make_scene("vase", 0)
    for field in ("vertices", "faces", "uvs", "texture"):
        assert torch.equal(getattr(again.mesh, field), getattr(scenes["vase"].mesh, field)), field
    path = again.write_photo(tmp_path / "vase.png", size=96)
    assert [p.name for p in tmp_path.iterdir()] == ["vase.png"]  # no temporary left behind
    assert np.array_equal(np.asarray(Image.open(path)), scenes["vase"].photo(96))
    other = make_scene("vase", 1)
    assert other.seed == 1 and other.name == "vase"
    assert other.mesh.texture.shape != again.mesh.texture.shape or \
        (other.mesh.texture - again.mesh.texture).abs().mean() > 0.05
    assert [s.name for s in make_scenes(0, ["box", "mug"])] == ["box", "mug"]


def test_surface_points_lie_on_the_mesh(scenes: dict[str, Scene]) -> None:
    scene = scenes["bottle"]
    points, colours = scene.surface_points(500, torch.Generator().manual_seed(0))
    assert points.shape == (500, 3) and colours.shape == (500, 3)
    assert colours.min() >= 0.0 and colours.max() <= 1.0
    lo, hi = scene.mesh.vertices.min(0).values, scene.mesh.vertices.max(0).values
    assert ((points >= lo - 1e-5) & (points <= hi + 1e-5)).all()
    again, _ = scene.surface_points(500, torch.Generator().manual_seed(0))
    assert torch.equal(points, again)


def test_photo_matches_the_reference_render_with_a_light_shadow(
        scenes: dict[str, Scene], references: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    scene = scenes["mug"]
    photo = scene.photo(SIZE)
    assert photo.shape == (SIZE, SIZE, 3) and photo.dtype == np.uint8
    for corner in (photo[0, 0], photo[0, -1], photo[-1, 0], photo[-1, -1]):
        assert (corner == 255).all()
    rgb, alpha = references["mug"]
    inside = _interior(alpha)
    diff = np.abs(photo.astype(np.float32) / 255.0 - rgb)[inside]
    print(f"photo vs render inside the mug: mean |Δ| {diff.mean():.4f}, 99th percentile {np.quantile(diff, 0.99):.3f}")
    assert diff.mean() < 0.03
    # Background: away from the silhouette (the photo is supersampled, so its edge differs a little).
    background = cv2.dilate((alpha > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
    grey = photo.astype(np.float32).mean(-1) / 255.0
    assert grey[background].min() >= SHADOW_DARKEST - 0.02  # light
    x0, y0, x1, y1 = bbox(alpha >= 0.5)
    below = grey[y1 + 1:y1 + 4, (x0 + x1) // 2 - 5:(x0 + x1) // 2 + 5]
    assert below.max() < 0.97  # present under the object
    assert (grey[:y0 - 2] == 1.0).all()  # and nowhere above it
    plain = scene.photo(SIZE, shadow=False).astype(np.float32).mean(-1) / 255.0
    assert (plain[background] > 0.995).all()


def test_fill_sets_the_object_size(scenes: dict[str, Scene]) -> None:
    scene = scenes["bottle"]
    tiny = scene.photo(512, fill=0.08, shadow=False)
    x0, y0, x1, y1 = bbox(tiny.min(-1) < 250)
    print(f"fill 0.08 at 512 px: bbox {(x0, y0, x1, y1)}")
    assert abs(max(x1 - x0, y1 - y0) - 0.08 * 512) <= 3
    assert abs((x0 + x1) / 2 - 256) <= 2 and abs((y0 + y1) / 2 - 256) <= 2
    big = scene.photo(128, fill=1.2, shadow=False).min(-1) < 250
    assert big[0].any() and big[-1].any()  # the tall bottle is cut at the top and bottom borders


def test_reference_stage_reproduces_the_frame(scenes: dict[str, Scene],
                                              references: dict[str, tuple[np.ndarray, np.ndarray]],
                                              tmp_path: Path) -> None:
    for name in ("mug", "bottle"):
        path = scenes[name].write_photo(tmp_path / f"{name}.png")
        prepare_reference(path, tmp_path / f"ref_{name}")
        mask = np.asarray(Image.open(tmp_path / f"ref_{name}" / "mask_256.png")) >= 128
        truth = references[name][1] >= 0.5
        iou = (mask & truth).sum() / (mask | truth).sum()
        print(f"{name}: reference-stage mask IoU {iou:.4f}")
        assert iou >= 0.95


def test_unknown_scene_names_the_valid_ones(scenes: dict[str, Scene]) -> None:
    with pytest.raises(ValueError, match="mug, bottle, box, vase, sneaker, lamp, chair, figure"):
        make_scene("teapot")
    with pytest.raises(ValueError, match="fill"):
        scenes["box"].photo(64, fill=0.0)
