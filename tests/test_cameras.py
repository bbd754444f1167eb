"""Orbit cameras: positions, look-at frames, projection consistent with rays and the pixel convention."""

from __future__ import annotations

import math

import pytest
import torch

from morpheus_core.cameras import OrbitConfig, look_at, orbit, reference_camera, sample_orbit, turntable


def test_reference_camera_sits_on_plus_z_looking_at_origin(device: torch.device) -> None:
    cam = reference_camera().to(device)
    torch.testing.assert_close(cam.positions.cpu(), torch.tensor([[0.0, 0.0, 2.5]]))
    forward = -cam.c2w[0, :3, 2].cpu()
    torch.testing.assert_close(forward, torch.tensor([0.0, 0.0, -1.0]))
    torch.testing.assert_close(cam.c2w[0, :3, 1].cpu(), torch.tensor([0.0, 1.0, 0.0]))


def test_orbit_angles_place_the_camera() -> None:
    cam = orbit([30.0, -45.0, 0.0], [90.0, 0.0, -90.0], 2.0)
    expected = torch.tensor(
        [[2 * math.cos(math.radians(30)), 2 * math.sin(math.radians(30)), 0.0],
         [0.0, -2 * math.sin(math.radians(45)), 2 * math.cos(math.radians(45))],
         [-2.0, 0.0, 0.0]]
    )
    torch.testing.assert_close(cam.positions, expected, atol=1e-6, rtol=0)


def test_frames_are_orthonormal_and_invert_exactly() -> None:
    cams = sample_orbit(16, generator=torch.Generator().manual_seed(0)).to(dtype=torch.float64)
    rot = cams.c2w[:, :3, :3]
    # Built in float32: orthonormal to float32 precision.
    eye3, eye4 = torch.eye(3, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    torch.testing.assert_close(rot.transpose(1, 2) @ rot, eye3.expand(16, 3, 3), atol=1e-6, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(16, dtype=torch.float64), atol=1e-6, rtol=0)
    torch.testing.assert_close(cams.world_to_camera() @ cams.c2w, eye4.expand(16, 4, 4), atol=1e-6, rtol=0)


def test_rays_project_to_their_pixel_centres(device: torch.device) -> None:
    """A point on the ray through pixel (i, j) projects to NDC ((2j+1)/W − 1, 1 − (2i+1)/H)."""
    h, w = 6, 10
    cams = sample_orbit(3, generator=torch.Generator().manual_seed(1)).to(device, torch.float64)
    origins, dirs = cams.rays(h, w)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(3, h, w, dtype=torch.float64, device=device))
    points = origins + 1.7 * dirs
    homo = torch.cat((points, torch.ones_like(points[..., :1])), -1)
    clip = torch.einsum("bij,bhwj->bhwi", cams.world_to_clip(aspect=w / h), homo)
    ndc = clip[..., :2] / clip[..., 3:]
    j = torch.arange(w, dtype=torch.float64, device=device)
    i = torch.arange(h, dtype=torch.float64, device=device)
    torch.testing.assert_close(ndc[..., 0], ((2 * j + 1) / w - 1).expand(3, h, w))
    torch.testing.assert_close(ndc[..., 1], (1 - (2 * i + 1) / h).reshape(h, 1).expand(3, h, w))
    assert (clip[..., 3] > 0).all() and (clip[..., 2].abs() <= clip[..., 3]).all()


def test_intrinsics_agree_with_projection() -> None:
    cams = sample_orbit(4, generator=torch.Generator().manual_seed(2)).to(dtype=torch.float64)
    h = w = 64
    k = cams.intrinsics(h, w)
    p_cam = torch.tensor([0.3, -0.2, -2.0], dtype=torch.float64)
    uvw = k @ torch.tensor([p_cam[0], -p_cam[1], -p_cam[2]], dtype=torch.float64)  # OpenCV frame: y down, z forward
    uv = uvw[:, :2] / uvw[:, 2:]
    clip = cams.projection() @ torch.cat((p_cam, torch.ones(1, dtype=torch.float64)))
    ndc = clip[:, :2] / clip[:, 3:]
    torch.testing.assert_close(uv[:, 0], (ndc[:, 0] + 1) * w / 2)
    torch.testing.assert_close(uv[:, 1], (1 - ndc[:, 1]) * h / 2)


def test_sampling_is_seeded_and_within_ranges() -> None:
    cfg = OrbitConfig()
    a = sample_orbit(256, cfg, torch.Generator().manual_seed(7))
    b = sample_orbit(256, cfg, torch.Generator().manual_seed(7))
    c = sample_orbit(256, cfg, torch.Generator().manual_seed(8))
    torch.testing.assert_close(a.c2w, b.c2w)
    assert not torch.allclose(a.c2w, c.c2w)
    assert a.elevation.min() >= -45 and a.elevation.max() <= 45 and a.elevation.std() > 15
    assert a.azimuth.min() >= -180 and a.azimuth.max() <= 180 and a.azimuth.std() > 60
    torch.testing.assert_close(a.fov_y, torch.full((256,), math.radians(40.0)))
    torch.testing.assert_close(a.positions.norm(dim=-1), torch.full((256,), 2.5))


def test_turntable_is_evenly_spaced_from_the_reference() -> None:
    cams = turntable(8, elevation_deg=10.0)
    assert cams.azimuth.tolist() == [0.0, 45.0, 90.0, 135.0, 180.0, -135.0, -90.0, -45.0]
    step = torch.acos((cams.positions[:-1] * cams.positions[1:]).sum(-1) / cams.positions.norm(dim=-1)[1:] ** 2)
    assert torch.allclose(step, step[0]) and len(cams[2:5]) == 3
    with pytest.raises(ValueError):
        turntable(0)


def test_look_at_handles_batches_and_bad_configs() -> None:
    eye = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.5, -2.0]])
    c2w = look_at(eye, torch.zeros(2, 3))
    forward = -c2w[:, :3, 2]
    torch.testing.assert_close(forward, -eye / eye.norm(dim=-1, keepdim=True))
    for bad in ({"fov_deg": 0.0}, {"near": 1.0, "far": 0.5}, {"elevation_range": (-90.0, 10.0)}, {"distance": 0.05}):
        with pytest.raises(ValueError):
            OrbitConfig(**bad)
