"""A simulated, renderable object: particles carrying Gaussians, in the simulation frame.

This is the one differentiable path shared by the ground-truth generator and by training:

    v_init --rollout(material)--> x_t, F_t --follow(binding)--> means_t, covs_t --render(camera)--> images

Ground truth runs it without gradients (analytic law, shaded colours); training runs it with
gradients to the law's parameters and the initial velocity.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from gca.assets.particles import Particles, load_particles
from gca.assets.ply import GaussianCloud, covariances, opacities, read_ply, sh0_to_rgb
from gca.render.follow import Binding, follow
from gca.render.camera import Camera
from gca.render.rasterize import RasterConfig, render
from gca.render.backend import choose
from gca.sh import view_term


@dataclasses.dataclass
class Body:
    """Particles and their bound Gaussians in the sim frame (torch tensors on one device).

    Attributes:
        x0: initial particle positions [P, 3] (m).
        vol: particle volumes [P] (m^3).
        mass: particle masses [P] (kg).
        binding: Gaussian -> particle weights W [G, P], rows sum to 1.
        means0: Gaussian centres [G, 3] (m).
        covs0: Gaussian covariances [G, 3, 3] (m^2).
        colors: base RGB [G, 3] in [0, 1].
        opacities: [G] in [0, 1].
        backend: rasterizer backend (``torch`` everywhere, ``gsplat`` on CUDA).
        raster: rasterizer settings.
        sh_rest: SH bands 1-3 [G, K, 3] when the scan has non-zero ones (view-dependent colour,
            :func:`body_colors`), else None. The sim frame is the object frame scaled and shifted
            (no rotation), so the bands apply to sim-frame view directions as stored. They are not
            rotated with each Gaussian's deformation (PhysGaussian's simplification).
    """

    x0: torch.Tensor
    vol: torch.Tensor
    mass: torch.Tensor
    binding: Binding
    means0: torch.Tensor
    covs0: torch.Tensor
    colors: torch.Tensor
    opacities: torch.Tensor
    backend: str = "torch"
    raster: RasterConfig = RasterConfig()
    sh_rest: torch.Tensor | None = None

    @property
    def n_particles(self) -> int:
        return int(self.x0.shape[0])

    @property
    def n_gaussians(self) -> int:
        return int(self.means0.shape[0])


def gaussians_in_sim(cloud: GaussianCloud, sim_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map Gaussian means [G, 3] and covariances [G, 3, 3] from world to sim frame (x_sim = A x + t)."""
    A, t = sim_from_world[:3, :3], sim_from_world[:3, 3]
    means = cloud.means.astype(np.float64) @ A.T + t
    covs = A @ covariances(cloud).astype(np.float64) @ A.T
    return means, covs


def load_body(particles_path: str | Path, gaussians_path: str | Path, device: str | torch.device = "cpu",
              dtype: torch.dtype = torch.float32, backend: str = "torch", raster: RasterConfig = RasterConfig()) -> Body:
    """Load ``particles.npz`` and the object's ``gaussians.ply`` into a :class:`Body`."""
    particles: Particles = load_particles(particles_path)
    cloud = read_ply(gaussians_path)
    if cloud.n != particles.n_gaussians:
        raise ValueError(f"{gaussians_path}: has {cloud.n} Gaussians but {particles_path} was made from "
                         f"{particles.n_gaussians}; re-run the particles stage")
    kept = cloud.subset(particles.gaussian_index)
    means, covs = gaussians_in_sim(kept, particles.sim_from_world)
    as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
    binding = Binding(rows=torch.as_tensor(particles.binding_rows, dtype=torch.long, device=device),
                      cols=torch.as_tensor(particles.binding_cols, dtype=torch.long, device=device),
                      weights=as_t(particles.binding_weights), n_gaussians=kept.n, n_particles=particles.n)
    return Body(x0=as_t(particles.x), vol=as_t(particles.vol), mass=as_t(particles.mass), binding=binding,
                means0=as_t(means), covs0=as_t(covs), colors=as_t(np.clip(sh0_to_rgb(kept.sh_dc), 0, 1)),
                opacities=as_t(opacities(kept)), backend=backend, raster=raster,
                sh_rest=as_t(kept.sh_rest) if np.any(kept.sh_rest) else None)


