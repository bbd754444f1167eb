"""The inflated proxy: sphere from a disk, reference silhouette = mask, closed meshes (frame-filling,
blobs, sub-cell specks), photo on the front and its mirror on the back, SDF signs, errors, targets.

Inputs are fresh random draws; the seed is printed (pytest shows it on failure) to replay one.
Expected values are derived from the definition, not from the implementation: the world point on
the z = 0 plane under pixel (u, v) is ((2u/W − 1)·h, (1 − 2v/H)·h, 0) with h = 2.5·tan 20°, and
D is recomputed here with OpenCV.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from morpheus_core.cameras import orbit, reference_camera, sample_orbit
from morpheus_core.geometry.mesh import Mesh
from morpheus_core.geometry.tet_surface import DMTet, DMTetConfig
from morpheus_core.priors.proxy.shape import EmptySilhouetteError, InflatedProxy, InflationConfig, from_reference_folder
from ops.intake.prepare import prepare_reference
from tests.photo_factory import PhotoSpec, product_photo

HALF_SPAN = 2.5 * math.tan(math.radians(20.0))  # half the reference view's width on z = 0


@pytest.fixture
def rng() -> np.random.Generator:
    seed = int(np.random.SeedSequence().entropy % 2**32)
    print(f"seed={seed}")
    return np.random.default_rng(seed)


def _rgba(mask: np.ndarray, rgb: np.ndarray | None = None) -> np.ndarray:
    """uint8 RGBA on white: the layout of a prepared reference."""
    out = np.full((*mask.shape, 4), 255, dtype=np.uint8)
    if rgb is not None:
        out[..., :3] = np.where(mask[..., None], np.round(rgb * 255), 255).astype(np.uint8)
    else:
        out[mask, :3] = (180, 60, 40)
    out[..., 3] = np.where(mask, 255, 0)
    return out


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (u = column + 0.5, v = row + 0.5)."""
    v, u = np.mgrid[0:size, 0:size] + 0.5
    return u, v


def _blob_mask(size: int, rng: np.random.Generator, centre: tuple[float, float], radius: float) -> np.ndarray:
    """A random smooth star-shaped blob (radius varies with angle by up to ±54%)."""
    u, v = _grid(size)
    ang = np.arctan2(v - centre[1], u - centre[0])
    r = np.full_like(u, radius)
    for k in range(2, 5):
        r += radius * rng.uniform(0.0, 0.25 / k * 2) * np.cos(k * ang + rng.uniform(0, 2 * np.pi))
    return np.hypot(u - centre[0], v - centre[1]) <= r


def _ellipse_mask(size: int, rng: np.random.Generator) -> np.ndarray:
    u, v = _grid(size)
    cx, cy = rng.uniform(0.4, 0.6, 2) * size
    a, b = rng.uniform(0.22, 0.32) * size, rng.uniform(0.12, 0.22) * size
    t = rng.uniform(0, np.pi)
    x = (u - cx) * np.cos(t) + (v - cy) * np.sin(t)
    y = -(u - cx) * np.sin(t) + (v - cy) * np.cos(t)
    return (x / a) ** 2 + (y / b) ** 2 <= 1


def _smooth_photo(size: int, rng: np.random.Generator) -> np.ndarray:
    u, v = _grid(size)
    img = np.full((size, size, 3), 0.5)
    for _ in range(3):
        f = rng.uniform(0.5, 2.0, 2) * rng.choice([-1, 1], 2)
        wave = np.sin(2 * np.pi * (f[0] * u + f[1] * v) / size + rng.uniform(0, 2 * np.pi))
        img += rng.uniform(0.05, 0.15, 3) * wave[..., None]
    return np.clip(img, 0.05, 0.95)


def _z0_point(u: np.ndarray, v: np.ndarray, size: int) -> np.ndarray:
    """World points on z = 0 seen at image coordinates (u, v) from the reference camera."""
    return np.stack([(2 * u / size - 1) * HALF_SPAN, (1 - 2 * v / size) * HALF_SPAN, np.zeros_like(u)], -1)


