"""The rasteriser: ids against a brute-force reference, gradients against finite differences,
silhouette anti-aliasing against the finite-difference gradient of the hard mask, and the guards."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from morpheus_core.cameras import orbit
from morpheus_core.geometry.mesh import Mesh, mesh_topology
from morpheus_core.render.antialias import antialias, silhouette_crossings
from morpheus_core.render.raster import RasterConfig, RasterInputError, interpolate, rasterize

NEAR_W = RasterConfig().near_w
MIN_AREA = RasterConfig().min_area_px
DEGENERATE_REL = 64 * torch.finfo(torch.float64).eps


def to_clip(vertices: torch.Tensor, world_to_clip: torch.Tensor) -> torch.Tensor:
    homog = torch.cat([vertices, torch.ones_like(vertices[:, :1])], dim=1)
    return torch.einsum("bij,vj->bvi", world_to_clip.to(vertices), homog)


def random_scene(seed: int, n_vertices: int = 40, n_faces: int = 60, device: str | torch.device = "cpu"):
    """Random triangle soup in [-1, 1]^3 seen from random orbit cameras, one of them so close that
    some triangles lie behind it or cross the camera plane."""
    g = torch.Generator().manual_seed(seed)
    vertices = (torch.rand(n_vertices, 3, generator=g, dtype=torch.float64) * 2 - 1) * 0.9
    faces = torch.randint(0, n_vertices, (n_faces, 3), generator=g)
    faces[0, 2] = faces[0, 1]  # one degenerate (repeated-vertex) face
    elev = (torch.rand(3, generator=g) * 80 - 40).tolist()
    azim = (torch.rand(3, generator=g) * 360 - 180).tolist()
    cams = orbit(elev, azim, distance=[2.5, 3.0, 0.8]).to(dtype=torch.float64)
    return vertices.to(device), faces.to(device), cams.world_to_clip().to(device), cams


def brute_force_ids(clip: np.ndarray, faces: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Independent reference in NDC (float64): a face is drawn when all its w > near_w and its area is
    non-zero; a pixel centre is covered when it is on the inner side of all three edges (edges
    included) and its NDC depth is in [-1, 1]; the smallest depth wins, then the smallest id."""
    batch = clip.shape[0]
    ids = np.full((batch, height, width), -1, dtype=np.int64)
    best = np.full((batch, height, width), np.inf)
    xs = (2 * np.arange(width) + 1) / width - 1
    ys = 1 - (2 * np.arange(height) + 1) / height
    px, py = np.meshgrid(xs, ys)  # (H, W), row 0 at the top
    pixel_area = (2.0 / width) * (2.0 / height)
    for b in range(batch):
        for f, tri in enumerate(faces):
            c = clip[b, tri]
            if not (c[:, 3] > NEAR_W).all():
                continue
            x, y, z = c[:, 0] / c[:, 3], c[:, 1] / c[:, 3], c[:, 2] / c[:, 3]
            area = (x[1] - x[0]) * (y[2] - y[0]) - (y[1] - y[0]) * (x[2] - x[0])
            longest = max(((c[k, :2] / c[k, 3] - c[k - 1, :2] / c[k - 1, 3]) ** 2).sum() for k in range(3))
            if abs(area) <= max(MIN_AREA * pixel_area, DEGENERATE_REL * longest):
                continue
            lam = []
            for k in range(3):
                a, bb = (k + 1) % 3, (k + 2) % 3
                lam.append(((x[bb] - x[a]) * (py - y[a]) - (y[bb] - y[a]) * (px - x[a])) / area)
            lam = np.stack(lam)
            depth = (lam * z[:, None, None]).sum(0)
            inside = (lam >= 0).all(0) & (depth >= -1) & (depth <= 1)
            better = inside & (depth < best[b])  # equal depth keeps the earlier (smaller) id
            best[b][better] = depth[better]
            ids[b][better] = f
    return ids, best


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_triangle_ids_match_brute_force(seed: int, device: torch.device) -> None:
    vertices, faces, w2c, cams = random_scene(seed, device=device)
    clip = to_clip(vertices, w2c)
    height, width = 37, 45
    frags = rasterize(clip, faces, height, width)
    ref_ids, ref_ndc_depth = brute_force_ids(clip.cpu().numpy(), faces.cpu().numpy(), height, width)
    assert frags.face_id.shape == (3, height, width)
    assert (frags.face_id.cpu().numpy() == ref_ids).all()
    assert (ref_ids >= 0).sum() > 200, "the scene must cover a fair share of the pixels"
    # View depth from perspective-correct barycentrics equals the depth recovered from the NDC z
    # that is affine in screen space: z_ndc = a − b/w for the OpenGL projection.
    n, f = cams.near, cams.far
    a, b = (f + n) / (f - n), 2 * f * n / (f - n)
    covered = ref_ids >= 0
    expected = b / (a - ref_ndc_depth[covered])
    got = frags.depth.cpu().numpy()[covered]
    np.testing.assert_allclose(got, expected, rtol=1e-9)
    assert (frags.depth.cpu().numpy()[~covered] == 0).all()