def resolve_backend(requested: str, device: str | torch.device | None = None) -> str:
    """The rasterizer that runs for ``render.backend = requested`` on ``device`` (default: cuda when available).

    ``auto`` picks gsplat on CUDA when the package is installed and the torch rasterizer otherwise,
    and says which and why once per process (:func:`gca.render.backend.choose`); an explicit
    ``gsplat`` off CUDA falls back to torch with a warning.
    """
    on_cuda = torch.cuda.is_available() if device is None else torch.device(device).type == "cuda"
    return choose(requested, on_cuda)[0]


def initial_velocity(x0: torch.Tensor, v0: torch.Tensor, w0: torch.Tensor | None = None) -> torch.Tensor:
    """Rigid initial velocity field v = v0 + w0 x (x - com) [P, 3] (m/s); differentiable in v0, w0."""
    v = v0.reshape(1, 3).expand_as(x0)
    if w0 is not None:
        v = v + torch.cross(w0.reshape(1, 3).expand_as(x0), x0 - x0.mean(0, keepdim=True), dim=1)
    return v


def gaussians_at(body: Body, x: torch.Tensor, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Deformed Gaussian means [G, 3] and covariances [G, 3, 3] for particle state (x [P,3], F [P,3,3]); with a
    leading frame dim (x [T,P,3], F [T,P,3,3]) the T states' [T, G, ...] at once."""
    return follow(body.binding, body.means0, body.covs0, body.x0, x, F)


def body_colors(body: Body, means: torch.Tensor, camera: Camera) -> torch.Tensor:
    """The body's colours seen from ``camera`` [G, 3] in [0, 1]: ``body.colors`` plus, when the scan has
    SH bands 1-3, their view-dependent term along camera centre -> mean (:mod:`gca.sh`); [T, G, 3] for means
    [T, G, 3] (T frames)."""
    if body.sh_rest is None:
        return body.colors if means.ndim == 2 else body.colors.expand(*means.shape[:-2], -1, -1)
    centre = camera.center_tensor(means.dtype, means.device)  # made once (a host copy per frame would wait for the GPU)
    return (body.colors + view_term(body.sh_rest, means, centre)).clamp(0.0, 1.0)


def render_gaussians(body: Body, means: torch.Tensor, covs: torch.Tensor, colors: torch.Tensor, camera: Camera,
                     bg: torch.Tensor, checks: list | None = None) -> dict:
    """Render the body's Gaussians at (means [G,3], covs [G,3,3]) with per-Gaussian ``colors`` [G,C]
    through the body's rasterizer settings: ``{rgb [H,W,C], alpha [H,W], depth [H,W], ...}``; T frames at
    once with a leading frame dim on means, covs, colors and the outputs (:func:`gca.render.rasterize.render`).
    ``colors`` given as ``body.colors`` itself means the scan's colours: view-dependent
    (:func:`body_colors`) when it has SH bands 1-3. ``checks``: as :func:`gca.render.rasterize.render`'s."""
    if colors is body.colors:
        colors = body_colors(body, means, camera)
    return render(means, covs, colors, body.opacities, camera, bg, backend=body.backend, cfg=body.raster,
                  checks=checks)


def render_body(body: Body, x: torch.Tensor, F: torch.Tensor, camera: Camera, background,
                colors: torch.Tensor | None = None) -> dict:
    """Render the body at one state from ``camera``: ``{rgb [H,W,3], alpha [H,W], depth [H,W]}``."""
    means, covs = gaussians_at(body, x, F)
    bg = torch.as_tensor(background, dtype=means.dtype, device=means.device)
    return render_gaussians(body, means, covs, body.colors if colors is None else colors, camera, bg)