def _on_ray(p0: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Points at depth z on the reference camera's rays through the z = 0 points p0."""
    scale = (2.5 - z) / 2.5
    return np.stack([p0[..., 0] * scale, p0[..., 1] * scale, z], -1)


def _signed_distance(mask: np.ndarray) -> np.ndarray:
    """D of the definition: distance from pixel centres to the silhouette's pixel edges, + inside."""
    din = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    dout = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(mask, din - 0.5, 0.5 - dout)


def _erode(mask: np.ndarray, px: int) -> np.ndarray:
    return cv2.erode(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1,) * 2)) > 0


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def _psnr(a: np.ndarray, b: np.ndarray, region: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a[region] - b[region]) ** 2)))


def _silhouette(proxy: InflatedProxy, size: int) -> np.ndarray:
    return proxy.render(reference_camera(), size, size).opacity[0, ..., 0].cpu().numpy() >= 0.5


def _assert_watertight(mesh: Mesh) -> None:
    counts = mesh.topology.edge_counts
    assert mesh.num_faces > 0
    assert bool((counts == 2).all()), f"{int((counts != 2).sum())} edges not shared by exactly two faces"


def test_disk_with_thickness_one_is_a_sphere(rng: np.random.Generator) -> None:
    """The solid is the sphere of radius R = Dmax·s in the reference camera's projective coordinates
    (image position on z = 0, depth): checked there to 0.5 grid cell. In world space perspective moves
    the front in and the back out (a point at depth z sits (2.5 − z)/2.5 times as far off-axis as its
    image position), so the spread of distances from the centre is that of the ideal shape, computed
    below (≈ 0.7–1.5 cells here), plus at most 0.6 cell of meshing error, and never above 2 cells."""
    size, res = 192, 48  # a fine mask: its pixel staircase stays well below a grid cell
    cell, s = 2.0 / res, 2 * HALF_SPAN / size
    radius_px = rng.uniform(0.25, 0.35) / s
    centre = rng.uniform(size / 2 - 16, size / 2 + 16, 2)
    u, v = _grid(size)
    mask = np.hypot(u - centre[0], v - centre[1]) <= radius_px
    proxy = InflatedProxy(_rgba(mask), InflationConfig(grid_resolution=res))
    vertices = proxy.mesh().vertices.double().numpy()
    radius = _signed_distance(mask).max() * s

    uv = proxy.pixel_coordinates(torch.from_numpy(vertices)).numpy()
    r_img = np.hypot(uv[:, 0] - centre[0], uv[:, 1] - centre[1]) * s
    residual = np.abs(np.hypot(r_img, vertices[:, 2]) - radius).max()
    print(f"projective-sphere residual {residual / cell:.2f} cells")
    assert residual <= 0.5 * cell

    sphere_centre = _z0_point(centre[0], centre[1], size)
    phi, theta = np.meshgrid(np.linspace(0, np.pi, 181), np.linspace(0, 2 * np.pi, 360))
    z = radius * np.cos(phi)
    on_image = sphere_centre[:2] + radius * np.sin(phi)[..., None] * np.stack([np.cos(theta), np.sin(theta)], -1)
    ideal = np.hypot(np.linalg.norm(on_image * ((2.5 - z) / 2.5)[..., None] - sphere_centre[:2], axis=-1), z)
    dist = np.linalg.norm(vertices - sphere_centre, axis=-1)
    print(f"world distance spread {np.ptp(dist) / cell:.2f} cells (ideal shape {np.ptp(ideal) / cell:.2f})")
    assert np.ptp(dist) <= min(np.ptp(ideal) + 0.6 * cell, 2 * cell)
    assert abs(dist.mean() - radius) <= 0.5 * cell
    assert vertices[:, 2].max() == pytest.approx(radius, abs=0.5 * cell)
    assert vertices[:, 2].min() == pytest.approx(-radius, abs=0.5 * cell)


def test_reference_silhouette_is_the_mask_and_mesh_is_closed(rng: np.random.Generator) -> None:
    size = 96
    for mask in (_ellipse_mask(size, rng), _blob_mask(size, rng, tuple(rng.uniform(40, 56, 2)), rng.uniform(20, 30))):
        proxy = InflatedProxy(_rgba(mask), InflationConfig(grid_resolution=40, thickness=rng.uniform(0.5, 1.5)))
        _assert_watertight(proxy.mesh())
        iou = _iou(_silhouette(proxy, size), mask)
        print(f"IoU {iou:.4f}")
        assert iou >= 0.93


