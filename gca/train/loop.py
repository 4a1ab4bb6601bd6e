"""Optimising a method's law from video: rollout -> render -> losses -> backward, with a frame curriculum.

One iteration (NeuMA stage B, with GCA's losses where the method asks for them):

1. roll the law out from the estimated initial velocity for the current curriculum horizon, with
   per-frame checkpointing (memory does not grow with every step's activations);
2. ``Objective.gradient`` (``gca.train.objective``): at each supervised video frame, move the Gaussians
   with the particles, render every training view and add the method's declared loss terms (colour L2
   for NeuMA, silhouette + RDGA geometry + CPR for GCA: eq. 8, L1 monocular depth for PAC-NeRF + depth);
   backward into the law's parameters;
3. clip the gradient norm, step the optimiser (``train.optimizer``: RAdam, as NeuMA; or Adam) with cosine decay
   (``gca.train.state``: schedule, undo, best law, checkpoints).

An update after which the rollout diverges (non-finite loss or state, particles leaving the domain, a
rollout drifting away from the observed silhouette) is rejected: the law and the optimiser go back to
before it, the learning rate is multiplied by ``backtrack_factor`` for the rest of the run and the
update is retaken from the same gradient. After ``max_rejections`` rejections in a row (or a
divergence before any update, i.e. of the prior itself) the run stops cleanly and is reported as
diverged with its last finite losses; every rejection is listed in the result. Checkpoints are
written every ``checkpoint_every`` iterations and resumed from.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from pathlib import Path
from typing import Callable

import torch
from tqdm import tqdm

from gca import stop
from gca.efficiency import synced_clock
from gca.laws.neural import neural_networks
from gca.sim.cfl import CFLError
from gca.sim.rollout import Rollout, SimulationDiverged, rollout
from gca.sim.solver import MPMSolver
from gca.train.config import TrainConfig, frame_weights
from gca.train.law import LearnedLaw
from gca.train.objective import Objective, TrainData
from gca.train.probe import GradProbe
from gca.train.state import BestLaw, Undo, make_optimizer, resume_checkpoint, save_checkpoint

# CFLError: the law stiffened until the scene's dt no longer resolves its waves: the rollout cannot be
# trusted, like one that blew up (an update that does this is rejected, not a crash)
DIVERGENCE_ERRORS = (SimulationDiverged, FloatingPointError, CFLError)


@dataclasses.dataclass
class TrainResult:
    status: str  # "ok" | "diverged"
    iterations: int
    history: list[dict]
    message: str = ""
    seconds: float = 0.0
    rejected: list[dict] = dataclasses.field(default_factory=list)  # {"iteration", "message", "lr_scale"}
    selected: dict = dataclasses.field(default_factory=dict)  # which law was kept (:class:`BestLaw`)
    resumed_at: int = 0  # the iteration this process resumed from (0: a fresh run)
    seconds_before: float = 0.0  # training time of the earlier processes of a resumed run [s]
    # every process that trained the run, this one last: {"resumed_at": <its first iteration>, **train's ``process``}
    processes: list[dict] = dataclasses.field(default_factory=list)


def horizon(cfg: TrainConfig, it: int, n_video: int) -> int:
    """Number of video frames supervised at iteration ``it`` (linear growth, then all)."""
    ramp = max(1.0, cfg.curriculum_until * cfg.iterations)
    frac = cfg.curriculum_start + (1.0 - cfg.curriculum_start) * min(1.0, it / ramp)
    return max(1, min(n_video, math.ceil(frac * n_video)))


def simulate(solver: MPMSolver, law: LearnedLaw, data: TrainData, n_video: int, sweep: bool = False) -> Rollout:
    """Differentiable rollout up to the ``n_video``-th video frame, from the law's learned launch (explicit rows)
    or the shared estimate ``data.v_init``; with ``sweep``, differentiated by its reverse sweep instead of
    autograd (``gca.sim.rollout.ReverseSweep``)."""
    n_frames = data.video_frames[n_video - 1]
    b = data.body
    return rollout(solver, law.material, b.x0, law.initial_velocity(b.x0, data.v_init), b.vol, b.mass,
                   n_steps=n_frames * data.substeps, steps_per_frame=data.substeps, checkpoint=True, sweep=sweep)


@contextlib.contextmanager
def matmul_precision(level: str):
    """torch's float32 matrix-product precision inside the block (``train.matmul_precision``:
    ``torch.set_float32_matmul_precision``), the process's own restored after it."""
    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision(level)
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(before)


@contextlib.contextmanager
def mlp_kernel(material, kind: str):
    """Every neural network of ``material`` runs its MLP on ``kind`` inside the block (``train.mlp_kernel``:
    ``NeuralElasticity.mlp_kernel``), each one's own restored after it."""
    nets = neural_networks(material)
    before = [net.mlp_kernel for net in nets]
    for net in nets:
        net.mlp_kernel = kind
    try:
        yield
    finally:
        for net, old in zip(nets, before):
            net.mlp_kernel = old