def test_chunking_does_not_change_the_result(device: torch.device) -> None:
    vertices, faces, w2c, _ = random_scene(7, device=device)
    clip = to_clip(vertices, w2c)
    whole = rasterize(clip, faces, 40, 40)
    tiny = rasterize(clip, faces, 40, 40, RasterConfig(max_pairs_per_chunk=97))
    assert torch.equal(whole.face_id, tiny.face_id)
    assert torch.equal(whole.bary, tiny.bary)


def test_interpolated_positions_project_to_their_pixel_centres(device: torch.device) -> None:
    """Perspective correctness: the interpolated world point of every covered pixel lies on the ray
    through that pixel's centre (affine, non-perspective interpolation fails this)."""
    vertices, faces, w2c, _ = random_scene(11, device=device)
    clip = to_clip(vertices, w2c)
    frags = rasterize(clip, faces, 30, 34)
    points = interpolate(vertices, frags)  # (B, H, W, 3) world space
    reproj = to_clip(points.reshape(-1, 3), w2c)  # (B, B*H*W, 4): take each view's own pixels
    batch, h, w = frags.face_id.shape
    reproj = reproj.reshape(batch, batch, h, w, 4)[torch.arange(batch), torch.arange(batch)]
    ndc = reproj[..., :2] / reproj[..., 3:]
    cov = frags.face_id >= 0
    xs = (2 * torch.arange(w, device=device, dtype=ndc.dtype) + 1) / w - 1
    ys = 1 - (2 * torch.arange(h, device=device, dtype=ndc.dtype) + 1) / h
    assert torch.allclose(ndc[..., 0][cov], xs.expand(batch, h, w)[cov], atol=1e-9)
    assert torch.allclose(ndc[..., 1][cov], ys[:, None].expand(batch, h, w)[cov], atol=1e-9)
    bary = frags.bary
    assert torch.allclose(bary.sum(-1), torch.ones_like(bary[:, 0]))
    assert (bary > -1e-9).all()


