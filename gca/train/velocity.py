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

**Point tracks** (``lambda_track`` > 0; a departure from NeuMA, which fits silhouettes only). Benchmark 2.0's
masks come from background subtraction of the lit video (IoU 0.63-0.76 with the true silhouettes, shadows and
highlights included), and their size errors read as motion along the ray: session 21 measured 0.35-7.3 m/s of
launch error on the Table 1 scenes, mostly along the ray. The texture does not have that bias. The surface point seen
at pixel p of the first video frame is taken to be the one the scan renders at p at rest (:func:`track_anchors`: its
world position X0(p) from a position image; the first video frame comes one frame interval after the launch, a few
px of motion, which the displacements below absorb). It is carried by its k nearest particles with their affine
maps, ``x_k + F_k (X0 - x0_k)`` (the renderer moves a Gaussian's mean by its particles' translation alone,
``gca.render.follow``; the two differ by ``(F_k - I)`` times the offset: not measured; estimated at a rotation of
~0.1 rad over the fitted frames times an offset of about half a particle spacing). Dense optical flow from the first
frame to frame j (``gca.vision.matching.match_flow``, forward-backward checked, observations only) says where that
texture point is seen at frame j, q_j(p). :func:`track_loss` is the Huber error [px] of the carried points' image
displacements from the first video frame against ``q_j - p``. Along-ray motion shows as the tracks' expansion about
the camera's centre (a 1 % change of depth moves the points of a 60-px object by ~0.3 px; the flow's matches are
within ~0.2 px, NOTES s16), over ~100 points a frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from tqdm import tqdm

from gca.align.rdga import sample_unpremultiplied
from gca.laws.base import Material
from gca.scenes.store import ViewData
from gca.scenes.world import Body, gaussians_at, initial_velocity, render_gaussians
from gca.sim.rollout import rollout
from gca.sim.solver import MPMSolver
from gca.train.config import VelocityConfig
from gca.vision.matching import MatchConfig, match_flow, rgb_uint8


def silhouette_loss(body: Body, x: torch.Tensor, F: torch.Tensor, camera, mask: torch.Tensor, rgb: torch.Tensor,
                    bg: torch.Tensor, cfg: VelocityConfig) -> torch.Tensor:
    """Mask [H, W] (and optional colour [H, W, 3]) L2 of the body at state (x, F) seen from ``camera``."""
    means, covs = gaussians_at(body, x, F)
    out = render_gaussians(body, means, covs, body.colors, camera, bg)
    loss = cfg.lambda_mask * (out["alpha"] - mask).square().mean()
    if cfg.lambda_color:
        loss = loss + cfg.lambda_color * (out["rgb"] - rgb).square().mean()
    return loss


@dataclasses.dataclass
class Tracks:
    """Texture points of the first video frame followed through frames 1..n-1 (:func:`track_anchors`).

    Attributes:
        idx: [M, k] the k particles nearest each point at frame 0.
        weight: [M, k] their weights (inverse distance, rows sum to 1).
        offset: [M, k, 3] the point minus each particle at rest, X0 - x0_k [m].
        p: [M, 2] the points' pixels in the first video frame [px, array-index convention].
        frames: the video frames j (1..n-1) with matches.
        which: per frame, [M_j] indices of the points matched there.
        q: per frame, [M_j, 2] where they are seen [px, array-index convention].
    """

    idx: torch.Tensor
    weight: torch.Tensor
    offset: torch.Tensor
    p: torch.Tensor
    frames: list[int]
    which: list[torch.Tensor]
    q: list[torch.Tensor]

    def __len__(self) -> int:
        return sum(len(w) for w in self.which)