@contextlib.contextmanager
def run_settings(cfg: TrainConfig, law: LearnedLaw):
    """What a training run's differentiation runs under: ``cfg.matmul_precision`` and ``cfg.mlp_kernel``."""
    with matmul_precision(cfg.matmul_precision), mlp_kernel(law.material, cfg.mlp_kernel):
        yield


def train(solver: MPMSolver, law: LearnedLaw, data: TrainData, objective: Objective, cfg: TrainConfig,
          checkpoint_path: Path | None = None, on_iteration: Callable[[int, dict], None] | None = None,
          process: dict | None = None) -> TrainResult:
    """Run the optimisation under :func:`run_settings`; returns the status, the per-iteration history and the
    rejected updates.

    ``process``: what the caller says of this process (JSON-able values, no ``resumed_at`` key; the loop reads none
    of it), kept in the checkpoint with the iteration it started at, after the earlier processes'
    (``TrainResult.processes``), so a run stopped and resumed elsewhere or otherwise says how each part trained."""
    with run_settings(cfg, law):
        return _train(solver, law, data, objective, cfg, checkpoint_path, on_iteration, process or {})


def _train(solver: MPMSolver, law: LearnedLaw, data: TrainData, objective: Objective, cfg: TrainConfig,
           checkpoint_path: Path | None, on_iteration: Callable[[int, dict], None] | None,
           process: dict) -> TrainResult:
    start = time.perf_counter()
    if not law.trainable():
        return TrainResult("ok", 0, [], "nothing to train", 0.0, processes=[{"resumed_at": 0, **process}])
    opt, sched = make_optimizer(law, cfg)
    best = BestLaw()
    it0, history, rejected, seconds_before, undo, processes = resume_checkpoint(checkpoint_path, law, opt, sched, best,
                                                                                objective)
    processes = [*processes, {"resumed_at": it0, **process}]
    resumed = {"resumed_at": it0, "seconds_before": seconds_before, "processes": processes}
    n_video = len(data.video_frames)
    in_a_row = 0  # rejected updates in a row: none at a checkpoint (it follows an accepted update, whose Undo it holds)
    bar = tqdm(total=cfg.iterations, desc="train", unit="it", initial=it0)
    it = it0
    while it < cfg.iterations:
        try:
            shares = cfg.term_shares_every > 0 and it % cfg.term_shares_every == 0
            objective.frame_weights = frame_weights(cfg, it, n_video)
            record = _gradient(solver, law, data, objective, cfg, horizon(cfg, it, n_video), shares)
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
        weights = objective.frame_weights
        if record["horizon"] == n_video and (weights is None or min(weights) == 1.0):  # comparable losses only
            best.offer(law, record["loss"], it)
        undo = Undo(law, opt, sched)
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
        stopping = stop.requested()  # read once: a stop asked between two reads would go uncheckpointed
        if checkpoint_path is not None and (it % cfg.checkpoint_every == 0 or it == cfg.iterations or stopping):
            save_checkpoint(checkpoint_path, law, opt, sched, it, history, rejected, best,
                             seconds_before + time.perf_counter() - start, objective, undo, processes)
        if stopping:  # SIGTERM under gca.stop.deferred, the stop file or the deadline: stop here, checkpointed
            stop.check()
    bar.close()
    objective.frame_weights = None  # after training the objective is the whole video, every frame at weight 1
    selected = (_select(best, undo, solver, law, data, objective, cfg, n_video, history, opt) if cfg.keep == "best"
                else {"rule": "last"})
    return TrainResult("ok", cfg.iterations, history, "", time.perf_counter() - start, rejected, selected, **resumed)


def _select(best: BestLaw, undo, solver, law, data, objective, cfg, n_video: int, history: list, opt) -> dict:
    """Keep the best law seen: the final law (never evaluated during the loop: its loss comes after the
    last update) is evaluated once over the whole video, and replaced by the best earlier one when that
    one's loss is lower or the final rollout diverges (with no earlier full-video loss to compare with,
    a diverging final law is replaced by the law before the last update)."""
    try:
        final = _gradient(solver, law, data, objective, cfg, n_video, provenance=False)["loss"]  # its message unused
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
    """Wall time per phase [s], synchronising CUDA so asynchronous kernels are charged to their phase.

    ``synced``: the phases whose end synchronises (None: all). A swept iteration (``train.reverse_sweep``) overlaps
    its phases on purpose (the GPU simulates while the host renders, and differentiates while the host evaluates
    the losses), so only its last phase synchronises: its earlier phases' times are the host's, and the total is
    the iteration's wall time either way."""

    def __init__(self, device: torch.device, synced: set[str] | None = None):
        self.device, self.seconds, self._t, self.synced = device, {}, None, synced

    def _now(self, phase: str | None = None) -> float:
        if self.synced is None or phase is None or phase in self.synced:
            return synced_clock(self.device)
        return time.perf_counter()

    def start(self) -> None:
        self._t = self._now()

    def lap(self, phase: str) -> None:
        t = self._now(phase)
        self.seconds[phase] = self.seconds.get(phase, 0.0) + t - self._t
        self._t = t


