"""Lighting interference for the synthetic benchmark videos (the paper's "randomized lighting interference";
"self-occlusions and rapid rotation cause severe lighting changes and shading artifacts").

Each frame gets a directional light drawn from a seeded generator within the ranges of a
:class:`LightingConfig`, and a camera response (exposure in EV and white-balance gains, random walks).
Gaussian colours are shaded two-sided Lambert-like with the light's visibility ``V`` (shadows,
:mod:`gca.render.shadow`) and an optional Blinn-Phong highlight:

    c' = clamp(c * light_color * (ambient + intensity * V * |n . l|) + specular * V * light_color * (n_v . h)^shininess, 0, 1)

with ``n`` the (sign-less) smallest axis of each Gaussian's covariance, so shading follows the object's
rotation and deformation, ``n_v`` it turned toward the viewer, ``l`` the unit direction towards the light,
``h`` the half vector, all in the sim frame (y up). The floor (y = 0) seen behind the object receives the
object's cast shadow (:func:`background_image`); the whole image then goes through the camera response
(:func:`camera_response`): ``I' = clamp(I * 2^ev * wb, 0, 1)``.
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
    shadows: bool = True                                # self- and cast shadows from the Gaussians' occupancy
    shadow_resolution: int = 64                          # light-space cells across the object [count]
    floor_shadow: bool = True                           # the object's cast shadow on the floor behind it
    specular: float = 0.2                                # Blinn-Phong highlight strength; 0 = off [-]
    shininess: float = 24.0                              # Blinn-Phong exponent [-]
    exposure_step_ev: float = 0.05                        # per-frame std of the exposure random walk [EV]
    exposure_max_ev: float = 0.3                         # |exposure| bound [EV]
    wb_step: float = 0.01                                 # per-frame std of each channel's log gain random walk [-]
    wb_max: float = 0.05                                 # |gain - 1| bound per channel [-]

    def __post_init__(self) -> None:
        for name in ("elevation_deg", "azimuth_deg", "intensity", "ambient"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{_WHERE}: LightingConfig.{name} must be (low, high), got ({lo}, {hi})")
        if not 0.0 <= self.color_jitter < 1.0 or not 0.0 <= self.drift <= 1.0:
            raise ValueError(f"{_WHERE}: need 0 <= color_jitter < 1 and 0 <= drift <= 1")
        if min(self.specular, self.exposure_step_ev, self.exposure_max_ev, self.wb_step, self.wb_max) < 0 \
                or self.shadow_resolution < 4 or self.wb_max >= 1:
            raise ValueError(f"{_WHERE}: need specular, exposure and white-balance amounts >= 0 (wb_max < 1) "
                             f"and shadow_resolution >= 4")


@dataclasses.dataclass(frozen=True)
class Light:
    """One frame's light: unit ``direction`` towards the light [3], ``intensity``, ``ambient``, ``color`` [3],
    and the camera's response that frame: ``exposure_ev`` [EV], ``white_balance`` gains [3]."""

    direction: tuple[float, float, float]
    intensity: float
    ambient: float
    color: tuple[float, float, float]
    exposure_ev: float = 0.0
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)


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
    response = np.random.default_rng([seed, 1])  # its own stream: the lights do not depend on the response's knobs
    p = _draw(cfg, rng)
    ev, log_wb = 0.0, np.zeros(3)
    lights = []
    for _ in range(n_frames):
        lights.append(dataclasses.replace(_to_light(p), exposure_ev=float(ev),
                                          white_balance=tuple(float(g) for g in np.exp(log_wb))))
        p = (1.0 - cfg.drift) * p + cfg.drift * _draw(cfg, rng)
        ev = float(np.clip(ev + cfg.exposure_step_ev * response.standard_normal(), -cfg.exposure_max_ev, cfg.exposure_max_ev))
        bound = math.log1p(cfg.wb_max)
        log_wb = np.clip(log_wb + cfg.wb_step * response.standard_normal(3), -bound, bound)
    return lights


