"""A method's training objective: its declared loss terms on the rendered video frames, and their gradient.

``Objective.gradient`` is the one function training differentiates (the paper's eq. 8 for GCA; the method's
declared terms for every other row, ``gca.train.methods.TERMS``). ``TrainData`` is everything a method may
observe: training views, estimated depth, masks made from the frames, keypoints, the launch velocity; never
the ground-truth trajectory.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

import numpy as np
import torch

from gca.align.cpr import CPR, CPRConfig
from gca.align.rdga import RDGAConfig, judge as judge_rdga, position_colors, position_image, rdga_frames
from gca.render.camera import Camera
from gca.render.rasterize import judge_inputs
from gca.scenes.store import ViewData
from gca.scenes.world import Body, body_colors, gaussians_at, render_gaussians
from gca.sim.rollout import Rollout
from gca.train.config import TrainConfig
from gca.train.law import LearnedLaw
from gca.train.methods import Method
from gca.train.probe import GradProbe
from gca.vision.matching import MatchConfig, match_frame, rgb_uint8


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


def position_image_ref(body: Body, means: torch.Tensor, covs: torch.Tensor, camera: Camera,
                       gradient: str = "material") -> torch.Tensor:
    """Premultiplied camera-frame positions [H, W, 3] in a separate render pass: the slow reference of
    :meth:`Objective._render` (which composites them with the colours in one pass). With ``gradient=
    "material"`` the Gaussians' geometry is detached, so only the composited positions carry a gradient."""
    xyz_cam = camera.to_camera(means)
    if gradient == "material":
        means, covs = means.detach(), covs.detach()
    return render_gaussians(body, means, covs, xyz_cam, camera, means.new_zeros(3))["rgb"]


def to_uint8(rgb: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 1] [..., 3] -> uint8 (rounded), on the tensor's device and without its graph."""
    return (rgb.detach().clamp(0, 1) * 255 + 0.5).to(torch.uint8)


