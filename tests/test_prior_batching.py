"""One batch mixing objects equals one call per object (each with its own reference and camera)."""

from __future__ import annotations

import torch

from morpheus_core.priors.image2d import Image2DCondition
from morpheus_core.priors.lora import ObjectLoras
from morpheus_core.priors.zero123 import Camera, Zero123Condition
from tests.helpers import photo

IDS = ["x", "y", "z"]


def _split(cond, i: int):
    if isinstance(cond, Zero123Condition):
        return Zero123Condition((cond.object_ids[i],), cond.elevation_deg[i: i + 1], cond.azimuth_deg[i: i + 1],
                                cond.radius[i: i + 1])
    return Image2DCondition((cond.object_ids[i],), cond.control[i: i + 1])


def _assert_batched_equals_singles(prior, zt, t, cond, cfg) -> None:
    batched = prior.predict_noise(zt, t, cond, cfg)
    singles = torch.cat([prior.predict_noise(zt[i: i + 1], t[i: i + 1], _split(cond, i), cfg) for i in range(3)])
    assert torch.isfinite(batched).all()
    assert torch.allclose(batched, singles, atol=2e-5, rtol=1e-4), (batched - singles).abs().max()


def test_zero123_batch_of_three_objects(zero123) -> None:
    for i, oid in enumerate(IDS):
        zero123.set_reference(f"b3{oid}", photo(30 + i), Camera(5.0 * i, -10.0 * i, 2.5))
    g = torch.Generator().manual_seed(30)
    zt = torch.randn(3, 4, 32, 32, generator=g)
    t = torch.tensor([50, 400, 900])
    cond = zero123.condition([f"b3{o}" for o in IDS], torch.tensor([0.0, 20.0, -30.0]),
                             torch.tensor([90.0, -45.0, 180.0]), torch.tensor([2.5, 2.7, 2.2]))
    _assert_batched_equals_singles(zero123, zt, t, cond, 3.0)


def test_image2d_batch_of_three_objects(image2d) -> None:
    for i, oid in enumerate(IDS):
        image2d.set_reference(f"b3{oid}", photo(40 + i))
    g = torch.Generator().manual_seed(40)
    renders = torch.rand(3, 3, 64, 64, generator=g)
    cond = image2d.condition([f"b3{o}" for o in IDS], renders)
    zt = torch.randn(3, 4, 8, 8, generator=g)
    _assert_batched_equals_singles(image2d, zt, torch.tensor([10, 500, 990]), cond, 2.0)


def test_lora_batch_of_three_objects_with_distinct_adapters(load_image2d) -> None:
    prior = load_image2d()
    loras = ObjectLoras(prior)
    g = torch.Generator().manual_seed(50)
    for i, oid in enumerate(IDS):
        prior.set_reference(oid, photo(50 + i))
        loras.add(oid)
        with torch.no_grad():
            for p in loras.parameters(oid):
                p.normal_(0.0, 0.2, generator=g)
    renders = torch.rand(3, 3, 64, 64, generator=g)
    zt = torch.randn(3, 4, 8, 8, generator=g)
    _assert_batched_equals_singles(loras, zt, torch.tensor([100, 200, 300]), prior.condition(IDS, renders), 1.0)
