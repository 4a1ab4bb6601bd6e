"""Lighting interference v2 (issue 21, item 2): shadows from the Gaussians' occupancy, exposure and
white-balance drift, highlights, and the unexplained-colour statistic."""

import dataclasses

import numpy as np
import torch

from gca.render.shading import (Light, LightingConfig, background_image, camera_response, floor_points,
                                sample_lights, shade)
from gca.render.shadow import light_visibility

UP = Light(direction=(0.0, 1.0, 0.0), intensity=0.8, ambient=0.2, color=(1.0, 1.0, 1.0))


def _plate(y, x0=0.3, x1=0.5, n=12, z0=0.3, z1=0.5):
    g = torch.linspace(0, 1, n)
    xs, zs = torch.meshgrid(x0 + (x1 - x0) * g, z0 + (z1 - z0) * g, indexing="ij")
    return torch.stack([xs.reshape(-1), torch.full((n * n,), y), zs.reshape(-1)], -1)


def _gaussians(points, sigma=0.012):
    covs = torch.eye(3).expand(len(points), 3, 3) * sigma ** 2
    return points, covs.contiguous(), torch.full((len(points),), 0.95)


def test_shadows_darken_points_occluded_from_the_light_and_not_others():
    top, below, aside = _plate(0.6), _plate(0.3), _plate(0.3, x0=0.7, x1=0.9)
    means, covs, opac = _gaussians(torch.cat([top, below, aside]))
    vis, _ = light_visibility(means, covs, opac, UP.direction, resolution=24)
    n = len(top)
    v_top, v_below, v_aside = vis[:n], vis[n:2 * n], vis[2 * n:]
    inner = torch.zeros(12, 12, dtype=torch.bool)
    inner[2:-2, 2:-2] = True
    inner = inner.reshape(-1)
    assert v_top.min() > 0.99 and v_aside.min() > 0.99                # nothing between them and the light
    assert v_below[inner].max() < 0.1                                  # under the plate: in its shadow
    colors, normals = torch.full((len(means), 3), 0.6), torch.tensor([[0.0, 1.0, 0.0]]).expand(len(means), 3)
    lit, shadowed = shade(colors, normals, UP), shade(colors, normals, UP, visibility=vis)
    assert torch.allclose(lit[:n], shadowed[:n]) and torch.allclose(lit[2 * n:], shadowed[2 * n:], atol=1e-3)
    assert (shadowed[n:2 * n][inner] < 0.5 * lit[n:2 * n][inner]).all()   # ambient only left
    # a light from the -x side: the plate beside the lower one is now behind it (shadowed), the lower one lit
    side, _ = light_visibility(means, covs, opac, (-1.0, 0.05, 0.0), resolution=24)
    assert side[2 * n:].median() < 0.1 and side[n:2 * n].reshape(12, 12)[0].min() > 0.99  # lower plate's -x edge


def test_the_cast_shadow_falls_on_the_floor_below_the_object_only():
    means, covs, opac = _gaussians(_plate(0.4))
    floor = torch.tensor([[0.4, 0.0, 0.4], [0.85, 0.0, 0.85], [0.05, 0.0, 0.4]])
    _, v = light_visibility(means, covs, opac, UP.direction, resolution=24, points=floor)
    assert v[0] < 0.1 and v[1] == 1.0 and v[2] == 1.0
    slanted = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)        # 45 deg: the shadow moves 0.4 m along -x
    _, v = light_visibility(means, covs, opac, tuple(slanted), resolution=24,
                            points=torch.tensor([[0.0, 0.0, 0.4], [0.4, 0.0, 0.4]]))
    assert v[0] < 0.1 and v[1] > 0.99


def test_floor_points_and_the_shadowed_background():
    from gca.render.camera import look_at

    cam = look_at((0.5, 0.5, 1.5), (0.5, 0.2, 0.5), (0.0, 1.0, 0.0), 40.0, 16, 16)
    pts, hit = floor_points(cam)
    assert hit[-16:].all() and not hit[:16].any()          # bottom row sees the floor, top row does not
    assert torch.allclose(pts[hit][:, 1], torch.zeros(int(hit.sum())), atol=1e-6)
    vis = torch.ones(hit.shape[0])
    vis[-1] = 0.0
    img = background_image(cam, torch.ones(3), UP, vis, hit)
    assert img[-1, -1].max() < 0.3 and torch.allclose(img[-1, 0], torch.ones(3))


