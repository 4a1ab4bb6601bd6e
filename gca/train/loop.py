"""Optimising a method's law from video: rollout -> render -> losses -> backward, with a frame curriculum.

One iteration (NeuMA stage B, with GCA's losses where the method asks for them):

1. roll the law out from the estimated initial velocity for the current curriculum horizon, with
   per-frame checkpointing (memory does not grow with every step's activations);
2. at each supervised video frame, move the Gaussians with the particles and render every training
   view; add the method's losses: colour L2 (NeuMA), silhouette + RDGA geometry (GCA), L1 monocular
   depth (PAC-NeRF + depth), and CPR residuals on the frame's deformation gradients;
3. backward once, clip the gradient norm, step Adam with cosine decay.

An update after which the rollout diverges (non-finite loss or state, particles leaving the domain, a
rollout drifting away from the observed silhouette) is rejected: the law and the optimiser go back to
before it, the learning rate is multiplied by ``backtrack_factor`` for the rest of the run and the
update is retaken from the same gradient. After ``max_rejections`` rejections in a row (or a
divergence before any update, i.e. of the prior itself) the run stops cleanly and is reported as
diverged with its last finite losses; every rejection is listed in the result. Checkpoints are
written every ``checkpoint_every`` iterations and resumed from.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from gca import stop
from gca.align.cpr import CPR, CPRConfig
from gca.align.rdga import RDGAConfig, position_colors, position_image, rdga_loss
from gca.eval.efficiency import synced_clock
from gca.render.camera import Camera
from gca.scenes.store import ViewData
from gca.scenes.world import Body, gaussians_at, render_gaussians
from gca.sim.cfl import CFLError
from gca.sim.rollout import Rollout, SimulationDiverged, rollout
from gca.sim.solver import MPMSolver
from gca.train.config import TrainConfig
from gca.train.law import LearnedLaw
from gca.train.methods import Method
from gca.train.probe import GradProbe
from gca.vision.matching import MatchConfig, match_cached

# CFLError: the law stiffened until the scene's dt no longer resolves its waves: the rollout cannot be
# trusted, like one that blew up (an update that does this is rejected, not a crash)
DIVERGENCE_ERRORS = (SimulationDiverged, FloatingPointError, CFLError)


@dataclasses.dataclass
class TrainData:
    """Everything a method may observe (never the ground-truth trajectory).

    Attributes:
        body: particles + Gaussians (sim frame).
        views: training views (``train0`` first), frames at ``video_frames``.
        video_frames: simulated-frame index of each video frame [T].
        substeps: MPM steps per simulated frame.
        est_depth: estimated relative depth of ``train0`` [T, H, W].
        keypoints: cached SIFT (keypoints [K,2], descriptors [K,128]) of ``train0`` per frame.
        v_init: estimated initial velocity field [P, 3] (m/s).
        background: render background RGB.
    """

    body: Body
    views: dict[str, ViewData]
    video_frames: list[int]
    substeps: int
    est_depth: np.ndarray
    keypoints: list[tuple[np.ndarray, np.ndarray]]
    v_init: torch.Tensor
    background: tuple[float, float, float]


@dataclasses.dataclass
class TrainResult:
    status: str  # "ok" | "diverged"
    iterations: int
    history: list[dict]
    message: str = ""
    seconds: float = 0.0
    rejected: list[dict] = dataclasses.field(default_factory=list)  # {"iteration", "message", "lr_scale"}
    selected: dict = dataclasses.field(default_factory=dict)  # which law was kept (:class:`_Best`)
    resumed_at: int = 0  # the iteration this process resumed from (0: a fresh run)
    seconds_before: float = 0.0  # training time of the earlier processes of a resumed run [s]


def horizon(cfg: TrainConfig, it: int, n_video: int) -> int:
    """Number of video frames supervised at iteration ``it`` (linear growth, then all)."""
    ramp = max(1.0, cfg.curriculum_until * cfg.iterations)
    frac = cfg.curriculum_start + (1.0 - cfg.curriculum_start) * min(1.0, it / ramp)
    return max(1, min(n_video, math.ceil(frac * n_video)))


def simulate(solver: MPMSolver, law: LearnedLaw, data: TrainData, n_video: int) -> Rollout:
    """Differentiable rollout up to the ``n_video``-th video frame."""
    n_frames = data.video_frames[n_video - 1]
    b = data.body
    return rollout(solver, law.material, b.x0, data.v_init, b.vol, b.mass,
                   n_steps=n_frames * data.substeps, steps_per_frame=data.substeps, checkpoint=True)


def position_image_ref(body: Body, means: torch.Tensor, covs: torch.Tensor, camera: Camera,
                       gradient: str = "material") -> torch.Tensor:
    """Premultiplied camera-frame positions [H, W, 3] in a separate render pass: the slow reference of
    :meth:`Objective._render` (which composites them with the colours in one pass). With ``gradient=
    "material"`` the Gaussians' geometry is detached, so only the composited positions carry a gradient."""
    xyz_cam = camera.to_camera(means)
    if gradient == "material":
        means, covs = means.detach(), covs.detach()
    return render_gaussians(body, means, covs, xyz_cam, camera, means.new_zeros(3))["rgb"]