class Objective:
    """A method's training objective over the supervised video frames: its declared loss terms
    (``Method.terms``: colour, L1 depth, silhouette, global and anchor alignment, CPR) and their gradient.

    :meth:`gradient` is what training differentiates; :meth:`loss` is its reference (every term with its
    graph, CPR in one call, no gradient scaling), used by tests and ``benchmarks/grad_terms.py``.
    """

    def __init__(self, method: Method, data: TrainData, cfg: TrainConfig, rdga: RDGAConfig,
                 cpr_cfg: CPRConfig, match: MatchConfig, cpr_target: tuple[str, str] = ("", "")):
        self.method, self.data, self.cfg, self.match = method, data, cfg, match
        self.probe: GradProbe | None = None  # set by loop._provenance only (a replay after a non-finite gradient)
        self._weights: torch.Tensor | None = None  # the current frames' weights in the loss [T], for the shares' terms
        self.frame_weights: list[float] | None = None  # per video frame, set per iteration by the loop (NeuMA's rollout weighting)
        self._terms: dict[str, torch.Tensor] | None = None  # per-term sums, collected only for term shares
        self._checks: list | None = None  # the rasterizer's input stats of the frames being rendered (_render_frames)
        self.last_term_grads: dict[str, list] | None = None  # each term's gradient of the last gradient(shares=True)
        self.last_shares_summed = False  # whether that gradient was its terms' gradients summed (no extra pass)
        switches = method.rdga_switches()  # the method's RDGA terms (silhouette, global, anchor) or None
        self.rdga = dataclasses.replace(rdga, **(switches or {}))
        self.train0_rdga = self.rdga if switches else None  # RDGA on train0, as the method's terms set it
        self.cpr = None
        if method.uses("cpr"):
            if method.cpr_remove_target:
                cpr_cfg = dataclasses.replace(
                    cpr_cfg, elastic=tuple(h for h in cpr_cfg.elastic if h != cpr_target[0]),
                    plastic=tuple(h for h in cpr_cfg.plastic if h != cpr_target[1]))
            self.cpr = CPR(cpr_cfg, data.body.n_particles, seed=cfg.seed)
        x0 = data.body.x0
        self.bg = torch.tensor(data.background, dtype=x0.dtype, device=x0.device)
        self.rgb = {n: torch.as_tensor(v.rgb, device=x0.device) for n, v in data.views.items()}
        self.mask = torch.as_tensor(data.views["train0"].mask, device=x0.device)
        # the matcher's side of train0 (host, once): its video frames and masks (backend "flow" matches images)
        train0 = data.views["train0"]
        self._gt_u8 = rgb_uint8(train0.rgb)
        self._gt_mask = np.asarray(train0.mask, bool)
        self.est_depth = torch.as_tensor(data.est_depth, dtype=x0.dtype, device=x0.device)
        self.K = {n: torch.tensor(np.array(v.camera.K), dtype=x0.dtype, device=x0.device) for n, v in data.views.items()}

    def state(self) -> dict:
        """What the objective carries from one iteration to the next (CPR's call count and fits), for a
        training checkpoint: without it a resumed run would refit CPR where the uninterrupted one reuses."""
        return {"cpr": None if self.cpr is None else self.cpr.state()}

    def load_state(self, state: dict | None) -> None:
        """Continue from :meth:`state` (None or no CPR state: nothing to restore)."""
        if state and state.get("cpr") is not None and self.cpr is not None:
            self.cpr.load_state(state["cpr"])

    def gradient(self, traj: Rollout, n_video: int, law: LearnedLaw,
                 lap: Callable[[str], None] = lambda phase: None, shares: bool = False,
                 on_rendered: Callable[[], None] = lambda: None) -> tuple[torch.Tensor, dict]:
        """The training loss over video frames ``0 .. n_video - 1`` and its gradient, left in the law's
        trainable parameters' ``.grad`` (which must be None or zero on entry).

        For GCA this is the paper's eq. 8, summed over the supervised frames f of the curriculum horizon:

            L = sum_f lambda_m L_mask(f) + lambda_g L_geo(f) + R_e(f) + R_p(f),
            L_geo = lambda_1 ||P_render - P_gt||_2 + lambda_2 sum_A (-gamma_i)      (eq. 7)

        and for every other method the sum of its declared terms (``Method.terms``; colour L2 for NeuMA).

        Departures from the paper (each a params knob, ``docs/architecture.md``):
        - R_e + R_p are taken on every ``train.cpr_every``-th supervised frame, ``align.cpr.chunk_frames``
          frames at a time (each chunk's graph freed before the next: the same gradient, less memory);
        - CPR's gradient is scaled by ``s = min(1, align.cpr.max_grad_ratio * |g_image| / |g_cpr|)`` before it
          is added to the image terms' (:func:`add_prior_gradient`; 0 = as written). The reported loss is
          the unscaled sum.

        Args:
            traj: the law's differentiable rollout; n_video: supervised video frames (the horizon).
            law: the law being trained; lap: called with "render_losses" and "backward" as each phase ends.
            on_rendered: a swept rollout's checks (e.g. the caller's drift check), called once its frames are
                rendered, after the rollout's own health checks (:meth:`gca.sim.rollout.ReverseSweep.judge`).
            shares: also each declared term's gradient (``torch.autograd.grad`` of that term alone, one backward
                pass per image term; ``train.term_shares_every``): its norm and its cosine with the total
                gradient go into the stats (:func:`term_shares`), the gradients into ``last_term_grads``.
                CPR's is the gradient as added (x ``prior_scale``). The total applied is the image terms' gradients
                summed where the terms add up to the data loss (as ``_collect`` makes them; checked on the values),
                else one more pass of the data loss. Off: the cost is unchanged.

        Returns:
            ``(loss, stats)``: the loss value (detached scalar) and the per-term means over the frames.

        Raises:
            FloatingPointError: a non-finite loss (before any backward; on a swept rollout after the frames' adjoints
                were queued, which are then abandoned: no gradient is added).
        """
        if traj.sweep is not None:
            if shares:
                raise ValueError("gca/train/objective.py: term shares differentiate each term through the whole "
                                 "rollout's graph; simulate without sweep for them")
            return self._gradient_swept(traj, n_video, law, lap, on_rendered)
        params = law.trainable()
        prior = self.cpr is not None
        self._terms = {} if shares else None
        try:
            # the frames first, then CPR chunk by chunk while the host matches train0's frames (the SIFT
            # threads overlap CPR's GPU work instead of following it); then the frames' losses
            renders = self._render_frames(traj, n_video)
            matching = self._start_matching(renders)
            prior_value, g_prior, prior_stats = self.prior_gradient(traj, n_video, law, params) if prior \
                else (0.0, None, {})
            data_loss, mean_stats = self._frame_losses(traj, renders, matching)
            stats = mean_stats.read()
        finally:
            collected, self._terms = self._terms, None
        stats.update(prior_stats)
        loss = data_loss.detach() + prior_value
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite training loss {float(loss)} (stats {stats})")
        lap("render_losses")
        term_grads: dict[str, list] = {}
        self.last_shares_summed = False
        if data_loss.requires_grad:
            terms = [(name, value) for name, value in (collected or {}).items() if value.requires_grad]
            summed = bool(terms) and _adds_up([value for _, value in terms], data_loss)
            for i, (name, value) in enumerate(terms):
                term_grads[name] = list(torch.autograd.grad(value, params, allow_unused=True,
                                                            retain_graph=not summed or i < len(terms) - 1))
            if summed:  # the terms add up to the data loss (_collect): its gradient is theirs summed, one backward
                # pass (a whole rollout's adjoint) fewer than differentiating it once more; equal to rounding (tested)
                _accumulate(params, [_sum_grads(gs) for gs in zip(*term_grads.values())])
                self.last_shares_summed = True
            else:
                data_loss.backward()
        if prior:  # a method without image terms (no_rdga) has only the prior to follow: nothing to cap it to
            ratio = self.cpr.cfg.max_grad_ratio if data_loss.requires_grad else 0.0
            stats.update(add_prior_gradient(params, g_prior, ratio))
            if shares:
                term_grads["cpr"] = [None if g is None else g * stats["prior_scale"] for g in g_prior]
        if shares:
            stats.update(term_shares(term_grads, [p.grad for p in params]))
            self.last_term_grads = term_grads
        lap("backward")
        return loss, stats

    def can_sweep(self) -> bool:
        """Whether :meth:`gradient` can take a swept rollout (``rollout(..., sweep=True)``): the image terms are
        per-frame functions of (x_f, F_f), and CPR, when used, does not differentiate through the rollout
        (``align.cpr.detach_F``)."""
        return self.cpr is None or self.cpr.cfg.detach_F

    def _gradient_swept(self, traj: Rollout, n_video: int, law: LearnedLaw, lap: Callable[[str], None],
                        on_rendered: Callable[[], None]) -> tuple[torch.Tensor, dict]:
        """:meth:`gradient` on a swept rollout: the same loss and, up to float rounding, the same gradient.

        The frames are rendered from autograd leaves of (x_f, F_f) (:class:`_FrameLeaves`) while the GPU still
        simulates, ``train.loss_chunk_frames`` at a time (their checks, the rollout's and ``on_rendered`` are read
        after the last one is queued); their train0 matching starts, last frame first; then the chunks' losses are
        evaluated **last chunk first**, each chunk's gradient with respect to its frames' (x_f, F_f) handed, last frame
        first, to the rollout's :class:`gca.sim.rollout.ReverseSweep`, which runs the adjoints of the later frames
        while the next chunk's losses are queued (on CUDA on a side stream: the losses' host work overlaps the
        simulator's backward instead of preceding it; with one chunk the adjoints follow all the losses); CPR's
        gradient is taken last, as in :meth:`gradient`, while the sweep finishes. The "render_losses" phase ends when CPR's gradient is
        queued, "backward" when the sweep is done and CPR's gradient added.
        """
        params = law.trainable()
        prior = self.cpr is not None
        self._terms = None
        view = _FrameLeaves(traj, self.data.video_frames[:n_video])
        try:
            renders = self._render_frames(view, n_video, first=lambda: (traj.sweep.judge(), on_rendered()))
            matching = self._start_matching(renders, last_first=True)
            data_loss, mean_stats = self._frame_losses(view, renders, matching, traj.sweep)
            prior_value, g_prior, prior_stats = self.prior_gradient(traj, n_video, law, params) if prior \
                else (0.0, None, {})
            stats = mean_stats.read()
            stats.update(prior_stats)
            loss = data_loss + prior_value
            if not torch.isfinite(loss):  # here after the frames' adjoints were queued (abandoned below)
                raise FloatingPointError(f"non-finite training loss {float(loss)} (stats {stats})")
        except BaseException:
            traj.sweep.abandon()  # the side stream's queued adjoints read the frames: wait for them, add nothing
            raise
        lap("render_losses")
        traj.sweep.finish()
        if prior:  # as in gradient(): no image term differentiable (no_rdga): the prior alone, unscaled
            stats.update(add_prior_gradient(params, g_prior, self.cpr.cfg.max_grad_ratio if traj.sweep.added else 0.0))
        lap("backward")
        return loss, stats

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

        Three passes, so the GPU is never waited on frame by frame: render every frame (all views),
        a chunk of frames per call; copy the frames that need feature matching to the host at once and match them
        in a thread pool (OpenCV releases the GIL); then the frames' losses, a chunk per call. The stats are read
        back in one transfer at the end. (:meth:`gradient` runs CPR between the second and the third.)
        """
        renders = self._render_frames(traj, n_video)
        return self._frame_losses(traj, renders, self._start_matching(renders))

    def _render_frames(self, traj, n_video: int, first: Callable[[], None] = lambda: None
                       ) -> list[tuple[range, dict[str, dict]]]:
        """Every view's render outputs at video frames ``0 .. n_video - 1`` (with their graphs), in chunks of
        ``train.loss_chunk_frames`` frames (0: one chunk), each ``(its frames js, {view: {key: [T, ...]}})``: each
        view's frames of a chunk in one call (:meth:`_render_at`), so a chunk's graph is its own (a chunk's backward
        leaves the others'); the rasterizer's input values are checked once for all frames (one host read after the
        last frame is queued, so the host does not wait for a swept rollout before queueing the frames), after
        ``first`` (a swept rollout's own checks: a diverged rollout is named as such, not as bad renderer input)."""
        if n_video < 1:
            raise ValueError(f"gca/train/objective.py: no video frame to render (n_video={n_video})")
        size = self.cfg.loss_chunk_frames or n_video
        self._checks = []
        try:
            renders = [(js, self._render_at(traj, js))
                       for js in (range(a, min(a + size, n_video)) for a in range(0, n_video, size))]
            checks = self._checks
        except Exception:  # a swept rollout renders before it is judged: a broken one is named as such (first)
            first()
            raise
        finally:
            self._checks = None
        first()
        rows, names = iter(torch.cat(checks).tolist() if checks else []), list(self.data.views)  # chunk, view, frame
        for js, _ in (renders if checks else []):
            for name in names:
                for j in js:
                    judge_inputs(next(rows), f"video frame {j}, view {name}: ")
        return renders

    def _frame_losses(self, traj, renders: list[tuple[range, dict]], matching: list[Future] | None, sweep=None
                      ) -> tuple[torch.Tensor, "_MeanStats"]:
        """The per-frame losses of ``renders`` summed over the frames (``frame_weights`` applied), with the
        train0 matches that ``matching`` (from :meth:`_start_matching`) delivers, and their stats.

        ``train.loss_chunk_frames`` frames at a time, or all at once (0) (:meth:`_frames_loss`: each term one call on
        [T, ...] tensors, the launches of one frame where frame by frame took T times as many: the host bound the
        iteration, NOTES session 40).
        With ``sweep`` (a swept rollout's :class:`gca.sim.rollout.ReverseSweep`; ``traj`` its :class:`_FrameLeaves`)
        the chunks go last first, each one's loss differentiated at once to its frames' (x_f, F_f), handed to the
        sweep last frame first, and the sum is returned detached (the renders then dropped: ``renders`` is emptied)."""
        n_video = renders[-1][0].stop
        loss, stats = self.data.body.x0.new_zeros(()), _MeanStats(n_video)
        checks: list = []  # RDGA's finiteness checks of every frame, read once after the loop (rdga.judge)
        weights = None if self.frame_weights is None else \
            _host_to(np.asarray(self.frame_weights[:n_video]), loss).to(loss.dtype)  # one copy for every chunk
        for js, outs in (renders if sweep is None else reversed(renders)):
            self._weights = None if weights is None else weights[js.start:js.stop]
            per_frame = self._frames_loss(traj, js, outs,
                                          [matching[j].result() for j in js] if matching is not None else None,
                                          stats, checks)
            l_js = (per_frame if self._weights is None else per_frame * self._weights).sum()
            if sweep is None:
                loss = loss + l_js
                continue
            loss = loss + l_js.detach()
            if l_js.requires_grad:
                frames = [traj.frames[j] for j in js]
                grads = torch.autograd.grad(l_js, [traj.x[f] for f in frames] + [traj.F[f] for f in frames],
                                            allow_unused=True)
                for i in reversed(range(len(js))):
                    g_x, g_F = grads[i], grads[len(js) + i]
                    if self.probe is not None:
                        for name, g in (("x", g_x), ("F", g_F)):
                            if g is not None:
                                self.probe.record("particles", name, js[i], g)
                    sweep.add(frames[i], g_x, g_F)
            outs.clear()  # the chunk's graph is spent: its images need not wait for the others'
        self._weights = None
        if sweep is not None:  # their graphs are spent: nothing keeps the images through CPR's gradient
            renders.clear()
        judge_rdga(checks)  # a non-finite frame raises here, before any gradient is applied (a swept one: abandoned)
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
        backward (ball, ~30k particles: ~0.08 GiB per frame on the H100, NOTES s12), a chunk only its share.

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
        """Every view's render outputs [H, W, ...] at video frame ``j`` (0-based): :meth:`_render_at` of that frame
        alone (a test's frame-by-frame reference)."""
        return {name: {key: v[0] for key, v in out.items()} for name, out in self._render_at(traj, range(j, j + 1)).items()}

    def _render_at(self, traj: Rollout, js: range) -> dict[str, dict]:
        """Every view's render outputs ``{view: {key: [T, ...]}}`` at the video frames ``js`` (T of them): their
        Gaussians in one call (:func:`gaussians_at` on the frames' stacked x and F), each view's frames in one render
        (gsplat's frame batch; the torch rasterizer frame by frame): a frame's launches once where frame by frame
        took T times as many (NOTES session 40)."""
        frames = [self.data.video_frames[j] for j in js]
        x, F = (torch.stack([states[f] for f in frames]) for states in (traj.x, traj.F))
        means, covs = gaussians_at(self.data.body, x, F)
        if self.probe is not None:
            self.probe.watch_frames("gaussians", "means", list(js), means)
            self.probe.watch_frames("gaussians", "covariances", list(js), covs)
        outs = {}
        for name, view in self.data.views.items():
            outs[name] = self._render(means, covs, view, with_positions=name == "train0" and self._needs_positions())
            if self.probe is not None:
                for key, image in outs[name].items():
                    self.probe.watch_frames("render outputs", f"{name}/{key}", list(js), image)
        return outs

    def _frame_loss(self, traj: Rollout, j: int, outs: dict[str, dict], pq, stats: "_MeanStats",
                    checks: list | None = None) -> torch.Tensor:
        """Loss [] at video frame ``j`` from its renders ``outs`` and train0 matches ``pq`` (or None): :meth:`_frames_loss`
        of that frame alone (a test's frame-by-frame reference)."""
        outs = {name: {key: v[None] for key, v in out.items()} for name, out in outs.items()}
        return self._frames_loss(traj, range(j, j + 1), outs, None if pq is None else [pq], stats, checks)[0]

    def _frames_loss(self, traj: Rollout, js: range, outs: dict[str, dict], pqs: list | None,
                     stats: "_MeanStats", checks: list | None = None) -> torch.Tensor:
        """Losses [T] at the consecutive video frames ``js`` (T of them) from their renders ``outs`` (``{view: {key:
        [T, ...]}}``) and train0 matches ``pqs`` (or None), each term evaluated once on the frames' [T, ...] tensors;
        their stats summed over the frames into ``stats``; RDGA's checks appended to ``checks`` (None: read at once)."""
        frames = slice(js.start, js.stop)
        loss = self.data.body.x0.new_zeros(len(js))
        for name in self.data.views:
            if self.method.uses("color"):
                l_color = (outs[name]["rgb"] - self.rgb[name][frames]).square().mean((-3, -2, -1))  # [T]
                loss = loss + self.cfg.lambda_color * l_color
                self._collect("color", self.cfg.lambda_color * l_color)
                stats.add(f"color/{name}", l_color.sum())
            if name == "train0":
                loss = loss + self._mono_terms(outs[name], pqs, frames, stats, checks)
        return loss

    def _needs_positions(self) -> bool:
        rdga = self.train0_rdga
        return rdga is not None and rdga.enabled and rdga.use_global

    def _needs_matches(self) -> bool:
        rdga = self.train0_rdga
        return rdga is not None and rdga.enabled and (rdga.use_global or rdga.use_anchor)

    def _start_matching(self, renders: list[tuple[range, dict]], last_first: bool = False) -> list[Future] | None:
        """Start matching every frame's train0 render with its video frame (``vision.matching.backend``: SIFT
        against the frame's cached keypoints, or dense flow against the frame itself, inside the rendered
        mask ``alpha >= align.rdga.alpha_threshold`` and the frame's mask); None when the method's terms need
        no matches. Returns one future per frame, each giving (p [M, 2] in the render, q [M, 2] in the video
        frame) [px]; ``last_first``: the frames are queued to the threads last first (a swept gradient's order).

        The frames (RGB and, as a 4th channel, the rendered mask) go to the host in one copy, asynchronous on
        CUDA (pinned memory and an event: the caller goes on queueing GPU work, e.g. CPR, while the copy and the
        matching threads run; OpenCV releases the GIL).
        """
        if not self._needs_matches():
            return None
        rgb, alpha = (torch.cat([out["train0"][key].detach() for _, out in renders]) for key in ("rgb", "alpha"))
        inside = alpha >= self.train0_rdga.alpha_threshold
        u8 = torch.cat([to_uint8(rgb), inside.to(torch.uint8)[..., None]], -1)  # [T, H, W, 4]
        ready = None
        if u8.is_cuda:
            host = torch.empty(u8.shape, dtype=torch.uint8, pin_memory=True)
            host.copy_(u8, non_blocking=True)
            ready = torch.cuda.Event(blocking=True)  # the waiting threads sleep instead of spinning on the host
            ready.record(torch.cuda.current_stream(u8.device))
        else:
            host = u8
        frames, keypoints = host.numpy(), self.data.keypoints

        def work(j: int) -> tuple[np.ndarray, np.ndarray]:
            if ready is not None:
                ready.synchronize()
            return match_frame(frames[j, ..., :3], self._gt_u8[j], *keypoints[j], self.match,
                               render_mask=frames[j, ..., 3] > 0, gt_mask=self._gt_mask[j])

        n_video = len(u8)
        order = range(n_video - 1, -1, -1) if last_first else range(n_video)
        futures = {j: _match_pool().submit(work, j) for j in order}
        return [futures[j] for j in range(n_video)]

    def _render(self, means, covs, view: ViewData, with_positions: bool) -> dict:
        """RGB/alpha/depth [(T,) H, W, ...] (means [(T,) G, 3]: T frames at once); with ``with_positions`` also the
        premultiplied camera-frame positions [(T,) H, W, 3] of RDGA's global term, composited in the same pass as 3 extra colour channels
        (background 0), so the frame is rasterized once."""
        body = self.data.body
        if not with_positions:
            return render_gaussians(body, means, covs, body.colors, view.camera, self.bg, checks=self._checks)
        extra = position_colors(view.camera.to_camera(means), self.train0_rdga.global_gradient)
        out = render_gaussians(body, means, covs, torch.cat([body_colors(body, means, view.camera), extra], -1),
                               view.camera, torch.cat([self.bg, self.bg.new_zeros(extra.shape[-1])]), checks=self._checks)
        return {**out, "rgb": out["rgb"][..., :3],
                "positions": position_image(out["rgb"][..., 3:], self.train0_rdga.global_gradient)}

    def _mono_terms(self, out: dict, pqs: list | None, frames: slice, stats: "_MeanStats",
                    checks: list | None = None) -> torch.Tensor:
        """Monocular terms [T] of train0 at the video frames ``frames`` (T of them; ``out`` their renders ``{key:
        [T, ...]}``, ``pqs`` their matches or None): L1 depth, raw or aligned (PAC-NeRF + depth), and silhouette/RDGA
        (:func:`gca.align.rdga.rdga_frames`, the frames' matches padded to the longest)."""
        alpha, depth = out["alpha"], out["depth"]
        T = len(alpha)
        loss = alpha.new_zeros(T)
        for term, fn in (("depth_l1", depth_l1_raw), ("depth_l1_aligned", depth_l1_aligned)):
            if self.method.uses(term):
                l_depth = fn(depth, self.est_depth[frames], self.mask[frames])
                loss = loss + self.cfg.lambda_depth_l1 * l_depth
                self._collect(term, self.cfg.lambda_depth_l1 * l_depth)
                stats.add(term, l_depth.sum())
        rdga = self.train0_rdga
        if rdga is not None:
            p, q, valid = _padded_matches(pqs, T, depth)
            positions = out.get("positions")  # rendered exactly when the global term needs it (_needs_positions)
            terms = {} if self._terms is not None else None
            l_rdga, s = rdga_frames(alpha, depth, self.mask[frames], self.est_depth[frames], p, q, rdga,
                                    pos_image=positions, K=self.K["train0"], valid=valid, terms=terms, checks=checks)
            for key, value in (terms or {}).items():
                self._collect(key, value)
            loss = loss + l_rdga
            for k, v in s.items():
                stats.add(f"rdga/{k}", v.sum() if isinstance(v, torch.Tensor) else v * T)
        return loss

    def _collect(self, term: str, value: torch.Tensor) -> None:
        """Add the batch's per-frame weighted ``term`` [T] to the per-term sums (only while term shares are
        collected), times each frame's weight in the loss (``frame_weights``: NeuMA's rollout weighting), so the terms
        add up to the total."""
        if self._terms is not None:
            value = (value if self._weights is None else value * self._weights).sum()
            self._terms[term] = self._terms[term] + value if term in self._terms else value


def depth_l1_raw(depth: torch.Tensor, est: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean L1 [...] between the rendered metric depth ``depth`` [..., H, W] (camera z, m) and the estimated depth
    ``est`` [..., H, W] inside ``mask`` [..., H, W] (bool), per frame (leading dims), as they come: the estimate is only
    defined up to an unknown per-frame scale and shift (``gca.vision.depth``), so this compares numbers in two
    different units (the ``pacnerf_depth`` row, labelled raw). A frame with an empty mask gives 0 (with the render's
    graph). Outside the mask nothing is read (no gradient, whatever the render holds there)."""
    m = mask.bool()
    n = m.sum((-2, -1))
    d, e = torch.where(m, depth, 0.0), torch.where(m, est.to(depth.dtype), 0.0)
    value = (d - e).abs().sum((-2, -1)) / n.clamp_min(1)
    return torch.where(n > 0, value, depth.sum((-2, -1)) * 0.0)


def depth_l1_aligned(depth: torch.Tensor, est: torch.Tensor, mask: torch.Tensor,
                     min_var: float = 1e-12) -> torch.Tensor:
    """Mean L1 [...] between the rendered depth ``depth`` [..., H, W] and the estimated depth ``est`` [..., H, W]
    mapped onto it by the per-frame least-squares scale and shift inside ``mask`` [..., H, W] (bool): the standard
    MiDaS-style alignment (Ranftl et al. 2020, scale-and-shift-invariant loss), the ``pacnerf_depth_aligned`` row.

        (s, t) = argmin sum_mask (s est + t - depth)^2:   s = cov(est, depth) / var(est),
                                                          t = mean(depth) - s mean(est)
        L = mean_mask |s est + t - depth|

    (s, t) are **not detached**: as in MiDaS they are part of the loss, so L is a function of the render that is
    invariant to any affine change of the estimate, and its gradient is that function's true gradient (the
    render is pulled towards the estimate's *shape*, never its unknown scale or offset). Detached, the gradient
    would treat the aligned estimate as a fixed target and the reported loss would not be the one descended.
    ``var(est)`` is floored at ``min_var`` (a constant estimate: s = 0, t = mean depth). A frame with an empty
    mask gives 0 (with the render's graph). Per frame (leading dims); outside the mask nothing is read.
    """
    m = mask.bool()
    n = m.sum((-2, -1))
    count = n.clamp_min(1)

    def mean(x):  # over the mask, per frame
        return torch.where(m, x, 0.0).sum((-2, -1)) / count

    e_c = torch.where(m, est.to(depth.dtype) - mean(est.to(depth.dtype))[..., None, None], 0.0)
    d_c = torch.where(m, depth - mean(depth)[..., None, None], 0.0)
    s = mean(e_c * d_c) / mean(e_c * e_c).clamp(min=min_var)
    value = mean((s[..., None, None] * e_c - d_c).abs())
    return torch.where(n > 0, value, depth.sum((-2, -1)) * 0.0)


def _adds_up(values: list[torch.Tensor], total: torch.Tensor, rtol: float = 1e-5) -> bool:
    """Whether the scalar terms ``values`` sum to ``total`` (to ``rtol`` of the terms' magnitudes, which may cancel:
    RDGA's anchor term is negative; one host read): a term left out of the collection would make their gradients'
    sum miss its part."""
    v = torch.stack([t.detach() for t in values]).double()
    a, b, scale = torch.stack([v.sum(), total.detach().double(), v.abs().sum()]).tolist()
    return abs(a - b) <= rtol * max(scale, abs(b), 1e-30)


def _sum_grads(grads) -> torch.Tensor | None:
    """The sum of one parameter's gradients over the terms (None entries: no dependence), None if all are None."""
    present = [g for g in grads if g is not None]
    return functools.reduce(torch.add, present) if present else None


def _accumulate(params: list[torch.Tensor], grads: list) -> None:
    """Add ``grads`` (None: nothing) into the parameters' ``.grad``, as ``backward`` would; a copy, never ``g`` itself
    (a term's own gradient when it is the only one, kept in ``last_term_grads``, which clipping ``.grad`` in place
    would rescale)."""
    for p, g in zip(params, grads):
        if g is not None:
            p.grad = g.clone() if p.grad is None else p.grad + g


def term_shares(term_grads: dict[str, list], total: list) -> dict[str, float]:
    """Each term's gradient norm and its cosine with the total gradient ``total`` (norms over all parameters;
    ``None`` entries are zero): ``{"share/<term>/norm", "share/<term>/cos"}``, plus ``share/total/norm``."""
    def flat(gs):
        parts = [g.detach().double().reshape(-1) for g in gs if g is not None]
        return torch.cat(parts) if parts else None

    g_total = flat(total)
    out = {}
    n_total = float(g_total.norm()) if g_total is not None else 0.0
    out["share/total/norm"] = n_total
    for name, grads in term_grads.items():
        g = flat([a if a is not None else (torch.zeros_like(b) if b is not None else None)
                  for a, b in zip(grads, total)])
        norm = float(g.norm()) if g is not None else 0.0
        cos = float(g @ g_total) / (norm * n_total) if g is not None and g_total is not None and norm * n_total > 0 \
            else 0.0
        out[f"share/{name}/norm"], out[f"share/{name}/cos"] = norm, cos
    return out


class _FrameLeaves:
    """A swept rollout's x and F at the supervised video frames as autograd leaves: ``x[f]`` [N, 3] and ``F[f]``
    [N, 3, 3] for each simulated frame ``f`` of ``frames`` (what the per-frame losses are differentiated to)."""

    def __init__(self, traj: Rollout, frames: list[int]):
        self.frames = list(frames)
        self.x = {f: traj.x[f].detach().requires_grad_(True) for f in self.frames}
        self.F = {f: traj.F[f].detach().requires_grad_(True) for f in self.frames}


def _host_to(array: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """A host array (matched points, the frames' weights) on ``like``'s device: on CUDA through pinned memory without
    blocking (a plain copy from pageable memory synchronises the stream, i.e. the host would wait for the GPU at every
    frame: NOTES session 32's review), elsewhere as a view."""
    t = torch.from_numpy(np.ascontiguousarray(array))
    return t.pin_memory().to(like.device, non_blocking=True) if like.is_cuda else t


def _padded_matches(pqs: list | None, T: int, like: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """T frames' matches ``pqs`` (pairs of [M_t, 2] host arrays [px], or None: none) as (p, q) [T, M, 2] in ``like``'s
    dtype and device, M = max M_t, and valid [T, M] bool (None when ``pqs`` is None), in one host-to-device copy; the
    padding rows are zeros, left out by ``valid``."""
    if pqs is None:
        empty = like.new_zeros(T, 0, 2)
        return empty, empty, None
    M = max(len(p) for p, _ in pqs)
    packed = np.zeros((T, M, 5), np.float64 if like.dtype == torch.float64 else np.float32)  # p, q, valid
    for t, (p, q) in enumerate(pqs):
        packed[t, :len(p), :2], packed[t, :len(p), 2:4], packed[t, :len(p), 4] = p, q, 1.0
    packed = _host_to(packed, like).to(like.dtype)
    return packed[..., :2], packed[..., 2:4], packed[..., 4] > 0.5


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
