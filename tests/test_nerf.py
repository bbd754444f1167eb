"""NeRF field: blob initialisation, trunc_exp, central-difference normals."""

from __future__ import annotations

import pytest
import torch

from morpheus_core.geometry.hashgrid import HashGridConfig
from morpheus_core.geometry.nerf import NerfConfig, NerfField, central_difference_normals, trunc_exp


def test_trunc_exp_forward_is_exp_and_backward_is_clamped() -> None:
    x = torch.tensor([-3.0, 0.0, 2.0, 20.0, 200.0], requires_grad=True)
    y = trunc_exp(x)
    torch.testing.assert_close(y[:4], torch.exp(x[:4].detach()))
    assert torch.isfinite(y).all()  # exp(200) would overflow float32
    y.sum().backward()
    torch.testing.assert_close(x.grad[:3], torch.exp(x[:3].detach()))
    torch.testing.assert_close(x.grad[3:], torch.full((2,), float(torch.exp(torch.tensor(15.0)))))


def test_blob_init_is_dense_at_the_centre_and_empty_at_the_corners(device: torch.device) -> None:
    grid = HashGridConfig(n_levels=4, log2_table_size=12, base_resolution=8, per_level_scale=1.6)
    field = NerfField(NerfConfig(grid=grid, hidden=16), generator=torch.Generator().manual_seed(0)).to(device)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.9, 0.9, 0.9], [-0.95, 0.9, -0.9]], device=device)
    sigma = field.density(pts)
    assert sigma[0] > 1000 and (sigma[1:] < 1e-3).all()
    sample = field.query(pts, with_normals=True)
    assert sample.albedo.min() > 0 and sample.albedo.max() < 1
    assert torch.isfinite(sample.normal).all()


def test_normals_of_a_radial_density_point_outwards(device: torch.device) -> None:
    gen = torch.Generator().manual_seed(1)
    pts = (torch.rand(64, 3, generator=gen, dtype=torch.float64) * 2 - 1).to(device) * 0.6
    normals = central_difference_normals(lambda p: torch.exp(-4 * p.square().sum(-1)), pts, eps=1e-4)
    radial = pts / pts.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(normals, radial, atol=1e-6, rtol=0)
    flat = central_difference_normals(lambda p: torch.zeros(p.shape[0], dtype=p.dtype), pts.cpu(), eps=1e-3)
    assert torch.all(flat == 0)  # empty space: a zero normal, not NaN


def test_progressive_levels_follow_the_step() -> None:
    field = NerfField(NerfConfig(), generator=torch.Generator().manual_seed(2))
    assert field.encoding.active_levels == 8
    field.update_step(3000)
    assert field.encoding.active_levels == 10


def test_the_nerf_stage_on_padded_sample_buffers_logs_drops_and_matches_the_exact_gather(tmp_path) -> None:
    """``sample_buffer=padded``: the stage runs, its run log counts
    the samples a full buffer dropped, and with none dropped it learns what the exact gather learns."""
    from assets_store.runlog import read_runlog
    from assets_store.store import Store
    from ops.pipeline.runner import Pipeline, stages_until
    from tests.pipeline_helpers import PHOTOS, tiny_config

    logs = {}
    for mode in ("exact", "padded"):
        cfg = tiny_config(f"nerf.render.sample_buffer={mode}", "nerf.occupancy.update_every=3", nerf=10)
        store = Store(tmp_path / mode)
        out = Pipeline(store, cfg, "tiny").run([(PHOTOS / "mug.jpg", "mug.jpg")], stages_until("nerf"))[0]
        assert out.error is None, out.error
        logs[mode] = read_runlog(store.stage_dir("mug.jpg", "nerf") / "runlog.parquet")
    dropped = [r["samples_dropped"] for r in logs["padded"]]
    assert all(d is not None and d >= 0 for d in dropped) and "samples_dropped" not in logs["exact"][0]
    if dropped[-1] == 0:
        for a, b in zip(logs["exact"], logs["padded"], strict=True):
            assert abs(a["ref_psnr"] - b["ref_psnr"]) < 1e-3


def test_graphed_sample_buffers_on_the_cpu_fail_at_the_stage_start_and_name_the_fix(tmp_path) -> None:
    from assets_store.store import Store
    from ops.pipeline.runner import Pipeline, stages_until
    from tests.pipeline_helpers import PHOTOS, tiny_config

    if tiny_config().device != "cpu":
        pytest.skip("a CPU-only failure")
    store = Store(tmp_path)
    pipeline = Pipeline(store, tiny_config("nerf.render.sample_buffer=graphed"), "tiny")
    out = pipeline.run([(PHOTOS / "mug.jpg", "mug.jpg")], stages_until("nerf"))[0]
    assert out.error is not None and "needs a CUDA device" in out.error and "auto, exact or padded" in out.error
    assert store.read_manifest("mug.jpg", "nerf") is None  # nothing finished was written