def test_prepared_photo_silhouette(tmp_path: Path, rng: np.random.Generator) -> None:
    """A synthetic product photo through the real preparation: the proxy's outline is its mask."""
    shape = str(rng.choice(["bottle", "cylinder", "blob"]))
    rgb, _ = product_photo(PhotoSpec(shape, "white", "stripes", int(rng.integers(1 << 30)), size=300))
    Image.fromarray(rgb).save(tmp_path / "photo.png")
    prepare_reference(tmp_path / "photo.png", tmp_path / "ref")
    proxy = from_reference_folder(tmp_path / "ref", 256, InflationConfig(grid_resolution=48))
    _assert_watertight(proxy.mesh())
    mask = np.asarray(Image.open(tmp_path / "ref" / "mask_256.png")).astype(np.float32) / 255
    size = 96
    small = cv2.resize(mask, (size, size), interpolation=cv2.INTER_AREA) >= 0.5
    iou = _iou(_silhouette(proxy, size), small)
    print(f"{shape}: IoU {iou:.4f}")
    assert iou >= 0.93


def test_missing_reference_file_names_prepare(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"rgba_512\.png.*morpheus3d prepare"):
        from_reference_folder(tmp_path, 512)


def test_frame_filling_silhouette_is_capped_and_closed(rng: np.random.Generator) -> None:
    """Cut by the left, right and bottom borders: the solid runs on to the grid and is capped there."""
    size, res = 96, 32
    mask = _blob_mask(size, rng, (size / 2, rng.uniform(35, 45)), rng.uniform(22, 28))
    mask[int(rng.uniform(0.55, 0.7) * size):] = True
    proxy = InflatedProxy(_rgba(mask), InflationConfig(grid_resolution=res))
    mesh = proxy.mesh()
    _assert_watertight(mesh)
    assert float(mesh.vertices.abs().max()) == pytest.approx(1.0, abs=1e-5)  # reaches the capped boundary
    iou = _iou(_silhouette(proxy, size), mask)
    print(f"IoU {iou:.4f}")
    assert iou >= 0.93


def test_a_proxy_deeper_than_the_grid_is_capped_with_a_warning() -> None:
    size, res = 64, 24
    u, v = _grid(size)
    mask = np.hypot(u - size / 2, v - size / 2) <= 0.5 / (2 * HALF_SPAN / size)  # radius 0.5: depth 1.5 > 1
    proxy = InflatedProxy(_rgba(mask), InflationConfig(thickness=3.0, grid_resolution=res))
    with pytest.warns(RuntimeWarning, match="capped"):
        mesh = proxy.mesh()
    _assert_watertight(mesh)
    assert float(mesh.vertices[:, 2].abs().max()) == pytest.approx(1.0, abs=1e-5)


def test_disconnected_blobs_each_become_a_closed_part(rng: np.random.Generator) -> None:
    """Two blobs and a speck of ~20 px that fits between grid vertices: three parts, all closed."""
    size = 128
    centres = [(32 + rng.uniform(-4, 4), 40.0), (92 + rng.uniform(-4, 4), 44.0), (64.0, 100 + rng.uniform(-4, 4))]
    mask = _blob_mask(size, rng, centres[0], rng.uniform(14, 17)) | _blob_mask(size, rng, centres[1], 16)  # never touch
    u, v = _grid(size)
    mask |= np.hypot(u - centres[2][0], v - centres[2][1]) <= 2.5
    proxy = InflatedProxy(_rgba(mask), InflationConfig(grid_resolution=32))
    _assert_watertight(proxy.mesh())
    silhouette = _silhouette(proxy, size)
    n_parts, _ = cv2.connectedComponents(silhouette.astype(np.uint8), connectivity=8)
    assert n_parts - 1 == 3
    assert _iou(silhouette, mask) >= 0.9


