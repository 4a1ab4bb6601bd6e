"""A tiny in-memory scene for training tests: a textured block of particles, one camera, GT views.

Built without the pipeline's files so that training tests stay fast: particles on a lattice, one
small isotropic Gaussian per particle (binding = identity), a ground-truth rollout with an analytic
law, and the monocular observations a method may use (RGB, masks, simulated depth, SIFT keypoints).
"""

from __future__ import annotations

import numpy as np
import torch

from gca.laws.presets import material_from_preset
from gca.render.camera import look_at
from gca.render.follow import Binding
from gca.render.rasterize import render
from gca.scenes.store import ViewData
from gca.scenes.world import Body, gaussians_at, initial_velocity
from gca.sim.rollout import rollout
from gca.sim.solver import MPMSolver, SimConfig
from gca.vision import SimulatedDepthConfig, SimulatedDepth, detect_keypoints

JELLY = {"elasticity": "corotated", "plasticity": "identity", "E": 2.0e4, "nu": 0.2, "rho": 1000.0}


def tiny_body(n_side: int = 5, spacing: float = 0.04, seed: int = 0, base_y: float = 0.2) -> Body:
    """A cube of n_side^3 particles ``base_y`` above the floor [m], each carrying one textured Gaussian."""
    g = torch.arange(n_side, dtype=torch.float32) * spacing
    x0 = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + torch.tensor([0.42, base_y, 0.42])
    P = x0.shape[0]
    rng = np.random.default_rng(seed)
    vol = torch.full((P,), spacing ** 3)
    idx = torch.arange(P)
    binding = Binding(rows=idx, cols=idx, weights=torch.ones(P), n_gaussians=P, n_particles=P)
    covs0 = torch.eye(3).expand(P, 3, 3) * (0.6 * spacing) ** 2
    return Body(x0=x0, vol=vol, mass=vol * 1000.0, binding=binding, means0=x0.clone(), covs0=covs0.contiguous(),
                colors=torch.as_tensor(rng.uniform(0.05, 0.95, (P, 3)), dtype=torch.float32),
                opacities=torch.full((P,), 0.95))


def tiny_camera(resolution: int = 48):
    return look_at((0.5, 0.3, 1.3), (0.5, 0.25, 0.5), (0.0, 1.0, 0.0), 30.0, resolution, resolution)


def tiny_solver(dt: float = 1e-3) -> MPMSolver:
    return MPMSolver(SimConfig(n_grid=16, dt=dt, bound=1, boundary="friction", friction=0.4, max_refine=1), "cpu")


def ground_truth_views(body: Body, v0, w0=(0.0, 0.0, 0.0), n_frames: int = 8, substeps: int = 2,
                       frame_every: int = 2, preset=JELLY, resolution: int = 48) -> tuple[ViewData, list[int], torch.Tensor]:
    """Simulate ``preset`` from (v0, w0) and render the monocular view; returns (view, video_frames, traj.x)."""
    solver = tiny_solver()
    material = material_from_preset(preset)
    v = initial_velocity(body.x0, torch.tensor(v0, dtype=torch.float32), torch.tensor(w0, dtype=torch.float32))
    with torch.no_grad():
        traj = rollout(solver, material, body.x0, v, body.vol, body.mass, n_frames * substeps, substeps, checkpoint=False)
    frames = list(range(frame_every, n_frames + 1, frame_every))
    camera, bg = tiny_camera(resolution), torch.ones(3)
    rgb, mask, depth = [], [], []
    for f in frames:
        means, covs = gaussians_at(body, traj.x[f], traj.F[f])
        with torch.no_grad():
            out = render(means, covs, body.colors, body.opacities, camera, bg)
        rgb.append(out["rgb"].clamp(0, 1).numpy())
        mask.append(out["alpha"].numpy() > 0.5)
        depth.append(np.where(mask[-1], out["depth"].numpy(), 0.0))
    view = ViewData("train0", camera, np.stack(rgb).astype(np.float32), np.stack(mask), np.stack(depth).astype(np.float32))
    return view, frames, traj.x


def observations(view: ViewData, seed: int = 0):
    """(estimated depth [T,H,W], SIFT keypoints per frame) as the preprocess stage would make them."""
    est = SimulatedDepth(SimulatedDepthConfig(edge_band_px=1.0, lowfreq_sigma_px=4.0), seed).estimate(
        (view.rgb * 255).astype(np.uint8), view.depth, view.mask)
    keypoints = [detect_keypoints((f * 255).astype(np.uint8)) for f in view.rgb]
    return est, keypoints


class NaNBackward(torch.autograd.Function):
    """Identity forward; the backward poisons one entry of the gradient: a broken stage, for the tests of where a
    non-finite gradient entered (``gca.train.probe``, ``gca.train.loop._provenance``)."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, g):
        g = g.clone()
        g.view(-1)[0] = float("nan")
        return g