def shade(colors: torch.Tensor, normals: torch.Tensor, light: Light, visibility: torch.Tensor | None = None,
          view_dirs: torch.Tensor | None = None, specular: float = 0.0, shininess: float = 32.0) -> torch.Tensor:
    """Two-sided Lambert-like shading of Gaussian colours, with shadows and an optional highlight.

    Args:
        colors: base colours [N, 3] in [0, 1].
        normals: unit normals [N, 3] (sign ignored), e.g. :func:`gca.render.follow.smallest_axis_normal`.
        light: the frame's :class:`Light`.
        visibility: light visibility V [N] in [0, 1] (:func:`gca.render.shadow.light_visibility`); None = 1.
        view_dirs: unit directions from each Gaussian toward the camera [N, 3] (needed when specular > 0).
        specular: Blinn-Phong strength; shininess: its exponent.

    Returns:
        Shaded colours [N, 3] in [0, 1].
    """
    assert colors.ndim == 2 and colors.shape[1] == 3 and normals.shape == colors.shape, \
        f"{_WHERE}: colors and normals must both be [N, 3], got {tuple(colors.shape)}, {tuple(normals.shape)}"
    l = torch.tensor(light.direction, dtype=colors.dtype, device=colors.device)
    rgb = torch.tensor(light.color, dtype=colors.dtype, device=colors.device)
    n = normals.to(colors.dtype)
    lambert = (n @ l).abs()
    vis = torch.ones_like(lambert) if visibility is None else visibility.to(colors.dtype)
    out = colors * rgb * (light.ambient + light.intensity * vis * lambert)[:, None]
    if specular > 0:
        if view_dirs is None:
            raise ValueError(f"{_WHERE}: specular shading needs view_dirs")
        n_v = n * torch.sign((n * view_dirs).sum(-1, keepdim=True) + 1e-12)
        half = torch.nn.functional.normalize(view_dirs + l, dim=-1)
        out = out + specular * (vis * (n_v * half).sum(-1).clamp(min=0.0) ** shininess)[:, None] * rgb
    return out.clamp(0.0, 1.0)


def floor_points(camera, dtype=torch.float32, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Where each pixel's ray meets the floor y = 0: points [H*W, 3] (sim frame) and a hit mask [H*W]."""
    K, _ = camera.tensors(torch.float64, "cpu")
    c2w = torch.tensor(camera.c2w.tolist(), dtype=torch.float64)
    jj, ii = torch.meshgrid(torch.arange(camera.height, dtype=torch.float64) + 0.5,
                            torch.arange(camera.width, dtype=torch.float64) + 0.5, indexing="ij")
    d_cam = torch.stack([(ii - K[0, 2]) / K[0, 0], (jj - K[1, 2]) / K[1, 1], torch.ones_like(ii)], -1).reshape(-1, 3)
    d = d_cam @ c2w[:3, :3].T
    o = c2w[:3, 3]
    t = -o[1] / torch.where(d[:, 1] < -1e-9, d[:, 1], torch.full_like(d[:, 1], -1e-9))
    hit = (d[:, 1] < -1e-9) & (t > 0)
    pts = o + t[:, None] * d
    return pts.to(dtype=dtype, device=device), hit.to(device)


def background_image(camera, background, light: Light, floor_visibility: torch.Tensor | None = None,
                     floor_hit: torch.Tensor | None = None) -> torch.Tensor:
    """The lit empty scene [H, W, 3]: the background colour under the light's colour, darkened on the floor
    where the object blocks the light: ``bg * rgb * (ambient + I * l_y * V) / (ambient + I * l_y)``."""
    bg = torch.as_tensor(background)
    rgb = torch.tensor(light.color, dtype=bg.dtype, device=bg.device)
    img = (bg * rgb).expand(camera.height * camera.width, 3).clone()
    if floor_visibility is not None:
        ly = max(light.direction[1], 0.0)
        full = light.ambient + light.intensity * ly
        factor = (light.ambient + light.intensity * ly * floor_visibility.to(bg.dtype)) / full
        img = torch.where(floor_hit[:, None], img * factor[:, None], img)
    return img.view(camera.height, camera.width, 3)


def camera_response(image: torch.Tensor, light: Light) -> torch.Tensor:
    """Exposure and white balance of one frame [..., 3]: ``clamp(I * 2^ev * wb, 0, 1)`` (saturates)."""
    wb = torch.tensor(light.white_balance, dtype=image.dtype, device=image.device)
    return (image * (2.0 ** light.exposure_ev) * wb).clamp(0.0, 1.0)