def to_uint8(rgb: torch.Tensor) -> np.ndarray:
    """RGB in [0, 1] [..., 3] -> uint8 on the host (converted on the tensor's device, copied once)."""
    return (rgb.detach().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


class Objective:
    """The method's loss at one video frame (all views), plus CPR on the frame's deformation gradients."""

    def __init__(self, method: Method, data: TrainData, cfg: TrainConfig, rdga: RDGAConfig,
                 cpr_cfg: CPRConfig, match: MatchConfig, cpr_target: tuple[str, str] = ("", "")):
        self.method, self.data, self.cfg, self.match = method, data, cfg, match
        self.probe: GradProbe | None = None  # set per iteration by _gradient (gradient provenance)
        self.rdga = dataclasses.replace(rdga, **dict(method.rdga))
        # the train0 RDGA terms: the full config with ``geo``, silhouette only with ``mask``, none otherwise
        self.train0_rdga = self.rdga if method.geo else (
            dataclasses.replace(self.rdga, use_global=False, use_anchor=False) if method.mask else None)
        self.cpr = None
        if method.cpr:
            if method.cpr_remove_target:
                cpr_cfg = dataclasses.replace(
                    cpr_cfg, elastic=tuple(h for h in cpr_cfg.elastic if h != cpr_target[0]),
                    plastic=tuple(h for h in cpr_cfg.plastic if h != cpr_target[1]))
            self.cpr = CPR(cpr_cfg, data.body.n_particles, seed=cfg.seed)
        x0 = data.body.x0
        self.bg = torch.tensor(data.background, dtype=x0.dtype, device=x0.device)
        self.rgb = {n: torch.as_tensor(v.rgb, device=x0.device) for n, v in data.views.items()}
        self.mask = torch.as_tensor(data.views["train0"].mask, device=x0.device)
        self.est_depth = torch.as_tensor(data.est_depth, dtype=x0.dtype, device=x0.device)
        self.K = {n: torch.tensor(np.array(v.camera.K), dtype=x0.dtype, device=x0.device) for n, v in data.views.items()}

    def loss(self, traj: Rollout, n_video: int, law: LearnedLaw) -> tuple[torch.Tensor, dict]:
        """Sum of the method's losses over video frames ``0 .. n_video - 1`` (CPR's in one call, with its
        graph: the reference of :meth:`prior_gradient`) and their mean stats."""
        loss, stats = self._image_terms(traj, n_video)
        if self.cpr is not None:
            loss = loss + self._cpr_terms(traj, n_video, law, stats)
        return loss, stats.read()

    def data_loss(self, traj: Rollout, n_video: int) -> tuple[torch.Tensor, dict]:
        """The image terms alone (training takes CPR's part from :meth:`prior_gradient`) and their stats."""
        loss, stats = self._image_terms(traj, n_video)
        return loss, stats.read()

    def _image_terms(self, traj: Rollout, n_video: int) -> tuple[torch.Tensor, "_MeanStats"]:
        """The image terms summed over video frames ``0 .. n_video - 1`` and their per-frame stats.

        Three passes, so the GPU is never waited on frame by frame: render every frame (all views)
        back to back; copy the frames that need feature matching to the host at once and match them
        in a thread pool (OpenCV releases the GIL); then the per-frame losses. The stats are read
        back in one transfer at the end.
        """
        renders = [self._render_frame(traj, j) for j in range(n_video)]
        matches = self._match_frames([r["train0"] for r in renders]) if self._needs_matches() else [None] * n_video
        loss, stats = traj.x.new_zeros(()), _MeanStats(n_video)
        for j in range(n_video):
            l_j = self._frame_loss(traj, j, renders[j], matches[j], stats)
            loss = loss + l_j
        return loss, stats

    def _cpr_frames(self, n_video: int) -> list[int]:
        """Simulated frames CPR regularises: every ``cpr_every``-th supervised video frame."""
        return self.data.video_frames[0:n_video:self.cfg.cpr_every]

    def _cpr_call(self, traj: Rollout, frames: list[int], law: LearnedLaw) -> tuple[torch.Tensor, torch.Tensor]:
        """(R_e, R_p) summed over ``frames``: their elastic F_e^t and the trial F of each one's last Euler
        step, in one batched call (frame by frame, each call costs a few hundred small launches)."""
        F_e = torch.stack([traj.F[i] for i in frames])  # [B, N, 3, 3]
        F_trial = torch.stack([traj.F_trial[i] for i in frames])
        R_e, R_p, _ = self.cpr.residuals_frames(law.material.elasticity, law.material.plasticity, F_e, F_trial)
        return R_e, R_p

    def _cpr_terms(self, traj: Rollout, n_video: int, law: LearnedLaw, stats: "_MeanStats") -> torch.Tensor:
        """CPR (Algorithm 2) on every ``cpr_every``-th supervised frame's state, all frames in one call,
        with its graph: the reference for :meth:`prior_gradient`."""
        R_e, R_p = self._cpr_call(traj, self._cpr_frames(n_video), law)
        stats.add("R_e", R_e)  # sums over the CPR frames; read() divides by n_video, as frame by frame
        stats.add("R_p", R_p)
        return R_e + R_p

    def prior_gradient(self, traj: Rollout, n_video: int, law: LearnedLaw,
                       params: list[torch.Tensor]) -> tuple[torch.Tensor, list, dict[str, float]]:
        """CPR's value and gradient, ``chunk_frames`` frames at a time, each chunk's graph freed before
        the next: the neural law evaluated on every particle of every CPR frame keeps its activations for
        backward (127k particles x 25 frames: ~9 GiB), a chunk only its share.

        Returns ``(R_e + R_p detached [], [grad of each param or None], {"R_e", "R_p"} as the stats
        report them: divided by ``n_video``)``. Equal to differentiating :meth:`_cpr_terms` (test).
        """
        frames = self._cpr_frames(n_video)
        size = self.cpr.cfg.chunk_frames or len(frames)
        grads: list = [None] * len(params)
        total_e = total_p = None
        for start in range(0, len(frames), size):
            R_e, R_p = self._cpr_call(traj, frames[start:start + size], law)
            # without detach_F the chunk's graph reaches the rollout, which the image terms still need
            g = torch.autograd.grad(R_e + R_p, params, allow_unused=True, retain_graph=not self.cpr.cfg.detach_F)
            grads = [a if b is None else (b if a is None else a + b) for a, b in zip(grads, g)]
            total_e = R_e.detach() if total_e is None else total_e + R_e.detach()
            total_p = R_p.detach() if total_p is None else total_p + R_p.detach()
        R_e, R_p = torch.stack([total_e, total_p]).double().tolist()
        return total_e + total_p, grads, {"R_e": R_e / n_video, "R_p": R_p / n_video}

    def _render_frame(self, traj: Rollout, j: int) -> dict[str, dict]:
        """Every view's render outputs at video frame ``j`` (0-based)."""
        f = self.data.video_frames[j]
        means, covs = gaussians_at(self.data.body, traj.x[f], traj.F[f])
        if self.probe is not None:
            self.probe.watch("gaussians", "means", j, means)
            self.probe.watch("gaussians", "covariances", j, covs)
        outs = {}
        for name, view in self.data.views.items():
            outs[name] = self._render(means, covs, view, with_positions=name == "train0" and self._needs_positions())
            if self.probe is not None:
                for key, image in outs[name].items():
                    self.probe.watch("render outputs", f"{name}/{key}", j, image)
        return outs

    def _frame_loss(self, traj: Rollout, j: int, outs: dict[str, dict], pq, stats: "_MeanStats") -> torch.Tensor:
        """Loss at video frame ``j`` from its renders ``outs`` and train0 matches ``pq`` (or None)."""
        loss = traj.x.new_zeros(())
        for name, out in outs.items():
            if self.method.color:
                l_color = (out["rgb"] - self.rgb[name][j]).square().mean()
                loss = loss + self.cfg.lambda_color * l_color
                stats.add(f"color/{name}", l_color)
            if name == "train0":
                loss = loss + self._mono_terms(out, pq, j, stats)
        return loss

    def _needs_positions(self) -> bool:
        rdga = self.train0_rdga
        return rdga is not None and rdga.enabled and rdga.use_global

    def _needs_matches(self) -> bool:
        rdga = self.train0_rdga
        return rdga is not None and rdga.enabled and (rdga.use_global or rdga.use_anchor)

    def _match_frames(self, outs: list[dict]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Matches (p [M, 2] in the render, q [M, 2] in the GT frame) of every frame's train0 render,
        from one host copy of all frames and a thread pool of SIFT detections."""
        frames = to_uint8(torch.stack([o["rgb"] for o in outs]))
        keypoints = self.data.keypoints
        work = lambda j: match_cached(frames[j], *keypoints[j], self.match)  # noqa: E731
        return list(_match_pool().map(work, range(len(frames))))

    def _render(self, means, covs, view: ViewData, with_positions: bool) -> dict:
        """RGB/alpha/depth; with ``with_positions`` also the premultiplied camera-frame positions
        [H, W, 3] of RDGA's global term, composited in the same pass as 3 extra colour channels
        (background 0), so the frame is rasterized once."""
        body = self.data.body
        if not with_positions:
            return render_gaussians(body, means, covs, body.colors, view.camera, self.bg)
        extra = position_colors(view.camera.to_camera(means), self.train0_rdga.global_gradient)
        out = render_gaussians(body, means, covs, torch.cat([body.colors, extra], 1), view.camera,
                               torch.cat([self.bg, self.bg.new_zeros(extra.shape[1])]))
        return {**out, "rgb": out["rgb"][..., :3],
                "positions": position_image(out["rgb"][..., 3:], self.train0_rdga.global_gradient)}

    def _mono_terms(self, out: dict, pq, j: int, stats: "_MeanStats") -> torch.Tensor:
        """Monocular terms of train0 at frame ``j``: L1 depth (PAC-NeRF + depth) and silhouette/RDGA."""
        loss = out["alpha"].new_zeros(())
        if self.method.depth_l1:
            mask, est = self.mask[j], self.est_depth[j]
            l_depth = (out["depth"] - est).abs()[mask].mean() if mask.any() else out["depth"].sum() * 0.0
            loss = loss + self.cfg.lambda_depth_l1 * l_depth
            stats.add("depth_l1", l_depth)
        rdga = self.train0_rdga
        if rdga is not None:
            p, q = pq if pq is not None else (np.zeros((0, 2), np.float32),) * 2
            # "positions" is rendered exactly when the global term needs it (_needs_positions)
            l_rdga, s = rdga_loss(out, self.mask[j], self.est_depth[j], p, q, rdga, pos_image=out.get("positions"),
                                  K=self.K["train0"])
            loss = loss + l_rdga
            for k, v in s.items():
                stats.add(f"rdga/{k}", v)
        return loss


class _MeanStats:
    """Per-frame statistics averaged over ``n`` frames; tensors are read back in one transfer."""

    def __init__(self, n: int):
        self.n, self.values = n, {}

    def add(self, key: str, value) -> None:
        value = value.detach() if isinstance(value, torch.Tensor) else float(value)
        self.values[key] = self.values[key] + value if key in self.values else value

    def read(self) -> dict[str, float]:
        keys = [k for k, v in self.values.items() if isinstance(v, torch.Tensor)]
        read = dict(zip(keys, torch.stack([self.values[k].double() for k in keys]).tolist())) if keys else {}
        return {k: read.get(k, v) / self.n for k, v in self.values.items()}


@functools.cache
def _match_pool() -> ThreadPoolExecutor:
    """Threads for the per-frame SIFT matching (OpenCV releases the GIL)."""
    return ThreadPoolExecutor(max_workers=max(1, min(8, os.cpu_count() or 1)), thread_name_prefix="gca-match")


class _Schedule:
    """Cosine decay from each group's lr to ``cosine_floor`` of it, times a backtracking scale.

    ``scale`` starts at 1 and shrinks by ``backtrack_factor`` at each rejected update; it is part of
    the checkpoint so a resumed run keeps the smaller steps.
    """

    def __init__(self, opt: torch.optim.Optimizer, cfg: TrainConfig):
        self.opt, self.cfg, self.scale = opt, cfg, 1.0
        self.base = [g["lr"] for g in opt.param_groups]
        self.it = 0
        self._apply()

    def factor(self, it: int) -> float:
        c, floor = self.cfg, self.cfg.cosine_floor
        return self.scale * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * min(it, c.iterations) / c.iterations)))

    def _apply(self, it: int | None = None) -> None:
        for group, base in zip(self.opt.param_groups, self.base):
            group["lr"] = base * self.factor(self.it if it is None else it)

    def step(self) -> None:
        self.it += 1
        self._apply()

    def shrink(self) -> None:
        self.scale *= self.cfg.backtrack_factor
        self._apply()

    def state_dict(self) -> dict:
        return {"it": self.it, "scale": self.scale}

    def load_state_dict(self, state: dict) -> None:
        self.it = int(state.get("it", state.get("last_epoch", 0)))  # LambdaLR checkpoints: last_epoch
        self.scale = float(state.get("scale", 1.0))
        self._apply()


def _optimizer(law: LearnedLaw, cfg: TrainConfig):
    opt = torch.optim.Adam([{"params": g["params"], "lr": g["lr"]} for g in law.groups])
    return opt, _Schedule(opt, cfg)


class _Undo:
    """What one optimiser update changed, so it can be taken back and retaken with a smaller lr:
    the parameters and Adam's state before it, the (clipped) gradient it used and its schedule step."""

    def __init__(self, law: LearnedLaw, opt: torch.optim.Optimizer, sched: _Schedule):
        params = law.trainable()
        self.params = [p.detach().clone() for p in params]
        self.grads = [None if p.grad is None else p.grad.detach().clone() for p in params]
        self.opt_state = copy.deepcopy(opt.state_dict())
        self.it = sched.it

    def restore(self, law: LearnedLaw, opt: torch.optim.Optimizer) -> None:
        """The parameters, gradients and Adam state as they were before the update (lrs untouched)."""
        with torch.no_grad():
            for p, saved, g in zip(law.trainable(), self.params, self.grads):
                p.copy_(saved)
                p.grad = None if g is None else g.clone()
        lrs = [group["lr"] for group in opt.param_groups]
        opt.load_state_dict(copy.deepcopy(self.opt_state))
        for group, lr in zip(opt.param_groups, lrs):  # load_state_dict brings the old lrs back too
            group["lr"] = lr

    def retake(self, law: LearnedLaw, opt: torch.optim.Optimizer, sched: _Schedule) -> None:
        """Restore, then step again from the same gradient at the update's own schedule step and the
        schedule's current (shrunk) scale."""
        self.restore(law, opt)
        sched._apply(self.it)
        opt.step()
        sched._apply()


def _save_checkpoint(path: Path, law: LearnedLaw, opt, sched, it: int, history: list, rejected: list,
                     best: _Best, seconds: float) -> None:
    from gca.io import save_torch
    save_torch({"law": law.state(), "opt": opt.state_dict(), "sched": sched.state_dict(), "iteration": it,
                "history": history, "rejected": rejected, "best": best.state(), "seconds": seconds}, path)


def _resume(path: Path | None, law: LearnedLaw, opt, sched, best: _Best) -> tuple[int, list, list, float]:
    """Load a checkpoint into the law, optimiser, schedule and best-law tracker; returns
    ``(iteration, history, rejected updates, training seconds spent before it)``."""
    if path is None or not path.is_file():
        return 0, [], [], 0.0
    ckpt = torch.load(path, weights_only=False, map_location=law.trainable()[0].device)
    law.load_state(ckpt["law"])
    opt.load_state_dict(ckpt["opt"])
    sched.load_state_dict(ckpt["sched"])
    best.load(ckpt.get("best"))
    return (int(ckpt["iteration"]), list(ckpt["history"]), list(ckpt.get("rejected", [])),
            float(ckpt.get("seconds", 0.0)))


def train(solver: MPMSolver, law: LearnedLaw, data: TrainData, objective: Objective, cfg: TrainConfig,
          checkpoint_path: Path | None = None, on_iteration: Callable[[int, dict], None] | None = None) -> TrainResult:
    """Run the optimisation; returns the status, the per-iteration history and the rejected updates."""
    start = time.perf_counter()
    if not law.trainable():
        return TrainResult("ok", 0, [], "nothing to train", 0.0)
    opt, sched = _optimizer(law, cfg)
    best = _Best()
    it0, history, rejected, seconds_before = _resume(checkpoint_path, law, opt, sched, best)
    resumed = {"resumed_at": it0, "seconds_before": seconds_before}
    n_video = len(data.video_frames)
    undo, in_a_row = None, 0  # the last update (none yet after a resume: it is not in the checkpoint)
    bar = tqdm(total=cfg.iterations, desc="train", unit="it", initial=it0)
    it = it0
    while it < cfg.iterations:
        try:
            record = _gradient(solver, law, data, objective, cfg, horizon(cfg, it, n_video))
        except DIVERGENCE_ERRORS as exc:
            message = f"{type(exc).__name__}: {exc}"
            if undo is None or in_a_row >= cfg.max_rejections:
                why = "before any update" if undo is None else f"after {in_a_row} rejected updates in a row"
                if undo is not None:  # keep the last law whose rollout was finite
                    undo.restore(law, opt)
                selected = {"rule": "last finite"}
                if cfg.keep == "best" and best.params is not None:  # its loss is <= the last finite law's
                    best.restore(law)
                    selected = {"rule": "best", "iteration": best.iteration, "loss": best.loss}
                bar.close()
                return TrainResult("diverged", it, history, f"{message} ({why})", time.perf_counter() - start,
                                   rejected, selected, **resumed)
            sched.shrink()
            undo.retake(law, opt, sched)
            in_a_row += 1
            rejected.append({"iteration": it, "message": message, "lr_scale": sched.scale})
            bar.set_postfix(rejected=len(rejected))
            continue
        in_a_row = 0
        if record["horizon"] == n_video:
            best.offer(law, record["loss"], it)
        undo = _Undo(law, opt, sched)
        t0 = time.perf_counter()
        opt.step()
        record["time/optimizer"] = time.perf_counter() - t0
        sched.step()
        record["iteration"] = it
        record["lr_scale"] = sched.scale
        history.append(record)
        if on_iteration:
            on_iteration(it, record)
        it += 1
        bar.update(1)
        if checkpoint_path is not None and (it % cfg.checkpoint_every == 0 or it == cfg.iterations or stop.requested()):
            _save_checkpoint(checkpoint_path, law, opt, sched, it, history, rejected, best,
                             seconds_before + time.perf_counter() - start)
        stop.check()  # SIGTERM under gca.stop.deferred: stop here, checkpointed
    bar.close()
    selected = (_select(best, undo, solver, law, data, objective, cfg, n_video, history, opt) if cfg.keep == "best"
                else {"rule": "last"})
    return TrainResult("ok", cfg.iterations, history, "", time.perf_counter() - start, rejected, selected, **resumed)


class _Best:
    """The law with the lowest training loss over the whole video so far: its trainable parameters,
    loss and iteration (the loss of iteration ``it`` is that of the law *before* update ``it``)."""

    def __init__(self):
        self.loss, self.iteration, self.params = math.inf, None, None

    def offer(self, law: LearnedLaw, loss: float, it: int) -> None:
        if loss < self.loss:
            self.loss, self.iteration = loss, it
            self.params = [p.detach().clone() for p in law.trainable()]

    def restore(self, law: LearnedLaw) -> None:
        params = law.trainable()
        if len(params) != len(self.params):
            raise ValueError(f"gca/train/loop.py: the best law has {len(self.params)} parameter tensors, "
                             f"the law {len(params)} (a checkpoint of another method?)")
        with torch.no_grad():
            for p, saved in zip(params, self.params):
                p.copy_(saved)

    def state(self) -> dict:
        return {"loss": self.loss, "iteration": self.iteration, "params": self.params}

    def load(self, state: dict | None) -> None:
        if state:
            self.loss, self.iteration, self.params = float(state["loss"]), state["iteration"], state["params"]


def _select(best: _Best, undo, solver, law, data, objective, cfg, n_video: int, history: list, opt) -> dict:
    """Keep the best law seen: the final law (never evaluated during the loop: its loss comes after the
    last update) is evaluated once over the whole video, and replaced by the best earlier one when that
    one's loss is lower or the final rollout diverges (with no earlier full-video loss to compare with,
    a diverging final law is replaced by the law before the last update)."""
    try:
        final = _gradient(solver, law, data, objective, cfg, n_video)["loss"]
    except DIVERGENCE_ERRORS:
        final = math.inf
    if best.params is not None and best.loss < final:
        best.restore(law)
        kept = {"iteration": best.iteration, "loss": best.loss}
    elif math.isinf(final) and undo is not None:
        undo.restore(law, opt)
        kept = {"iteration": cfg.iterations - 1, "loss": history[-1]["loss"],
                "note": "the final law diverged; the law before the last update is kept"}
    else:
        kept = {"iteration": cfg.iterations, "loss": final}
    for p in law.trainable():  # the evaluation's (or the undone update's) gradient is not the kept law's
        p.grad = None
    return {"rule": "best", "final_loss": final, "best_earlier_loss": best.loss,
            "best_earlier_iteration": best.iteration, **kept}


class PhaseTimer:
    """Wall time per phase [s], synchronising CUDA so asynchronous kernels are charged to their phase."""

    def __init__(self, device: torch.device):
        self.device, self.seconds, self._t = device, {}, None

    def _now(self) -> float:
        return synced_clock(self.device)

    def start(self) -> None:
        self._t = self._now()

    def lap(self, phase: str) -> None:
        t = self._now()
        self.seconds[phase] = self.seconds.get(phase, 0.0) + t - self._t
        self._t = t


def _gradient(solver, law, data, objective, cfg, n_video) -> dict:
    """Rollout, losses, backward and clipping: the law's ``.grad`` is ready for the update.

    Returns the iteration's record (loss, gradient norm before clipping, horizon, stats, phase times).
    Raises one of ``DIVERGENCE_ERRORS`` when the rollout, the loss or a gradient is not usable.
    """
    timer = PhaseTimer(data.body.x0.device)
    timer.start()
    for p in law.trainable():
        p.grad = None
    traj = simulate(solver, law, data, n_video)
    probe = objective.probe = GradProbe()
    probe.watch("particles", "x", -1, traj.x)
    probe.watch("particles", "F", -1, traj.F)
    timer.lap("simulate")
    params = law.trainable()
    prior = objective.cpr is not None
    # CPR first, chunk by chunk, so its activations are gone before the frames are rendered
    prior_value, g_prior, prior_stats = objective.prior_gradient(traj, n_video, law, params) if prior else (0.0, None, {})
    data_loss, stats = objective.data_loss(traj, n_video)
    stats.update(prior_stats)
    loss = data_loss.detach() + prior_value
    if not torch.isfinite(loss):
        raise FloatingPointError(f"non-finite training loss {float(loss)} (stats {stats})")
    _check_drift(traj, data, n_video, cfg)
    timer.lap("render_losses")
    if data_loss.requires_grad:
        data_loss.backward()
    if prior:  # a method without image terms (no_rdga) has only the prior to follow: nothing to cap it to
        ratio = objective.cpr.cfg.max_grad_ratio if data_loss.requires_grad else 0.0
        stats.update(add_prior_gradient(params, g_prior, ratio))
    timer.lap("backward")
    _check_gradients(law, probe)
    grad_norm = torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
    return {"loss": float(loss), "grad_norm": float(grad_norm), "horizon": n_video, "sim_refine": traj.refine, **stats,
            **{f"time/{k}": v for k, v in timer.seconds.items()}}


def add_prior_gradient(params: list[torch.Tensor], g_prior: list, ratio: float) -> dict[str, float]:
    """Add the prior's gradient ``g_prior`` to the data terms' gradient already in ``.grad``, scaled by
    ``s = min(1, ratio * |g_data| / |g_prior|)`` when ``ratio > 0`` (else s = 1: the loss as written): the
    prior steers, the data lead (CPR's residuals act on the law's weights directly, the image terms
    through a whole rollout, so their gradients differ by orders of magnitude; benchmarks/NOTES.md,
    session 8). Norms are over all ``params``.

    Returns ``{"grad_norm_data", "grad_norm_prior", "prior_scale"}``.
    """
    zero = params[0].new_zeros((), dtype=torch.float64)
    norm = lambda gs: torch.stack([zero] + [g.double().square().sum() for g in gs if g is not None]).sum().sqrt()  # noqa: E731
    n_data, n_prior = norm([p.grad for p in params]), norm(g_prior)
    scale = torch.clamp(ratio * n_data / n_prior.clamp(min=1e-300), max=1.0) if ratio > 0 else zero + 1.0
    with torch.no_grad():
        for p, g in zip(params, g_prior):
            if g is not None:
                p.grad = g * scale.to(g.dtype) if p.grad is None else p.grad + g * scale.to(g.dtype)
    n_data, n_prior, scale = torch.stack([n_data, n_prior, scale]).tolist()
    return {"grad_norm_data": n_data, "grad_norm_prior": n_prior, "prior_scale": scale}


def _check_gradients(law: LearnedLaw, probe: GradProbe | None = None) -> None:
    """Raise FloatingPointError naming the parameter groups whose gradients are non-finite (never zeroed)
    and, with a probe, where along the loss -> render -> Gaussians -> particles chain they broke."""
    bad = []
    for group in law.groups:
        n_bad = sum(int((~torch.isfinite(p.grad)).sum()) for p in group["params"] if p.grad is not None)
        if n_bad:
            bad.append(f"{group['name']}: {n_bad} non-finite gradient entries")
    if bad:
        where = f"; provenance: {probe.report()}" if probe is not None else ""
        raise FloatingPointError("non-finite gradients after backward (" + "; ".join(bad) + ")" + where)


def _check_drift(traj: Rollout, data: TrainData, n_video: int, cfg: TrainConfig) -> None:
    """Particles drifting far from where they started in a way no object moves: treated as divergence."""
    with torch.no_grad():
        last = traj.x[data.video_frames[n_video - 1]]
        spread = (last - last.mean(0)).norm(dim=1).max()
        spread0 = (data.body.x0 - data.body.x0.mean(0)).norm(dim=1).max()
    if float(spread) > spread0 + cfg.max_spread_growth:
        raise FloatingPointError(f"rollout blew up: particle spread {float(spread):.3g} m vs {float(spread0):.3g} m "
                                 f"at rest (limit +{cfg.max_spread_growth} m)")
