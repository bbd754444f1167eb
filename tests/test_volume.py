"""Volume renderer against analytic densities; stability at extreme densities; occupancy skipping."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from morpheus_core.cameras import orbit, reference_camera, sample_orbit
from morpheus_core.geometry.nerf import FieldSample, NerfField
from morpheus_core.render.volume import (
    OccupancyGrid,
    OccupancyGridConfig,
    SampleBudget,
    VolumeRenderConfig,
    ray_box,
    render_silhouette,
    render_volume,
)
from tests.nerf_fields import occupancy_grid_for, small_nerf
from tests.seeds import fresh_seed


class ConstantSphere:
    """Density ``sigma`` (a learnable scale) inside a ball of ``radius``, colour by octant."""

    bbox_radius = 1.0

    def __init__(self, sigma: float, radius: float = 0.5) -> None:
        self.log_sigma = torch.tensor(float(torch.log(torch.tensor(sigma, dtype=torch.float64))),
                                      dtype=torch.float64, requires_grad=True)
        self.radius = radius

    def density(self, points: Tensor) -> Tensor:
        inside = (points.norm(dim=-1) < self.radius).to(points.dtype)
        return inside * torch.exp(self.log_sigma).to(points.dtype)

    def query(self, points: Tensor, with_normals: bool) -> FieldSample:
        albedo = (points > 0).to(points.dtype) * 0.8 + 0.1
        normal = points / points.norm(dim=-1, keepdim=True).clamp_min(1e-9) if with_normals else None
        return FieldSample(self.density(points), albedo, normal)


def impact_parameter(cams, h: int, w: int) -> Tensor:
    origins, dirs = cams.rays(h, w)
    return torch.linalg.cross(origins, dirs, dim=-1).norm(dim=-1)


@pytest.mark.parametrize("sigma", [2.0, 8.0])
def test_sphere_opacity_profile_is_analytic(sigma: float, device: torch.device) -> None:
    cams = orbit([0.0, 30.0], [0.0, 120.0]).to(device, torch.float64)
    field = ConstantSphere(sigma)
    out = render_volume(field, cams, 48, 48, VolumeRenderConfig(n_samples=512, stratified=False, with_normals=False))
    b = impact_parameter(cams, 48, 48)
    chord = 2 * torch.sqrt((0.5**2 - b**2).clamp_min(0))
    expected = 1 - torch.exp(-sigma * chord)
    err = (out.opacity.squeeze(-1) - expected).abs()
    # Discretisation shifts the entry/exit points by at most one bin (≈ 0.007 here).
    assert err.mean() < 5e-3 and err.max() < sigma * 0.01
    # Off the sphere the render is exactly the white background.
    miss = b > 0.52
    assert torch.all(out.opacity.squeeze(-1)[miss] == 0) and torch.all(out.rgb[miss] == 1)


def test_transmittance_and_outputs_stay_bounded_for_random_densities(device: torch.device) -> None:
    class Wild(ConstantSphere):
        def density(self, points: Tensor) -> Tensor:
            g = torch.sin(points @ torch.tensor([13.0, 7.0, 5.0], dtype=points.dtype, device=points.device))
            return torch.exp(12 * g) * torch.exp(self.log_sigma).to(points.dtype)

    cams = sample_orbit(2, generator=torch.Generator().manual_seed(0)).to(device)
    out = render_volume(Wild(1.0), cams, 16, 16, VolumeRenderConfig(n_samples=64),
                        generator=torch.Generator().manual_seed(1))
    assert out.opacity.min() >= 0 and out.opacity.max() <= 1
    assert out.rgb.min() >= 0 and out.rgb.max() <= 1 + 1e-6
    assert torch.isfinite(out.depth).all() and torch.isfinite(out.normal).all()


@pytest.mark.parametrize("sigma", [1e-8, 1e8])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_densities_give_finite_values_and_gradients(sigma: float, dtype: torch.dtype,
                                                            device: torch.device) -> None:
    field = ConstantSphere(sigma)
    cams = reference_camera().to(device, dtype)
    out = render_volume(field, cams, 16, 16, VolumeRenderConfig(n_samples=64), background=0.5,
                        generator=torch.Generator().manual_seed(2))
    loss = out.rgb.sum() + out.opacity.sum() + out.depth.sum() + out.normal.sum()
    loss.backward()
    assert all(torch.isfinite(t).all() for t in (out.rgb, out.opacity, out.depth, out.normal))
    assert torch.isfinite(field.log_sigma.grad)
    expected = 0.0 if sigma < 1 else 1.0
    centre = out.opacity[0, 8, 8, 0].item()
    assert abs(centre - expected) < 1e-4


def test_ray_box_entry_exit_and_misses() -> None:
    o = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.0, 0.0, 0.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    near, far, hit = ray_box(o, d, 1.0)
    assert hit.tolist() == [True, False, True]
    torch.testing.assert_close(near[[0, 2]], torch.tensor([2.0, 0.0]))
    torch.testing.assert_close(far[[0, 2]], torch.tensor([4.0, 1.0]))


def test_occupancy_grid_skips_empty_space_without_changing_the_render(device: torch.device) -> None:
    field = small_nerf().to(device)
    cams = sample_orbit(2, generator=torch.Generator().manual_seed(3)).to(device)
    config = VolumeRenderConfig(n_samples=64, stratified=False)
    grid_cfg = OccupancyGridConfig(resolution=32, update_every=4, density_threshold=1e-3)
    grid = OccupancyGrid(grid_cfg, field.bbox_radius).to(device)
    assert grid.occupied_fraction == 1.0  # nothing is hidden before the first refresh
    assert not grid.maybe_refresh(field, step=3)
    assert grid.maybe_refresh(field, step=4, generator=torch.Generator().manual_seed(4))
    assert 0.05 < grid.occupied_fraction < 0.5  # the blob fills a ball of radius ≈ 0.73 of the box
    full = render_volume(field, cams, 24, 24, config)
    skipped = render_volume(field, cams, 24, 24, config, occupancy=grid)
    assert (full.rgb - skipped.rgb).abs().max() < 1e-2
    assert (full.opacity - skipped.opacity).abs().mean() < 1e-3


@pytest.mark.parametrize("seed", [0, fresh_seed()])
def test_silhouette_render_matches_the_volume_render_opacity(seed: int, device: torch.device) -> None:
    g = torch.Generator().manual_seed(seed)
    field = small_nerf(seed).to(device)
    cams = sample_orbit(2, generator=g).to(device)
    samples, segment = int(torch.randint(8, 64, (1,), generator=g)), int(torch.randint(1, 20, (1,), generator=g))
    level = float(torch.rand(1, generator=g)) * 0.8 + 0.1
    grid = OccupancyGrid(OccupancyGridConfig(resolution=16, density_threshold=1e-3), field.bbox_radius).to(device)
    grid.refresh(field, g)
    for occupancy in (None, grid):
        opacity = render_volume(field, cams, 24, 24, VolumeRenderConfig(n_samples=samples, stratified=False,
                                                                         with_normals=False), occupancy=occupancy)
        want = opacity.opacity[..., 0] > level
        got = render_silhouette(field, cams, 24, 24, samples, occupancy, level, segment)
        # Summation order differs (per segment vs one cumsum): a pixel exactly at the level may flip.
        near_level = (opacity.opacity[..., 0] - level).abs() < 1e-5
        assert got.shape == want.shape and bool((got == want)[~near_level].all()), f"seed {seed}"
        assert 0 < int(want.sum()) < want.numel(), f"seed {seed}: the test field should be partly opaque"


def test_occupancy_grid_decays_towards_new_densities() -> None:
    field = ConstantSphere(5.0)
    grid = OccupancyGrid(OccupancyGridConfig(resolution=8, decay=0.5, density_threshold=1.0), 1.0)
    grid.refresh(field, torch.Generator().manual_seed(0))
    before = grid.occupied_fraction
    with torch.no_grad():
        field.log_sigma.fill_(-10.0)
    grid.refresh(field, torch.Generator().manual_seed(1))  # 5 → 2.5: still above 1
    assert grid.occupied_fraction == before
    grid.refresh(field, torch.Generator().manual_seed(2))  # 1.25
    grid.refresh(field, torch.Generator().manual_seed(3))  # 0.625: now empty
    assert before > 0 and grid.occupied_fraction == 0.0


def test_nerf_render_backpropagates_to_grid_and_mlps(device: torch.device) -> None:
    field = small_nerf(1).to(device)
    cams = sample_orbit(2, generator=torch.Generator().manual_seed(5)).to(device)
    out = render_volume(field, cams, 12, 12, VolumeRenderConfig(n_samples=32), background=torch.tensor([0.2, 0.3, 0.4]),
                        generator=torch.Generator().manual_seed(6))
    target = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(7)).to(device)
    ((out.rgb - target) ** 2).mean().add(out.normal.square().mean()).backward()
    grads = [p.grad for p in field.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert field.encoding.table.grad.abs().sum() > 0
    assert out.depth[out.opacity > 0.5].min() > 1.0  # surface in front of the origin, behind the near plane


def test_normals_only_at_visible_samples_match_normals_everywhere(device: torch.device) -> None:
    """Skipping normals where a sample's compositing weight is < 1e-4 changes the rendered normal
    by at most the skipped weight mass, and the normal-smoothness gradient stays essentially the same."""
    field = small_nerf(3).to(device)
    cams = sample_orbit(2, generator=torch.Generator().manual_seed(4)).to(device)
    outs = {}
    for threshold in (0.0, 1e-4):
        cfg = VolumeRenderConfig(n_samples=96, stratified=False, with_normals=True, normal_weight_threshold=threshold)
        field.zero_grad()
        out = render_volume(field, cams, 24, 24, cfg)
        out.normal.square().sum().backward()
        grad = field.encoding.table.grad.clone()
        outs[threshold] = (out.normal.detach(), grad, out.rgb.detach())
    (n_all, g_all, rgb_all), (n_vis, g_vis, rgb_vis) = outs[0.0], outs[1e-4]
    assert torch.equal(rgb_all, rgb_vis)  # colour and opacity do not depend on the normals
    assert (n_all - n_vis).abs().max() < 96 * 1e-4 + 1e-6
    assert n_all.abs().max() > 0.1  # the test renders real surfaces, not empty space
    assert torch.nn.functional.cosine_similarity(g_all.flatten(), g_vis.flatten(), dim=0) > 0.99


def test_training_renders_skip_samples_behind_opaque_surfaces(device: torch.device,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """With the option on, training renders skip samples whose transmittance is below 1e-4: the render
    and the gradients match rendering every sample, and far fewer samples reach the field."""
    from morpheus_core.render import volume

    field = small_nerf(5).to(device)
    cams = sample_orbit(2, generator=torch.Generator().manual_seed(6)).to(device)
    counts: list[int] = []
    real_query = volume._query

    def counting(field_, points, keep, *args, **kwargs):
        if not kwargs.get("density_only"):
            counts.append(int(keep.sum()))
        return real_query(field_, points, keep, *args, **kwargs)

    monkeypatch.setattr(volume, "_query", counting)
    grid = OccupancyGrid(OccupancyGridConfig(resolution=32, density_threshold=1e-3), field.bbox_radius).to(device)
    grid.refresh(field, torch.Generator().manual_seed(8))
    results = {}
    for threshold in (0.0, 1e-4):
        cfg = VolumeRenderConfig(n_samples=96, stratified=False, with_normals=False, transmittance_threshold=threshold)
        field.zero_grad()
        out = render_volume(field, cams, 24, 24, cfg, occupancy=grid)
        weights = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(7)).to(device)
        ((out.rgb * weights).sum() + out.opacity.sum()).backward()
        results[threshold] = (out.rgb.detach(), out.opacity.detach(), field.encoding.table.grad.clone(),
                              field.density_mlp[0].weight.grad.clone())
    full, culled = results[0.0], results[1e-4]
    assert counts[1] < 0.95 * counts[0], counts  # samples behind the opaque core are skipped
    assert (full[0] - culled[0]).abs().max() < 1e-3 and (full[1] - culled[1]).abs().max() < 1e-3
    for a, b in zip(full[2:], culled[2:], strict=True):
        assert torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0) > 0.999


def _render_and_grads(field: NerfField, cams, grid: OccupancyGrid, budget: SampleBudget | None, seed: int):
    cfg = VolumeRenderConfig(n_samples=40, with_normals=True, normal_weight_threshold=1e-4)
    field.zero_grad()
    out = render_volume(field, cams, 16, 16, cfg, occupancy=grid, generator=torch.Generator().manual_seed(seed),
                        budget=budget)
    target = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(seed + 1)).to(out.rgb.device)
    ((out.rgb - target) ** 2).mean().add(out.normal.square().mean()).backward()
    return out, [p.grad.clone() for p in field.parameters()]


@pytest.mark.parametrize("seed", [0, fresh_seed()])
def test_padded_sample_buffers_render_and_backpropagate_like_the_exact_gather(seed: int,
                                                                              device: torch.device) -> None:
    field = small_nerf(seed % 1000).to(device)
    cams = sample_orbit(2, generator=torch.Generator().manual_seed(seed)).to(device)
    grid = occupancy_grid_for(field, device, seed)
    exact, exact_grads = _render_and_grads(field, cams, grid, None, seed)
    budget = SampleBudget(headroom=1.0, quantum=64)
    _render_and_grads(field, cams, grid, budget, seed)  # the first render sizes the buffers from its counts
    assert set(budget.adapt()) == {"render", "render/normals"}
    assert budget.capacity["render"] < 2 * 16 * 16 * 40  # sized from what the grid keeps, not the box
    padded, padded_grads = _render_and_grads(field, cams, grid, budget, seed)
    assert int(budget.dropped()) == 0
    for name in ("rgb", "opacity", "depth", "normal"):
        torch.testing.assert_close(getattr(padded, name), getattr(exact, name), rtol=1e-5, atol=1e-6)
    for a, b in zip(padded_grads, exact_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)


def test_a_full_sample_buffer_drops_the_deepest_samples_and_counts_them() -> None:
    g = torch.Generator().manual_seed(fresh_seed())
    keep = torch.rand(37, 11, generator=g) < 0.6
    count = int(keep.sum())
    budget = SampleBudget(headroom=1.0, quantum=1, hold=(1.0, 1.0))
    budget.capacity["k"] = cap = count - 5
    index, counted = budget.gather("k", keep)
    assert int(counted) == count and index.shape == (cap,)
    # the first ``cap`` kept samples in sample order (all rays' sample 0, then sample 1, …)
    rays, samples = keep.t().nonzero(as_tuple=True)
    expected = (samples * 11 + rays)[:cap]
    assert torch.equal(index, expected)
    assert int(budget.dropped()) == 5
    budget.capacity["k"] = count + 3  # room to spare: every kept sample, then padding
    index, _ = budget.gather("k", keep)
    assert torch.equal(index[:count], (samples * 11 + rays)) and bool((index[count:] == keep.numel()).all())
    assert budget.adapt() == {"k": 5}
    assert budget.capacity["k"] == count and budget.dropped() is None  # peak × headroom 1, quantum 1


def test_sample_budget_rounds_capacity_up_and_rejects_nonsense() -> None:
    budget = SampleBudget(headroom=1.25, quantum=100)
    budget.gather("k", torch.ones(10, 33, dtype=torch.bool))
    budget.adapt()
    assert budget.capacity["k"] == 500  # 330 · 1.25 = 412.5 → 500
    with pytest.raises(ValueError, match="headroom"):
        SampleBudget(headroom=0.5)
    with pytest.raises(ValueError, match="hold"):
        SampleBudget(hold=(0.5, 0.9))
    with pytest.raises(ValueError, match="sample_buffer"):
        VolumeRenderConfig(sample_buffer="fast")  # type: ignore[arg-type]


def test_a_sample_buffer_keeps_its_size_while_the_peak_drifts_within_hold() -> None:
    """Every new size is a new CUDA graph under ``graphed``: small drifts must not resize."""
    budget = SampleBudget(headroom=1.25, quantum=10, hold=(0.75, 1.125))
    rays = 100

    def peak(count: int) -> int:
        keep = torch.zeros(rays, 20, dtype=torch.bool)
        keep.view(-1)[torch.randperm(keep.numel())[:count]] = True
        budget.gather("k", keep)
        budget.adapt()
        return budget.capacity["k"]

    first = peak(800)  # 800 · 1.25 = 1000: sized for a peak of 800
    assert first == 1000
    drift = [peak(c) for c in (620, 700, 880, 900)]  # within [0.75, 1.125] · 800 = [600, 900]
    assert drift == [1000] * 4 and budget.resizes == 0
    assert peak(950) == 1190 and budget.resizes == 1  # 950 · 1.25 = 1187.5 → 1190
    assert peak(400) == 500 and budget.resizes == 2  # far below: shrink


def test_auto_sample_buffers_are_graphed_alone_on_cuda_and_exact_otherwise_and_graphed_needs_cuda() -> None:
    assert VolumeRenderConfig().sample_buffer_on(torch.device("cuda")) == "graphed"
    assert VolumeRenderConfig().sample_buffer_on(torch.device("cuda"), alone=False) == "exact"  # in a batch
    assert VolumeRenderConfig().sample_buffer_on(torch.device("cpu")) == "exact"
    assert VolumeRenderConfig(sample_buffer="padded").sample_buffer_on(torch.device("cuda")) == "padded"
    with pytest.raises(ValueError, match=r"graphed.*needs a CUDA device"):
        VolumeRenderConfig(sample_buffer="graphed").sample_buffer_on(torch.device("cpu"))


def test_graphed_sample_buffers_refuse_a_field_whose_parameters_they_cannot_see() -> None:
    budget = SampleBudget(graphed=True)
    with pytest.raises(TypeError, match=r"nn\.Module"):
        budget.evaluator("render", ConstantSphere(1.0), False, 1024)


@pytest.mark.parametrize("seed", [1, fresh_seed()])
def test_no_grad_renders_in_ray_chunks_equal_one_pass_and_stay_bounded(seed: int, device: torch.device,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Evaluation and previews render in ``chunk_rays`` slices (bounded memory) with the same jitter and
    the same pixels as one pass; a training render (with gradients) still takes one pass."""
    import morpheus_core.render.volume as volume

    g = torch.Generator().manual_seed(seed)
    field = small_nerf(seed).to(device)
    cams = sample_orbit(3, generator=g).to(device)
    grid = OccupancyGrid(OccupancyGridConfig(resolution=16, density_threshold=1e-3), field.bbox_radius).to(device)
    grid.refresh(field, g)
    chunk = int(torch.randint(50, 400, (1,), generator=g))
    passes: list[int] = []
    real = volume._composite
    monkeypatch.setattr(volume, "_composite", lambda q, keep, *a: passes.append(keep.shape[0]) or real(q, keep, *a))
    renders = []
    for rays in (10**9, chunk):
        config = VolumeRenderConfig(n_samples=24, with_normals=True, normal_weight_threshold=0.0, chunk_rays=rays)
        with torch.no_grad():
            renders.append(render_volume(field, cams, 20, 18, config, 1.0, grid, torch.Generator().manual_seed(7)))
    whole, sliced = renders
    assert passes[0] == 3 * 20 * 18 and len(passes) == 1 + -(-3 * 20 * 18 // chunk) and max(passes[1:]) <= chunk
    for name in ("rgb", "opacity", "depth", "normal"):
        torch.testing.assert_close(getattr(sliced, name), getattr(whole, name), rtol=1e-5, atol=1e-6)
    assert 0 < float(whole.opacity.mean()) < 1
    passes.clear()
    config = VolumeRenderConfig(n_samples=24, with_normals=False, chunk_rays=chunk)
    trained = render_volume(field, cams, 20, 18, config, 1.0, grid, torch.Generator().manual_seed(7))
    assert passes == [3 * 20 * 18] and trained.rgb.requires_grad
    with pytest.raises(ValueError, match="chunk_rays"):
        VolumeRenderConfig(chunk_rays=0)