def test_exposure_and_white_balance_drift_change_image_means_but_not_masks():
    from gca.scenes.ground_truth import _render_view
    from gca.vision.segment import iou, segment_frames
    from synthetic import tiny_body, tiny_camera

    from types import SimpleNamespace

    body = tiny_body()
    x = torch.stack([body.x0 + torch.tensor([0.01 * t, 0.0, 0.0]) for t in range(6)])
    F = torch.eye(3).expand(6, body.n_particles, 3, 3)
    traj = SimpleNamespace(x=x, F=F)  # _render_view reads the positions and deformation gradients only
    cam, bg = tiny_camera(40), torch.full((3,), 0.75)  # an exposed backdrop does not saturate at +0.8 EV x 1.1
    base = LightingConfig(drift=0.0)
    drifting = dataclasses.replace(base, exposure_step_ev=0.3, exposure_max_ev=0.3, wb_step=0.03, wb_max=0.05)
    a = _render_view(body, traj, list(range(6)), cam, sample_lights(base, 6, 3), bg, base)
    b = _render_view(body, traj, list(range(6)), cam, sample_lights(drifting, 6, 3), bg, drifting)
    means_a, means_b = a["rgb"].mean(axis=(1, 2, 3)), b["rgb"].mean(axis=(1, 2, 3))
    assert np.ptp(means_b - means_a) > 0.02                       # the drift moves the image means
    np.testing.assert_array_equal(a["alpha"], b["alpha"])         # the object is where it was
    from gca.vision.segment import SegmentConfig

    cfg = SegmentConfig(plate_color=(0.75, 0.75, 0.75))
    ma, mb = segment_frames(a["rgb"], cfg), segment_frames(b["rgb"], cfg)
    assert (ma == mb).mean() > 0.999 and iou(mb, b["alpha"] > 0.5).min() > 0.85


def test_response_saturates_and_is_identity_at_zero_drift():
    img = torch.full((2, 2, 3), 0.8)
    assert torch.equal(camera_response(img, UP), img)
    bright = dataclasses.replace(UP, exposure_ev=1.0, white_balance=(1.0, 0.9, 1.0))
    out = camera_response(img, bright)
    assert torch.allclose(out[..., 0], torch.ones(2, 2)) and torch.allclose(out[..., 1], torch.full((2, 2), 1.0))


def test_exposure_walk_is_bounded_and_lights_unchanged_by_the_response_knobs():
    cfg = LightingConfig(exposure_step_ev=0.5, exposure_max_ev=0.4, wb_step=0.1, wb_max=0.05)
    lights = sample_lights(cfg, 30, seed=2)
    assert max(abs(l.exposure_ev) for l in lights) <= 0.4 + 1e-12
    assert all(abs(g - 1) <= 0.05 + 1e-9 for l in lights for g in l.white_balance)
    plain = sample_lights(LightingConfig(), 30, seed=2)
    assert [l.direction for l in lights] == [l.direction for l in plain]


def test_specular_adds_a_highlight_toward_the_mirror_direction_only():
    n = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    colors = torch.full((2, 3), 0.3)
    view = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]]), dim=-1)
    spec = shade(colors, n, UP, view_dirs=view, specular=0.5, shininess=16.0)
    plain = shade(colors, n, UP)
    assert spec[0, 0] > plain[0, 0] + 0.4 and torch.allclose(spec[1], plain[1], atol=1e-6)


def test_unexplained_share_is_zero_for_a_global_colour_change_and_grows_with_shadows():
    from gca.scenes.ground_truth import unexplained_colour_share

    rng = np.random.default_rng(0)
    unlit = rng.uniform(0.1, 0.9, (3, 16, 16, 3))
    mask = np.ones((3, 16, 16), bool)
    affine = unlit @ np.array([[0.9, 0.05, 0], [0, 0.8, 0], [0.02, 0, 1.1]]).T + 0.03
    assert unexplained_colour_share(affine, unlit, mask) < 1e-12
    shadowed = affine.copy()
    shadowed[:, :8] *= 0.4                                     # half the object in shadow
    assert unexplained_colour_share(shadowed, unlit, mask) > 0.1
