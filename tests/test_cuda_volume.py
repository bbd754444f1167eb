"""The NeRF stage's field queries replayed from CUDA graphs (``sample_buffer=graphed``) against the
same padded buffers evaluated eagerly (skipped where no GPU is present, as in CI)."""

from __future__ import annotations

import pytest
import torch

from morpheus_core.cameras import sample_orbit
from morpheus_core.render.volume import SampleBudget, VolumeRenderConfig, render_volume
from morpheus_core.runtime.cuda_graphs import GraphedCall
from tests.nerf_fields import occupancy_grid_for, small_nerf
from tests.seeds import fresh_seed

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]

CFG = VolumeRenderConfig(n_samples=48, with_normals=True, normal_weight_threshold=1e-4)


def _steps(graphed: bool, seed: int, steps: int, resize_at: int | None = None):
    """``steps`` Adam steps of a small field on padded buffers; per step the render and the gradients."""
    dev = torch.device("cuda")
    field = small_nerf(seed % 1000).to(dev)
    grid = occupancy_grid_for(field, dev, seed)
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    budget = SampleBudget(headroom=1.25, quantum=256, graphed=graphed)
    out = []
    for step in range(steps):
        if step == resize_at:  # as after an occupancy refresh that changed what the grid keeps
            budget.capacity = {k: v + 512 for k, v in budget.capacity.items()}
        cams = sample_orbit(2, generator=torch.Generator().manual_seed(seed + step)).to(dev)
        opt.zero_grad(set_to_none=True)
        ref = render_volume(field, cams[:1], 16, 16, CFG, occupancy=grid, budget=budget, budget_key="reference",
                            generator=torch.Generator().manual_seed(seed + 100 + step))
        novel = render_volume(field, cams[1:], 16, 16, CFG, occupancy=grid, budget=budget, budget_key="novel",
                              generator=torch.Generator().manual_seed(seed + 200 + step))
        target = torch.rand(ref.rgb.shape, generator=torch.Generator().manual_seed(seed + 1)).to(dev)
        loss = (ref.rgb - target).square().mean() + novel.rgb.mean() + novel.normal.square().mean()
        loss.backward()
        out.append(([ref.rgb.detach(), novel.rgb.detach(), novel.normal.detach(), novel.opacity.detach()],
                    [p.grad.clone() for p in field.parameters()]))
        opt.step()
    return out, budget


@pytest.mark.parametrize("seed", [0, fresh_seed()])
def test_graphed_field_queries_render_and_backpropagate_like_eager_ones_through_adam_steps(seed: int) -> None:
    eager, _ = _steps(False, seed, 4)
    before = GraphedCall.captures
    graphed, budget = _steps(True, seed, 4)
    # one graph per buffer (reference, novel and their normals), captured on first use only
    assert GraphedCall.captures - before == 4 and budget.graphed
    for (images_e, grads_e), (images_g, grads_g) in zip(eager, graphed, strict=True):
        for a, b in zip(images_g, images_e, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
        for a, b in zip(grads_g, grads_e, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)


def test_a_resized_buffer_is_captured_again_and_still_matches_eager() -> None:
    seed = fresh_seed()
    eager, _ = _steps(False, seed, 3, resize_at=2)
    before = GraphedCall.captures
    graphed, _ = _steps(True, seed, 3, resize_at=2)
    assert GraphedCall.captures - before == 8  # four buffers, two sizes each
    for (images_e, grads_e), (images_g, grads_g) in zip(eager, graphed, strict=True):
        for a, b in zip(images_g + grads_g, images_e + grads_e, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)



def test_the_nerf_stage_graphs_its_field_alone_and_not_in_a_batch(tmp_path) -> None:
    """``sample_buffer=auto`` on CUDA: a photo optimised alone gets graphed buffers (its manifest
    counts their resizes), photos in a batch the exact gather."""
    from assets_store.store import Store
    from ops.pipeline.runner import Pipeline, stages_until
    from tests.pipeline_helpers import PHOTOS, manifest, tiny_config

    cfg = tiny_config("device=cuda", "nerf.occupancy.update_every=3", nerf=8)
    before = GraphedCall.captures
    alone = Store(tmp_path / "alone")
    assert Pipeline(alone, cfg, "tiny").run([(PHOTOS / "mug.jpg", "mug.jpg")], stages_until("nerf"))[0].error is None
    assert "sample_buffer_resizes" in manifest(alone, "mug.jpg", "nerf").metrics
    assert GraphedCall.captures > before
    batched = Store(tmp_path / "batched")
    photos = [(PHOTOS / name, name) for name in ("mug.jpg", "bottle.jpg")]
    outcomes = Pipeline(batched, cfg, "tiny").run(photos, stages_until("nerf"))
    assert all(o.error is None for o in outcomes)
    assert all("sample_buffer_resizes" not in manifest(batched, key, "nerf").metrics for _, key in photos)
