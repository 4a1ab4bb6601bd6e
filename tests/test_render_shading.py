"""Lighting interference: seeded, varies between frames, two-sided Lambert."""

import dataclasses

import pytest
import torch

from gca.render import Light, LightingConfig, sample_lights, shade


def test_lights_are_deterministic_per_seed_and_change_between_frames():
    cfg = LightingConfig(drift=1.0)
    a, b, c = sample_lights(cfg, 4, seed=5), sample_lights(cfg, 4, seed=5), sample_lights(cfg, 4, seed=6)
    assert a == b and a != c
    colors = torch.full((10, 3), 0.6)
    normals = torch.nn.functional.normalize(torch.randn(10, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    shaded = [shade(colors, normals, light) for light in a]
    assert all(not torch.allclose(shaded[0], s) for s in shaded[1:])
    for light in a:
        assert abs(sum(d * d for d in light.direction) - 1.0) < 1e-12
        assert light.direction[1] > 0      # elevation in (20, 70) deg: light above the ground
        assert cfg.intensity[0] <= light.intensity <= cfg.intensity[1]


def test_drift_zero_gives_a_constant_light():
    lights = sample_lights(dataclasses.replace(LightingConfig(drift=1.0), drift=0.0, exposure_step_ev=0.0, wb_step=0.0), 3,
                           seed=1)  # the camera-response random walks off too
    assert lights[0] == lights[1] == lights[2]


def test_shading_is_two_sided_lambert_hand_computed():
    light = Light(direction=(0.0, 1.0, 0.0), intensity=0.5, ambient=0.2, color=(1.0, 0.5, 1.0))
    colors = torch.tensor([[0.8, 0.8, 0.8]] * 3)
    normals = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    out = shade(colors, normals, light)
    torch.testing.assert_close(out[0], torch.tensor([0.56, 0.28, 0.56]))     # 0.8 * (0.2 + 0.5)
    torch.testing.assert_close(out[1], out[0])                              # sign of n does not matter
    torch.testing.assert_close(out[2], torch.tensor([0.16, 0.08, 0.16]))     # grazing: ambient only


def test_bad_ranges_raise():
    with pytest.raises(ValueError, match="shading.py.*intensity"):
        LightingConfig(intensity=(0.9, 0.1), drift=1.0)