def test_a_speck_between_grid_vertices_still_gets_a_surface(rng: np.random.Generator) -> None:
    """A ~22 px disk centred in a grid cell's xy-middle: its solid (radius ≈ 0.038) holds no grid vertex
    (the nearest is ≥ 0.044 away), so plain marching tets would find no surface at all."""
    size, res = 128, 32
    cell = 2.0 / res
    x, y = (-1 + (rng.integers(4, res - 4, 2) + 0.5) * cell)  # a cell centre in xy, inside the view
    cu, cv = (x / HALF_SPAN + 1) * size / 2, (1 - y / HALF_SPAN) * size / 2
    u, v = _grid(size)
    mask = np.hypot(u - cu, v - cv) <= 2.7
    assert 16 < mask.sum() <= 30
    proxy = InflatedProxy(_rgba(mask), InflationConfig(grid_resolution=res))
    grid = DMTet(DMTetConfig(resolution=res)).grid_vertices
    assert bool((proxy.sdf(grid) >= 0).all())  # the premise: no vertex inside
    mesh = proxy.mesh()
    _assert_watertight(mesh)
    assert float((mesh.vertices[:, :2] - torch.tensor([x, y])).norm(dim=-1).max()) <= cell
    silhouette = _silhouette(proxy, size)
    assert silhouette[int(cv), int(cu)]
    iou = _iou(silhouette, mask)
    print(f"speck IoU {iou:.2f}")
    assert iou >= 0.3  # a sub-cell speck is a coarse polyhedron (0.42–0.83 over 100 draws), but there and in place
    assert not (silhouette & (cv2.dilate(mask.astype(np.uint8), np.ones((13, 13), np.uint8)) == 0)).any()


def test_front_shows_the_photo(rng: np.random.Generator) -> None:
    size = 96
    photo = _smooth_photo(size, rng)
    mask = _blob_mask(size, rng, tuple(rng.uniform(42, 54, 2)), rng.uniform(24, 32))
    proxy = InflatedProxy(_rgba(mask, photo), InflationConfig(grid_resolution=32))
    front = proxy.render(reference_camera(), size, size).rgb[0].numpy()
    expected = np.round(photo * 255) / 255
    psnr = _psnr(front, expected, _erode(mask, 2))
    print(f"front PSNR {psnr:.1f} dB")
    assert psnr >= 20
    # Rim and side points sample the photo right at the mask edge: no white may bleed in there.
    rim_colours = proxy.colour(proxy.mesh().vertices)
    assert float(rim_colours.max()) <= expected[mask].max() + 1e-6


def test_back_shows_the_mirrored_photo(rng: np.random.Generator) -> None:
    """Derivation: a back point and the reference camera (0, 0, 2.5) see the same photo colour; from
    the back camera (0, 0, −2.5) the image is mirrored (its right is world −x) and, being at a
    different depth, scaled about the image centre by (2.5 + |z|)/(2.5 − |z|). Both cameras lie on
    the z axis, so every ray of the back camera projects into the reference view on a line through
    the image centre: a photo whose colour depends only on the angle about the centre is unchanged
    by that scaling, and the back render must equal the flipped photo. Near the centre the angle
    changes within a pixel, so a 3 px disc there is left out."""
    size = 96
    u, v = _grid(size)
    ang = np.arctan2(v - size / 2, u - size / 2)
    photo = 0.5 + sum(rng.uniform(0.1, 0.2, 3) * np.sin(k * ang[..., None] + rng.uniform(0, 2 * np.pi, 3))
                      for k in (1, 2))
    mask = _blob_mask(size, rng, tuple(rng.uniform(42, 54, 2)), rng.uniform(24, 32))
    proxy = InflatedProxy(_rgba(mask, photo), InflationConfig(grid_resolution=32))
    back = proxy.render(orbit(0.0, 180.0), size, size).rgb[0].numpy()
    expected = (np.round(photo * 255) / 255)[:, ::-1]
    region = _erode(mask[:, ::-1], 2) & (np.hypot(u - size / 2, v - size / 2) > 3)
    psnr = _psnr(back, expected, region)
    print(f"back PSNR {psnr:.1f} dB (unflipped: {_psnr(back, expected[:, ::-1], region):.1f} dB)")
    assert psnr >= 18
    assert _psnr(back, expected[:, ::-1], region) < psnr - 6  # it is the mirror image, not the photo