def _gradient(solver, law, data, objective, cfg, n_video, shares: bool = False, provenance: bool = True) -> dict:
    """Rollout, losses, backward and clipping: the law's ``.grad`` is ready for the update.

    Returns the iteration's record (loss, gradient norm before clipping, horizon, stats, phase times).
    Raises one of ``DIVERGENCE_ERRORS`` when the rollout, the loss or a gradient is not usable; with ``provenance``,
    a non-finite gradient's message says where it entered (:func:`_provenance`: the iteration once more, probed).
    """
    swept = cfg.reverse_sweep and not shares and objective.can_sweep()
    timer = PhaseTimer(data.body.x0.device, synced={"backward"} if swept else None)
    timer.start()
    objective.probe = None
    before = objective.state()  # what the iteration advances (CPR's calls and fits): a replay starts from it
    loss, stats, traj = _losses_backward(solver, law, data, objective, cfg, n_video, shares, swept, timer.lap)
    refine, wave_speed = traj.refine, traj.wave_speed
    del traj  # a replay's rollout should not sit beside this one
    _check_gradients(law, (lambda: _provenance(solver, law, data, objective, cfg, n_video, swept, before))
                     if provenance else None)
    params = law.trainable()
    grad_norm = torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
    return {"loss": float(loss), "grad_norm": float(grad_norm), "horizon": n_video, "sim_refine": refine,
            "wave_speed": wave_speed, **stats,
            **{f"time/{k}": v for k, v in timer.seconds.items()}}


def _losses_backward(solver, law, data, objective, cfg, n_video: int, shares: bool, swept: bool,
                     lap: Callable[[str], None]) -> tuple[torch.Tensor, dict, Rollout]:
    """One rollout of ``n_video`` frames, its losses and their backward (swept frame by frame or one autograd pass):
    the law's ``.grad`` filled from None; (loss, stats, rollout). With ``objective.probe`` set, the rollout's x and F
    are watched too."""
    for p in law.trainable():
        p.grad = None
    traj = simulate(solver, law, data, n_video, sweep=swept)
    if objective.probe is not None:
        objective.probe.watch("particles", "x", -1, traj.x)
        objective.probe.watch("particles", "F", -1, traj.F)
    lap("simulate")
    if swept:  # the rollout's checks are read once its frames are rendered (the GPU simulates meanwhile)
        loss, stats = objective.gradient(traj, n_video, law, lap,
                                         on_rendered=lambda: _check_drift(traj, data, n_video, cfg))
    else:
        _check_drift(traj, data, n_video, cfg)
        loss, stats = objective.gradient(traj, n_video, law, lap, shares=shares) if shares else \
            objective.gradient(traj, n_video, law, lap)
    return loss, stats, traj


def _provenance(solver, law, data, objective, cfg, n_video: int, swept: bool, before: dict) -> str:
    """Where a non-finite gradient entered the loss -> render -> Gaussians -> particles chain: the same iteration
    once more (the law has not moved: a non-finite gradient is never applied; the objective's state, CPR's calls and
    fits, put back to ``before`` for it and to where the iteration left it after) with a :class:`GradProbe` on the
    tensors between the stages, and its report; the same gradient pass (swept or not), without the term-share
    passes. The probe costs ~280 autograd hooks and ~840 launches an iteration on the ball (a large share of its host
    time, NOTES session 39), so it runs only here, after the fact. A replay that fails (any error: it must not replace
    the divergence being reported), or whose gradients come out finite (GPU float atomics sum in another order each
    run), says so. The law's ``.grad`` then holds the replay's gradient (the caller raises; nothing applies it)."""
    after = objective.state()
    objective.load_state(before)
    probe = objective.probe = GradProbe()
    try:
        _losses_backward(solver, law, data, objective, cfg, n_video, False, swept, lambda phase: None)
    except Exception as exc:  # noqa: BLE001 (a report, not a recovery: the caller raises the divergence)
        return f"the probed replay of the iteration failed ({type(exc).__name__}: {exc})"
    finally:
        objective.probe = None
        objective.load_state(after)
    if not _nonfinite_gradients(law):
        return "the probed replay of the iteration had finite gradients (not reproduced: no stage named)"
    return probe.report()


def _nonfinite_gradients(law: LearnedLaw) -> list[str]:
    """Per parameter group with non-finite gradient entries: "<group>: <n> non-finite gradient entries"."""
    bad = []
    for group in law.groups:
        n_bad = sum(int((~torch.isfinite(p.grad)).sum()) for p in group["params"] if p.grad is not None)
        if n_bad:
            bad.append(f"{group['name']}: {n_bad} non-finite gradient entries")
    return bad


def _check_gradients(law: LearnedLaw, provenance: Callable[[], str] | None = None) -> None:
    """Raise FloatingPointError naming the parameter groups whose gradients are non-finite (never zeroed; a
    ``provenance`` replay leaves its own in ``.grad``, which the loop's undo or the next iteration clears) and, with
    ``provenance`` (called only then), where along the loss -> render -> Gaussians -> particles chain they broke."""
    bad = _nonfinite_gradients(law)
    if bad:
        where = f"; provenance: {provenance()}" if provenance is not None else ""
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
