"""Initial velocity estimation from the first video frames, with the prior law (NeuMA's stage A).

A single launch velocity v0 [3] (m/s), broadcast to every particle (NeuMA), and optionally an angular
velocity w0 [3] (rad/s) about the centre of mass, are optimised so that the prior's rollout over the
first few video frames matches the observed silhouettes (and optionally colours).
The result is shared by every visual method of a scene, so they differ only in the law they learn.

Motion along the camera's viewing axis only changes the silhouette's size slightly, so over a few
free-flight frames it is weakly observable from one view. An L2 prior pulling that component to zero
(``reg_view_axis``, in the spirit of NeuMA's vertical-drop prior on v_x, v_z) biases every thrown
object whose launch has a component along the ray (session 6: the whole v0 error, 0.4-0.65 m/s, lay
along the ray on all six scenes). The default fits without it, through the first ground contact and
not much further (``n_video_frames``): when the object lands depends on its height, so on the along-ray
part of its image motion, which pins that component; frames well after the contact show the prior's
impact response, not the truth's, and a wrong prior then biases v0 (session 7: 20 frames, ~85% impact,
gave the pawn 0.58 m/s of error, 4 frames 0.11; ``benchmarks/velocity_fit.py``).
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from gca.laws.base import Material
from gca.scenes.store import ViewData
from gca.scenes.world import Body, gaussians_at, initial_velocity, render_gaussians
from gca.sim.rollout import rollout
from gca.sim.solver import MPMSolver
from gca.train.config import VelocityConfig


def silhouette_loss(body: Body, x: torch.Tensor, F: torch.Tensor, camera, mask: torch.Tensor, rgb: torch.Tensor,
                    bg: torch.Tensor, cfg: VelocityConfig) -> torch.Tensor:
    """Mask [H, W] (and optional colour [H, W, 3]) L2 of the body at state (x, F) seen from ``camera``."""
    means, covs = gaussians_at(body, x, F)
    out = render_gaussians(body, means, covs, body.colors, camera, bg)
    loss = cfg.lambda_mask * (out["alpha"] - mask).square().mean()
    if cfg.lambda_color:
        loss = loss + cfg.lambda_color * (out["rgb"] - rgb).square().mean()
    return loss


def estimate_velocity(solver: MPMSolver, material: Material, body: Body, view: ViewData, video_frames: list[int],
                      substeps: int, cfg: VelocityConfig, background=(1.0, 1.0, 1.0),
                      ) -> tuple[torch.Tensor, torch.Tensor, list[float]]:
    """Fit v0 [3] (m/s) and, if ``cfg.angular``, w0 [3] (rad/s) on the first video frames of ``view``.

    Returns:
        (v0 [3], w0 [3] (zeros unless fitted), loss history).
    """
    n = min(cfg.n_video_frames, len(video_frames))
    dtype = body.x0.dtype
    device = body.x0.device
    v0 = torch.zeros(3, dtype=dtype, device=device, requires_grad=True)
    w0 = torch.zeros(3, dtype=dtype, device=device, requires_grad=cfg.angular)
    opt = torch.optim.Adam([v0, w0] if cfg.angular else [v0], lr=cfg.lr)
    bg = torch.tensor(background, dtype=dtype, device=device)
    masks = torch.as_tensor(view.mask, dtype=dtype, device=device)
    rgbs = torch.as_tensor(view.rgb, dtype=dtype, device=device)
    for p in material.parameters():
        p.requires_grad_(False)
    axis = torch.tensor(np.array(view.camera.w2c)[2, :3], dtype=dtype, device=device)  # viewing direction (world)
    history = []
    for _ in tqdm(range(cfg.iterations), desc="velocity", unit="it"):
        opt.zero_grad(set_to_none=True)
        traj = rollout(solver, material, body.x0, initial_velocity(body.x0, v0, w0), body.vol, body.mass,
                       n_steps=video_frames[n - 1] * substeps, steps_per_frame=substeps, checkpoint=True)
        loss = sum(silhouette_loss(body, traj.x[f], traj.F[f], view.camera, masks[j], rgbs[j], bg, cfg)
                   for j, f in enumerate(video_frames[:n]))
        loss = loss + cfg.reg_view_axis * (v0 @ axis).square()
        if not torch.isfinite(loss):
            raise FloatingPointError(f"velocity estimation: non-finite loss at v0={v0.tolist()}, w0={w0.tolist()}")
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    return v0.detach(), w0.detach(), history