def test_sdf_signs_and_height_profile(rng: np.random.Generator) -> None:
    size = 96
    mask = _ellipse_mask(size, rng)
    thickness = rng.uniform(0.5, 1.5)
    proxy = InflatedProxy(_rgba(mask), InflationConfig(thickness=thickness))
    d = _signed_distance(mask)
    s, dmax = 2 * HALF_SPAN / size, d.max()
    u, v = _grid(size)

    def sdf(points: np.ndarray) -> np.ndarray:
        return proxy.sdf(torch.from_numpy(points.reshape(-1, 3)).float()).numpy()

    # Inside pixels (D ≥ 1): the definition's H, negative within it, positive beyond it on both sides.
    inside = d >= 1
    p0 = _z0_point(u[inside], v[inside], size)
    height = thickness * s * np.sqrt(d[inside] * (2 * dmax - d[inside]))
    assert np.allclose(proxy.height_at(torch.from_numpy(p0).float()).numpy(), height, atol=1e-5)
    for sign in (1.0, -1.0):
        assert (sdf(_on_ray(p0, sign * 0.95 * height)) < 0).all()
        assert (sdf(_on_ray(p0, sign * (1.05 * height + 1e-4))) > 0).all()
    # Outside the silhouette cone (≥ 2 px away), at any depth in the box.
    outside = d <= -2
    p0 = _z0_point(u[outside], v[outside], size)
    assert (sdf(_on_ray(p0, rng.uniform(-1, 1, p0.shape[0]))) > 0).all()
    # Thickest in the middle: the deepest pixel against pixels on the rim.
    i, j = np.unravel_index(np.argmax(d), d.shape)
    centre = _z0_point(u[i, j], v[i, j], size)
    assert sdf(centre)[0] < 0
    rim = _z0_point(u[(d > 0) & (d < 1)], v[(d > 0) & (d < 1)], size)
    h_centre = proxy.height_at(torch.from_numpy(centre[None]).float())[0]
    h_rim = proxy.height_at(torch.from_numpy(rim).float())
    assert float(h_centre) == pytest.approx(thickness * dmax * s, rel=1e-4)
    assert float(h_centre) > 2 * float(h_rim.max())


@pytest.mark.parametrize("pixels", [0, 3])
def test_empty_or_tiny_mask_is_rejected(pixels: int, rng: np.random.Generator) -> None:
    mask = np.zeros((64, 64), dtype=bool)
    mask.ravel()[rng.choice(mask.size, pixels, replace=False)] = True
    with pytest.raises(EmptySilhouetteError, match=r"mask is (empty|too small).*segmentation"):
        InflatedProxy(_rgba(mask))


def test_bad_inputs_are_rejected() -> None:
    with pytest.raises(EmptySilhouetteError, match="whole image"):
        InflatedProxy(_rgba(np.ones((32, 32), dtype=bool)))
    with pytest.raises(ValueError, match="RGBA"):
        InflatedProxy(np.zeros((32, 32, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        InflatedProxy(torch.full((32, 32, 4), 2.0))
    with pytest.raises(TypeError, match="tensor or numpy"):
        InflatedProxy([[0, 0, 0, 255]])


@pytest.mark.parametrize("field, value", [
    ("thickness", 0.0), ("thickness", -1.0), ("thickness", float("nan")), ("thickness", float("inf")),
    ("grid_resolution", 3), ("grid_resolution", 2000), ("grid_resolution", 32.0), ("half_extent", 0.0),
    ("half_extent", float("nan")), ("colour_dilation", -1), ("min_mask_pixels", 0),
])
def test_invalid_config_values(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        InflationConfig(**{field: value})


def test_grid_must_lie_in_front_of_the_reference_camera() -> None:
    mask = np.zeros((32, 32), dtype=bool)
    mask[10:20, 10:20] = True
    with pytest.raises(ValueError, match="half_extent"):
        InflatedProxy(_rgba(mask), InflationConfig(half_extent=2.5))


def test_target_images(rng: np.random.Generator, device: torch.device) -> None:
    size = 64
    mask = _ellipse_mask(size, rng)
    rgba = torch.from_numpy(_rgba(mask, _smooth_photo(size, rng))).to(device).float() / 255
    proxy = InflatedProxy(rgba, InflationConfig(grid_resolution=32))
    cams = sample_orbit(3, generator=torch.Generator().manual_seed(int(rng.integers(1 << 30)))).to(device)
    with torch.enable_grad():
        target = proxy.target_images(cams, 48, 40)
    assert target.shape == (3, 3, 48, 40) and target.device.type == device.type
    assert not target.requires_grad and target.grad_fn is None
    assert float(target.min()) >= 0 and float(target.max()) <= 1
    assert torch.all(target[:, :, 0, 0] == 1.0)  # white background in the corner
    assert bool(((target < 0.99).any(1).flatten(1).float().mean(1) > 0.05).all())  # the object is in every view
    assert proxy.mesh().vertices.device.type == device.type and not proxy.mesh().vertices.requires_grad
