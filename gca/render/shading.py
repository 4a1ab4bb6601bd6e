"""Lighting interference for the synthetic benchmark videos (the paper's "randomized lighting").

Each frame gets a directional light drawn from a seeded generator within the ranges of a
:class:`LightingConfig`. Gaussian colours are shaded two-sided Lambert-like:

    c' = clamp(c * light_color * (ambient + intensity * |n . l|), 0, 1)

with ``n`` the (sign-less) smallest axis of each Gaussian's covariance and ``l`` the unit direction
towards the light, both in the sim frame (y up).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

_WHERE = "gca/render/shading.py"


@dataclasses.dataclass(frozen=True)
class LightingConfig:
    """Ranges of per-frame lights (params.yaml section ``render.lighting``)."""

    elevation_deg: tuple[float, float] = (20.0, 70.0)    # light elevation above the ground plane [deg]
    azimuth_deg: tuple[float, float] = (0.0, 360.0)      # light azimuth around +y [deg]
    intensity: tuple[float, float] = (0.5, 0.9)          # directional intensity [-]
    ambient: tuple[float, float] = (0.2, 0.5)            # ambient term [-]
    color_jitter: float = 0.1                            # per-channel light colour in [1 - j, 1] [-]
    drift: float = 0.5                                   # 1: independent per frame; <1: each frame moves
                                                         # this fraction from the previous light to a fresh draw [-]

    def __post_init__(self) -> None:
        for name in ("elevation_deg", "azimuth_deg", "intensity", "ambient"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{_WHERE}: LightingConfig.{name} must be (low, high), got ({lo}, {hi})")
        if not 0.0 <= self.color_jitter < 1.0 or not 0.0 <= self.drift <= 1.0:
            raise ValueError(f"{_WHERE}: need 0 <= color_jitter < 1 and 0 <= drift <= 1")


@dataclasses.dataclass(frozen=True)
class Light:
    """One frame's light: unit ``direction`` towards the light [3], ``intensity``, ``ambient``, ``color`` [3]."""

    direction: tuple[float, float, float]
    intensity: float
    ambient: float
    color: tuple[float, float, float]


def _draw(cfg: LightingConfig, rng: np.random.Generator) -> np.ndarray:
    """A raw light parameter vector (elevation, azimuth [rad], intensity, ambient, rgb)."""
    return np.array([math.radians(rng.uniform(*cfg.elevation_deg)), math.radians(rng.uniform(*cfg.azimuth_deg)),
                     rng.uniform(*cfg.intensity), rng.uniform(*cfg.ambient),
                     *rng.uniform(1.0 - cfg.color_jitter, 1.0, size=3)])


def _to_light(p: np.ndarray) -> Light:
    elev, azim = p[0], p[1]
    direction = (math.cos(elev) * math.cos(azim), math.sin(elev), math.cos(elev) * math.sin(azim))
    return Light(direction=direction, intensity=float(p[2]), ambient=float(p[3]), color=tuple(float(c) for c in p[4:7]))


def sample_lights(cfg: LightingConfig, n_frames: int, seed: int) -> list[Light]:
    """Per-frame lights, reproducible from ``seed``.

    Args:
        cfg: ranges.
        n_frames: number of frames.
        seed: generator seed.

    Returns:
        ``n_frames`` :class:`Light` objects.
    """
    rng = np.random.default_rng(seed)
    p = _draw(cfg, rng)
    lights = []
    for _ in range(n_frames):
        lights.append(_to_light(p))
        p = (1.0 - cfg.drift) * p + cfg.drift * _draw(cfg, rng)
    return lights


def shade(colors: torch.Tensor, normals: torch.Tensor, light: Light) -> torch.Tensor:
    """Two-sided Lambert-like shading of Gaussian colours.

    Args:
        colors: base colours [N, 3] in [0, 1].
        normals: unit normals [N, 3] (sign ignored), e.g. :func:`gca.render.follow.smallest_axis_normal`.
        light: the frame's :class:`Light`.

    Returns:
        Shaded colours [N, 3] in [0, 1].
    """
    assert colors.ndim == 2 and colors.shape[1] == 3 and normals.shape == colors.shape, \
        f"{_WHERE}: colors and normals must both be [N, 3], got {tuple(colors.shape)}, {tuple(normals.shape)}"
    l = torch.tensor(light.direction, dtype=colors.dtype, device=colors.device)
    rgb = torch.tensor(light.color, dtype=colors.dtype, device=colors.device)
    lambert = (normals.to(colors.dtype) @ l).abs()
    return (colors * rgb * (light.ambient + light.intensity * lambert)[:, None]).clamp(0.0, 1.0)