def test_interpolation_gradients_match_finite_differences(device: torch.device) -> None:
    g = torch.Generator().manual_seed(5)
    vertices = (torch.rand(9, 3, generator=g, dtype=torch.float64) - 0.5) * 2.0
    faces = torch.arange(9).reshape(3, 3).to(device)
    w2c = orbit([10.0, -25.0], [20.0, 140.0]).to(dtype=torch.float64).world_to_clip().to(device)
    clip = to_clip(vertices.to(device), w2c).detach().requires_grad_(True)
    attrs = torch.rand(9, 2, generator=g, dtype=torch.float64).to(device).requires_grad_(True)
    weights = torch.rand(2, 14, 12, 2, generator=g, dtype=torch.float64).to(device)
    frags = rasterize(clip.detach(), faces, 14, 12)
    assert (frags.face_id >= 0).sum() > 20

    def loss(c: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        fr = rasterize(c, faces, 14, 12)
        assert torch.equal(fr.face_id, frags.face_id), "the perturbation must not change visibility"
        return (interpolate(a, fr) * weights).sum() + (fr.depth * weights[..., 0]).sum()

    # On CUDA the gathers' gradients add with atomics (morpheus_core/runtime/gather.py), in no fixed order.
    nondet = 1e-12 if clip.is_cuda else 0.0
    assert torch.autograd.gradcheck(loss, (clip, attrs), eps=1e-6, atol=1e-6, rtol=1e-5, nondet_tol=nondet)
    # Batched (B, V, C) attributes take the same path per view.
    a2 = attrs.detach().expand(2, -1, -1).clone().requires_grad_(True)
    assert torch.allclose(interpolate(a2, frags), interpolate(attrs.detach(), frags))


def icosphere(subdivisions: int, radius: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return torch.tensor(ico.vertices, dtype=torch.float64), torch.tensor(ico.faces, dtype=torch.int64)


def box() -> tuple[torch.Tensor, torch.Tensor]:
    b = trimesh.creation.box(extents=(0.9, 0.6, 0.75))
    return torch.tensor(b.vertices, dtype=torch.float64), torch.tensor(b.faces, dtype=torch.int64)


@pytest.mark.parametrize("shape", ["icosphere", "box"])
def test_silhouette_gradient_matches_finite_difference_of_hard_mask(shape: str, device: torch.device) -> None:
    """d(anti-aliased mask area)/d(global scale) vs the central difference of the hard pixel count."""
    vertices, faces = icosphere(4) if shape == "icosphere" else box()
    if shape == "icosphere":
        assert faces.shape[0] >= 5000
    vertices, faces = vertices.to(device=device, dtype=torch.float32), faces.to(device)
    w2c = orbit([20.0, -35.0], [30.0, 200.0]).world_to_clip().to(device)
    size = 192

    def area(scale: torch.Tensor, soft: bool) -> torch.Tensor:
        frags = rasterize(to_clip(vertices * scale, w2c), faces, size, size)
        return antialias(frags.mask, frags).sum() if soft else frags.mask.sum()

    scale = torch.tensor(1.0, device=device, requires_grad=True)
    area(scale, soft=True).backward()
    h = 0.03
    fd = (area(torch.tensor(1 + h, device=device), False) - area(torch.tensor(1 - h, device=device), False)) / (2 * h)
    assert fd > 1000  # a real silhouette with many pixels crossing it
    assert abs(scale.grad.item() - fd.item()) / fd.item() < 0.10


def test_antialiased_mask_is_hard_mask_away_from_the_silhouette(device: torch.device) -> None:
    vertices, faces = icosphere(3)
    vertices, faces = vertices.float().to(device), faces.to(device)
    w2c = orbit([15.0], [40.0]).world_to_clip().to(device)
    frags = rasterize(to_clip(vertices, w2c), faces, 64, 64)
    hard = frags.mask
    soft = antialias(hard, frags)
    assert ((soft >= 0) & (soft <= 1)).all()
    crossings = silhouette_crossings(frags)
    assert crossings.t.numel() > 50
    touched = torch.zeros(hard.numel(), dtype=torch.bool, device=device)
    touched[crossings.inner] = True
    touched[crossings.outer] = True
    changed = (soft != hard).reshape(-1)
    assert not (changed & ~touched).any()
    # Every crossing pairs a covered pixel with an empty direct neighbour.
    cov = hard.reshape(-1) > 0
    assert cov[crossings.inner].all() and not cov[crossings.outer].any()
    assert set((crossings.outer - crossings.inner).abs().unique().tolist()) <= {1, 64}


def test_edge_topology_of_a_closed_mesh() -> None:
    vertices, faces = icosphere(2)
    topo = mesh_topology(faces, vertices.shape[0])
    assert topo.edge_vertices.shape[0] == faces.shape[0] * 3 // 2  # closed manifold: E = 3F/2
    assert (topo.edge_faces >= 0).all() and not topo.nonmanifold.any() and (topo.edge_counts == 2).all()
    # Each edge's two faces really contain both end points.
    for k in range(2):
        tri = faces[topo.edge_faces[:, k]]
        assert ((tri == topo.edge_vertices[:, :1]).any(1) & (tri == topo.edge_vertices[:, 1:]).any(1)).all()
    open_topo = mesh_topology(faces[1:], vertices.shape[0])
    assert (open_topo.edge_faces[:, 1] < 0).sum() == 3 and (open_topo.edge_counts == 1).sum() == 3


def test_a_mesh_topology_gives_the_same_fragments_and_gradients(device: torch.device) -> None:
    """Rasterising through ``Mesh.topology`` (checked once, edges reused) equals the plain-faces path:
    ids, barycentrics, anti-aliased mask and the vertex gradient through the silhouette."""
    g = torch.Generator().manual_seed(11)
    vertices, faces = icosphere(3)
    vertices = (vertices * (1 + 0.2 * torch.rand(vertices.shape[0], 1, generator=g, dtype=torch.float64))).float()
    mesh = Mesh(vertices.to(device), faces.to(device))
    w2c = orbit([25.0, -10.0], [70.0, 250.0]).world_to_clip().to(device)
    outs = []
    for faces_in in (mesh.faces, mesh.topology):
        v = mesh.vertices.clone().requires_grad_(True)
        frags = rasterize(to_clip(v, w2c), faces_in, 48, 48)
        soft = antialias(frags.mask, frags)
        weight = torch.rand(soft.shape, generator=g.manual_seed(5)).to(device)
        (grad,) = torch.autograd.grad((soft * weight).sum(), v)
        outs.append((frags, soft, grad))
    (a, soft_a, grad_a), (b, soft_b, grad_b) = outs
    assert torch.equal(a.face_id, b.face_id) and torch.equal(a.bary, b.bary)
    assert torch.equal(soft_a, soft_b) and torch.equal(grad_a, grad_b) and grad_a.abs().sum() > 0
    assert b.edges is mesh.topology


def test_a_stale_or_foreign_topology_is_refused() -> None:
    vertices, faces = icosphere(1)
    mesh = Mesh(vertices.float(), faces.clone())
    topo = mesh.topology
    clip = to_clip(mesh.vertices, orbit([10.0], [20.0]).world_to_clip())
    with pytest.raises(RasterInputError, match="for 42 vertices"):
        rasterize(clip[:, :-1], topo, 16, 16)
    mesh.faces[0] = mesh.faces[0].flip(0)  # in place: the cached topology no longer describes the faces
    with pytest.raises(RasterInputError, match="changed in place"):
        rasterize(clip, topo, 16, 16)
    assert mesh.topology is not topo and mesh.topology.is_current()  # the mesh rebuilds its own
    rasterize(clip, mesh.topology, 16, 16)


def test_back_face_culling() -> None:
    vertices, faces = icosphere(3)
    w2c = orbit([5.0], [60.0]).world_to_clip().to(torch.float64)
    clip = to_clip(vertices, w2c)
    both = rasterize(clip, faces, 48, 48)
    culled = rasterize(clip, faces, 48, 48, RasterConfig(cull_backfaces=True))
    assert torch.equal(both.face_id, culled.face_id)  # closed convex mesh: front faces win anyway
    flipped = rasterize(clip, faces.flip(1), 48, 48, RasterConfig(cull_backfaces=True))
    # With the winding flipped, only the far half of the sphere is drawn: every pixel is deeper.
    cov = both.face_id >= 0
    assert torch.equal(flipped.face_id >= 0, cov)
    assert (flipped.depth[cov] > both.depth[cov]).all()


def test_near_plane_degenerate_and_empty_inputs_are_safe(device: torch.device) -> None:
    clip = torch.tensor([[-0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, 1.0], [0.0, 0.5, 0.0, 1.0],   # normal
                         [-0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, -1.0], [0.0, 0.9, 0.0, 1.0],  # crosses w = 0
                         [0.2, 0.2, 0.0, 1.0], [0.4, 0.4, 0.0, 1.0], [0.6, 0.6, 0.0, 1.0],      # collinear
                         [0.1, 0.1, 0.0, 0.0], [0.4, 0.1, 0.0, 0.0], [0.1, 0.4, 0.0, 0.0],      # all at w = 0
                         [0.3, 0.3, 0.0, float("nan")], [0.9, 0.3, 0.0, 1.0], [0.3, 0.9, 0.0, 1.0]],
                        device=device, requires_grad=True)
    faces = torch.arange(15, device=device).reshape(5, 3)
    frags = rasterize(clip, faces, 32, 32)
    assert set(frags.face_id.unique().tolist()) == {-1, 0}
    assert frags.orientation.tolist() == [[1, 0, 0, 0, 0]]
    colours = torch.rand(15, 3, generator=torch.Generator().manual_seed(0)).to(device)
    out = antialias(torch.cat([interpolate(colours, frags), frags.mask], -1), frags)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(clip.grad).all()
    assert clip.grad[:3].abs().sum() > 0 and (clip.grad[3:] == 0).all()

    empty = rasterize(clip[:3], torch.zeros(0, 3, dtype=torch.int64, device=device), 8, 8)
    assert (empty.face_id == -1).all() and empty.bary.shape == (0, 3)
    assert antialias(empty.mask, empty).sum() == 0


def test_half_precision_clip_is_rasterised_in_float32(device: torch.device) -> None:
    vertices, faces = icosphere(2)
    w2c = orbit([10.0], [10.0]).world_to_clip()
    clip32 = to_clip(vertices.float(), w2c)
    ref = rasterize(clip32, faces, 40, 40)
    for dtype in (torch.float16, torch.bfloat16):
        frags = rasterize(clip32.to(dtype).to(device), faces.to(device), 40, 40)
        assert frags.bary.dtype == torch.float32 and torch.isfinite(frags.bary).all()
        agree = (frags.face_id.cpu() >= 0) == (ref.face_id >= 0)
        assert agree.float().mean() > 0.97  # the half-precision vertices moved slightly


def test_bad_inputs_raise_typed_errors() -> None:
    clip = torch.rand(5, 4)
    faces = torch.tensor([[0, 1, 2]])
    with pytest.raises(RasterInputError, match="int64"):
        rasterize(clip, faces.int(), 8, 8)
    with pytest.raises(RasterInputError, match="face indices"):
        rasterize(clip, torch.tensor([[0, 1, 5]]), 8, 8)
    with pytest.raises(RasterInputError, match=r"\(B, V, 4\)"):
        rasterize(torch.rand(5, 3), faces, 8, 8)
    with pytest.raises(RasterInputError, match="image size"):
        rasterize(clip, faces, 0, 8)
    frags = rasterize(clip, faces, 8, 8)
    with pytest.raises(RasterInputError, match="attributes"):
        interpolate(torch.rand(4, 3), frags)
    with pytest.raises(RasterInputError, match="image must be"):
        antialias(torch.rand(1, 8, 9, 1), frags)
    with pytest.raises(ValueError, match="max_pairs_per_chunk"):
        RasterConfig(max_pairs_per_chunk=0)