def track_anchors(body: Body, view: ViewData, n: int, match: MatchConfig, k: int = 4,
                  alpha_min: float = 0.95) -> Tracks:
    """Point tracks from the first video frame of ``view`` to frames 1..n-1, anchored on the body at rest.

    The scan is rendered at x0 with its positions as colours (a position image): the surface point seen at a pixel
    p where that render is opaque (alpha >= ``alpha_min``) and the first frame's mask is set has world position
    X0(p). ``match_flow`` (first frame -> frame j, on the observed RGB only) gives q_j(p). Each X0(p) is carried by
    its ``k`` nearest particles (inverse-distance weights). Returns :class:`Tracks` (empty when nothing matched).
    """
    dtype, device = body.x0.dtype, body.x0.device
    eye = torch.eye(3, dtype=dtype, device=device).expand(len(body.x0), 3, 3)
    with torch.no_grad():
        means, covs = gaussians_at(body, body.x0, eye)
        out = render_gaussians(body, means, covs, means, view.camera, torch.zeros(3, dtype=dtype, device=device))
    alpha = out["alpha"]
    opaque = (alpha >= alpha_min).cpu().numpy() & np.asarray(view.mask[0], bool)
    first = rgb_uint8(view.rgb[0])
    per_frame, starts = [], {}
    for j in range(1, n):
        p, q = match_flow(first, rgb_uint8(view.rgb[j]), match, render_mask=opaque, gt_mask=np.asarray(view.mask[j], bool))
        rows = [starts.setdefault((float(a), float(b)), len(starts)) for a, b in p]
        per_frame.append((j, rows, q))
    empty = torch.zeros(0, dtype=torch.long, device=device)
    if not starts:
        return Tracks(empty.view(0, k), torch.zeros(0, k, dtype=dtype, device=device),
                      torch.zeros(0, k, 3, dtype=dtype, device=device), torch.zeros(0, 2, dtype=dtype, device=device),
                      [], [], [])
    p_all = torch.tensor(list(starts), dtype=dtype, device=device)  # [M, 2] in first-seen order (dict order)
    X0 = sample_unpremultiplied(out["rgb"], alpha, p_all)  # [M, 3] world
    dist, idx = torch.cdist(X0, body.x0).topk(min(k, len(body.x0)), largest=False)
    weight = 1.0 / dist.clamp_min(1e-6)
    weight = weight / weight.sum(-1, keepdim=True)
    frames, which, qs = [], [], []
    for j, rows, q in per_frame:
        if rows:
            frames.append(j)
            which.append(torch.tensor(rows, dtype=torch.long, device=device))
            qs.append(torch.as_tensor(q, dtype=dtype, device=device))
    return Tracks(idx, weight, X0[:, None, :] - body.x0[idx], p_all, frames, which, qs)


def track_points(tracks: Tracks, x: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
    """The tracked surface points [M, 3] at particle state (x [P, 3], F [P, 3, 3]): each neighbour's affine map
    ``x_k + F_k (X0 - x0_k)``, weighted. Not the renderer's binding (``gca.render.follow`` moves a Gaussian's mean by
    its particles' translation only): see the module's docstring."""
    moved = x[tracks.idx] + (F[tracks.idx] @ tracks.offset[..., None])[..., 0]  # [M, k, 3]
    return (tracks.weight[..., None] * moved).sum(1)


def track_loss(tracks: Tracks, traj, video_frames: list[int], camera, delta_px: float) -> torch.Tensor:
    """Mean Huber error [px^2 scale] of the tracked points' image displacements from the first video frame to
    frame j: the points carried by the rollout, projected at both frames, ``pi(P_j) - pi(P_0)``, against the flow's
    ``q_j - p``. Displacements, not positions: the first video frame comes one frame interval after the launch
    (``SceneVideo.video_frames`` starts at ``frame_every``), so the material the rest render shows at p is off by
    that interval's image motion (a few px), which changes a displacement only by the displacement field's
    variation over a few px (~0.03 px), but a position by the whole motion."""
    f0 = video_frames[0]
    uv0, _ = camera.project(track_points(tracks, traj.x[f0], traj.F[f0]))
    terms = []
    for j, which, q in zip(tracks.frames, tracks.which, tracks.q):
        f = video_frames[j]
        uv, _ = camera.project(track_points(tracks, traj.x[f], traj.F[f])[which])
        terms.append(torch.nn.functional.huber_loss(uv - uv0[which], q - tracks.p[which], delta=delta_px,
                                                    reduction="none").sum(-1))
    return torch.cat(terms).mean()


def estimate_velocity(solver: MPMSolver, material: Material, body: Body, view: ViewData, video_frames: list[int],
                      substeps: int, cfg: VelocityConfig, background=(1.0, 1.0, 1.0),
                      match: MatchConfig = MatchConfig()) -> tuple[torch.Tensor, torch.Tensor, list[float]]:
    """Fit v0 [3] (m/s) and, if ``cfg.angular``, w0 [3] (rad/s) on the first video frames of ``view``: the
    silhouettes' L2 (``lambda_mask``, optional colour) plus, with ``cfg.lambda_track`` > 0, the point tracks'
    reprojection error (:func:`track_loss`; ``match``: the flow's knobs, ``vision.matching``).

    Returns:
        (v0 [3], w0 [3] (zeros unless fitted), loss history).
    """
    n = min(cfg.n_video_frames, len(video_frames))
    dtype = body.x0.dtype
    device = body.x0.device
    tracks = track_anchors(body, view, n, match, cfg.track_k) if cfg.lambda_track > 0 else None
    if tracks is not None and len(tracks) == 0:
        raise ValueError(f"velocity estimation: lambda_track={cfg.lambda_track} but no point of the first frame "
                         f"was tracked through frames 1..{n - 1} of view {view.name!r} (textureless, or masks empty)")
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
        if tracks is not None:
            loss = loss + cfg.lambda_track * track_loss(tracks, traj, video_frames, view.camera, cfg.track_huber_px)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"velocity estimation: non-finite loss at v0={v0.tolist()}, w0={w0.tolist()}")
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    return v0.detach(), w0.detach(), history
