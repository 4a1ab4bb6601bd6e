"""Pretraining of the neural prior M_0 = {E_0, P_0} of one material family (the ``prior`` stage).

Recipe (NCLaw, reference notes §5.2, on many trajectories instead of one):

1. **Data** (:mod:`gca.train.prior_data`): thrown bodies of the family's analytic material, full
   state (x, v, C, F) stored at every step; a disjoint set of held-out trajectories.
2. **Warm start** (optional, not in NCLaw): law-level regression of the networks onto the family's
   analytic elasticity and return map (:mod:`gca.laws.pretrain`).
3. **Teacher forcing**: each Adam step restarts ``batch`` windows from ground-truth states at random
   steps, simulates ``window`` steps with the neural laws and penalises the positions,

       loss = mean_windows mean_{j=1..k} mean_p ||x_p(s+j) - x_p^gt(s+j)||^2 / dx^2   [cells^2],

   with the elasticity and plasticity in separate parameter groups, cosine-decayed learning rates and
   global grad-norm clipping. A non-finite loss or a diverging window raises with a diagnostic.
4. **Evaluation**: full rollouts of the held-out trajectories from their launch states, position
   error of the untrained, warm-started and trained networks (mean over steps and particles of the
   squared distance, m^2); law-level response error [%] of the elasticity against the family's
   analytic law on uniaxial and simple-shear sweeps (:func:`gca.laws.pretrain.sweep_response_error`).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import time
from pathlib import Path
from typing import Callable, Mapping, Sequence

import torch

from gca import stop
from gca.io import atomic_path, save_torch
from gca.laws.base import Material
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity
from gca.laws.pretrain import (DeformationSampling, PretrainConfig, fit_elasticity, fit_plasticity, response_error,
                               sweep_deformations)
from gca.laws.presets import material_from_preset
from gca.sim import MPMSolver, SimConfig, SimulationDiverged
from gca.sim.frame import simulate_frame
from gca.sim.rollout import check_state
from gca.train.prior_data import PriorDataConfig, Trajectory, make_trajectories, trajectory_seed

_WHERE = "gca/train/prior.py"
NETWORKS = ("elasticity", "plasticity")


@dataclasses.dataclass(frozen=True)
class PriorTrainConfig:
    """Knobs of the prior stage (params ``prior.train``); paper-scale defaults."""

    sim: SimConfig = SimConfig(dt=4e-4, bound=2, max_refine=1)  # simulator: params `sim` + prior.train.sim
    data: PriorDataConfig = PriorDataConfig()  # how trajectories are drawn
    n_train: int = 16  # training trajectories {paper: 16, ci: 4} [count]
    n_heldout: int = 4  # held-out trajectories (other seeds) {paper: 4, ci: 2} [count]
    window: int = 16  # teacher-forced steps k per window (NCLaw: 25 -> 200) {paper: 16, ci: 8} [count]
    batch: int = 4  # windows per Adam step [count]
    iterations: int = 2000  # Adam steps {paper: 2000, ci: 40} [count]
    lr_elasticity: float = 1e-3  # initial Adam learning rate of the elasticity network
    lr_plasticity: float = 1e-4  # initial Adam learning rate of the plasticity network
    cosine_floor: float = 0.05  # final learning rate as a fraction of the initial one [1]
    grad_clip: float = 1.0  # global gradient-norm clip [loss units]
    warm_start: tuple[str, ...] = NETWORKS  # networks regressed onto the analytic law first ([] = none)
    fit_elasticity: PretrainConfig = PretrainConfig(lr=1e-2, sampling=DeformationSampling(0.2, 0.2, math.pi))  # warm-start regression of the elasticity (stress)
    # ... of the return map: one step's trial states lie near the yield surface and barely rotated (the
    # fluid's F -> J^(1/3) I drops rotations, which F + alpha R S cannot represent for R != I)
    fit_plasticity: PretrainConfig = PretrainConfig(lr=1e-2, sampling=DeformationSampling(0.05, 0.05, 0.0))
    response_max_strain: float = 0.1  # sweeps of the law-level response error span +-this strain [1]
    log_every: int = 10  # iterations between logged training losses [count]
    cpu_threads: int = 1  # torch intra-op threads on a CPU device (0 = torch default; >1 is ~10x slower on a busy box)

    def __post_init__(self):
        object.__setattr__(self, "warm_start", tuple(self.warm_start))
        problems = []
        if set(self.warm_start) - set(NETWORKS):
            problems.append(f"warm_start={self.warm_start} must be a subset of {NETWORKS}")
        if min(self.n_train, self.n_heldout, self.window, self.batch, self.log_every) < 1 or self.iterations < 0:
            problems.append("n_train, n_heldout, window, batch, log_every must be >= 1 and iterations >= 0")
        if self.cpu_threads < 0:
            problems.append(f"cpu_threads={self.cpu_threads} must be >= 0")
        if self.window > self.data.n_steps:
            problems.append(f"window={self.window} exceeds the trajectory length data.n_steps={self.data.n_steps}")
        if not (self.lr_elasticity >= 0 and self.lr_plasticity >= 0 and 0 < self.cosine_floor <= 1
                and self.grad_clip > 0 and self.response_max_strain > 0):
            problems.append("need lr >= 0, 0 < cosine_floor <= 1, grad_clip > 0, response_max_strain > 0")
        if problems:
            raise ValueError(f"{_WHERE}: bad PriorTrainConfig: " + "; ".join(problems))


@dataclasses.dataclass
class PriorResult:
    """What :func:`pretrain_prior` produced: the trained networks, metrics and curves for plots."""

    elasticity: NeuralElasticity
    plasticity: NeuralPlasticity
    metrics: dict
    history: list  # [(iteration, loss [cells^2])]
    curves: dict  # sweep name -> {"strain": [n], "reference"/"untrained"/"trained": [n]} (Pa)


def make_networks(law_cfg: NeuralLawConfig, seed: int, dtype: torch.dtype = torch.float32,
                  device: str | torch.device = "cpu") -> tuple[NeuralElasticity, NeuralPlasticity]:
    """Freshly initialised (Xavier) neural elasticity and plasticity, reproducible from ``seed``."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        elasticity, plasticity = NeuralElasticity(law_cfg), NeuralPlasticity(law_cfg)
    return elasticity.to(dtype=dtype, device=device), plasticity.to(dtype=dtype, device=device)


def window_loss(solver: MPMSolver, material: Material, trajectory: Trajectory, start: int, k: int) -> torch.Tensor:
    """Teacher-forced position loss of one window [cells^2] (scalar tensor with grad).

    Args:
        solver: MPM solver.
        material: the neural material being trained.
        trajectory: ground truth; the window starts from its full state at ``start``.
        start: first step, ``0 <= start <= T - k``.
        k: steps simulated.

    Raises:
        SimulationDiverged: the neural law blew the window up (names step, start and law).
    """
    if not 0 <= start <= trajectory.n_steps - k:
        raise ValueError(f"{_WHERE}: window [{start}, {start + k}] leaves the trajectory of {trajectory.n_steps} steps")
    x, v, C, F = trajectory.state(start)
    loss = x.new_zeros(())
    for j in range(1, k + 1):
        x, v, C, F = simulate_frame(solver, material, 1, x, v, C, F, trajectory.vol, trajectory.mass)
        loss = loss + (x - trajectory.x[start + j]).square().sum(dim=1).mean()
    check_state(solver, x.detach(), v.detach(), F.detach(), start + k, f"neural prior (window from step {start})")
    return loss / (k * solver.cfg.dx ** 2)


def _cosine(iteration: int, cfg: PriorTrainConfig) -> float:
    """Learning-rate factor: 1 -> cosine_floor over ``cfg.iterations``."""
    t = iteration / max(cfg.iterations - 1, 1)
    return cfg.cosine_floor + (1 - cfg.cosine_floor) * 0.5 * (1 + math.cos(math.pi * t))


def _optimizer(material: Material, cfg: PriorTrainConfig) -> torch.optim.Adam:
    groups = [{"params": list(material.elasticity.parameters()), "lr": cfg.lr_elasticity, "base_lr": cfg.lr_elasticity},
              {"params": list(material.plasticity.parameters()), "lr": cfg.lr_plasticity, "base_lr": cfg.lr_plasticity}]
    return torch.optim.Adam(groups)


def sample_windows(trajectories: Sequence[Trajectory], k: int, n: int, generator: torch.Generator) -> list[tuple[int, int]]:
    """``n`` random (trajectory index, start step) pairs with room for ``k`` steps."""
    windows = []
    for _ in range(n):
        i = int(torch.randint(len(trajectories), (1,), generator=generator))
        start = int(torch.randint(trajectories[i].n_steps - k + 1, (1,), generator=generator))
        windows.append((i, start))
    return windows


def train_teacher_forced(material: Material, solver: MPMSolver, trajectories: Sequence[Trajectory],
                         cfg: PriorTrainConfig, seed: int,
                         on_step: Callable[[int, float], None] | None = None,
                         save: Callable[[dict], None] | None = None, resume: dict | None = None,
                         checkpoint_every: int = 100) -> list[tuple[int, float]]:
    """Adam on :func:`window_loss` over random windows (in place on ``material``'s networks).

    Args:
        save: called with the loop's state (``{"iteration", "opt", "generator", "history"}``, the networks' own
            state is the caller's) every ``checkpoint_every`` iterations and when SIGTERM arrived inside
            :func:`gca.stop.deferred`, after which the loop stops (:func:`gca.stop.check`).
        resume: such a state: the loop goes on from its iteration with its optimiser and window sampler, so the
            result equals the uninterrupted run's (bitwise on a CPU, tested).

    Returns:
        The loss history [(iteration, mean window loss [cells^2])], every iteration.

    Raises:
        RuntimeError: non-finite loss or gradient (names the iteration, the windows and the last loss).
    """
    opt = _optimizer(material, cfg)
    g = torch.Generator().manual_seed(int(seed) + 17)
    history: list[tuple[int, float]] = []
    start = 0
    if resume is not None:
        opt.load_state_dict(resume["opt"])
        g.set_state(resume["generator"])
        history, start = [tuple(h) for h in resume["history"]], int(resume["iteration"])
    params = [p for group in opt.param_groups for p in group["params"]]
    for it in range(start, cfg.iterations):
        windows = sample_windows(trajectories, cfg.window, cfg.batch, g)
        last = history[-1][1] if history else None
        try:
            loss = sum(window_loss(solver, material, trajectories[i], s, cfg.window) for i, s in windows) / cfg.batch
        except (SimulationDiverged, torch.linalg.LinAlgError) as exc:
            raise SimulationDiverged(f"{_WHERE}: teacher forcing diverged at iteration {it} (windows (trajectory, "
                                     f"start)={windows}, last loss={last}): {exc}") from exc
        opt.zero_grad()
        loss.backward()
        if not torch.isfinite(loss):
            raise RuntimeError(f"{_WHERE}: teacher forcing diverged at iteration {it}: loss={loss.item()}, "
                               f"windows (trajectory, start)={windows}, last finite loss={last}")
        try:
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip, error_if_nonfinite=True)
        except RuntimeError as exc:
            raise RuntimeError(f"{_WHERE}: non-finite gradient at iteration {it} (loss={loss.item():.4g}, "
                               f"windows={windows}): {exc}") from exc
        for group in opt.param_groups:
            group["lr"] = group["base_lr"] * _cosine(it, cfg)
        opt.step()
        history.append((it, loss.item()))
        if on_step is not None:
            on_step(it, loss.item())
        stopping = stop.requested()  # read once (gca.train.loop's reason)
        if save is not None and ((it + 1) % checkpoint_every == 0 or stopping):
            save({"iteration": it + 1, "opt": opt.state_dict(), "generator": g.get_state(), "history": history})
        if stopping:
            stop.check()
    return history


@torch.no_grad()
def rollout_sq_error(solver: MPMSolver, material: Material, trajectory: Trajectory) -> float:
    """Full rollout from the launch state: mean over steps and particles of ||x - x_gt||^2 [m^2].

    A rollout that diverges returns ``inf`` (the law is useless there; callers report it as such).
    """
    x, v, C, F = trajectory.state(0)
    total = 0.0
    for step in range(1, trajectory.n_steps + 1):
        try:  # a non-finite F_trial makes the law's SVD fail before check_state sees it
            x, v, C, F = simulate_frame(solver, material, 1, x, v, C, F, trajectory.vol, trajectory.mass)
            check_state(solver, x, v, F, step, "neural prior (held-out rollout)")
        except (SimulationDiverged, torch.linalg.LinAlgError):
            return math.inf
        total += float((x - trajectory.x[step]).square().sum(dim=1).mean())
    return total / trajectory.n_steps


def heldout_rmse(solver: MPMSolver, material: Material, trajectories: Sequence[Trajectory]) -> float:
    """Root of the mean :func:`rollout_sq_error` over the held-out trajectories: position RMSE [m]."""
    return math.sqrt(sum(rollout_sq_error(solver, material, t) for t in trajectories) / len(trajectories))


def warm_start(material: Material, reference: Material, cfg: PriorTrainConfig) -> dict[str, float]:
    """Regress the networks named in ``cfg.warm_start`` onto the analytic law; returns final fit losses."""
    reference = reference.to(dtype=next(material.parameters()).dtype, device=next(material.parameters()).device)
    losses = {}
    if "elasticity" in cfg.warm_start:
        losses["elasticity"] = fit_elasticity(material.elasticity, reference.elasticity, cfg.fit_elasticity)[-1]
    if "plasticity" in cfg.warm_start:
        losses["plasticity"] = fit_plasticity(material.plasticity, reference.plasticity, cfg.fit_plasticity)[-1]
    return losses


def response_error_pct(elasticity, reference, max_strain: float) -> dict[str, float | None]:
    """Law-level response error [%] of an elasticity against the reference on each sweep, and their mean.

    A sweep on which the reference is stress-free (simple shear of a volume-only law) has no relative
    error: it is reported as None and left out of the mean.
    """
    law, ref = copy.deepcopy(elasticity).cpu().float(), copy.deepcopy(reference).cpu().float()
    errors: dict[str, float | None] = {}
    for name, Fs in sweep_deformations(max_strain, 10, torch.float32).items():
        with torch.no_grad():
            defined = bool(ref(Fs).norm() > 0)
        errors[name] = 100.0 * response_error(law, ref, Fs) if defined else None
    known = [e for e in errors.values() if e is not None]
    errors["mean"] = sum(known) / len(known) if known else None
    return errors


@torch.no_grad()
def response_curves(laws: Mapping[str, torch.nn.Module], max_strain: float, n: int = 21) -> dict:
    """tau_xx over the uniaxial and tau_xy over the shear sweep (Pa) for each named elasticity."""
    curves = {}
    for name, Fs in sweep_deformations(max_strain, n, torch.float32).items():
        component = (0, 0) if name == "uniaxial" else (0, 1)
        curves[name] = {"strain": (Fs[:, 0, 0] - 1 if name == "uniaxial" else Fs[:, 0, 1]).tolist()}
        for label, law in laws.items():
            tau = copy.deepcopy(law).cpu().float()(Fs)
            curves[name][label] = tau[:, component[0], component[1]].tolist()
    return curves


def _progress(total: int, callback) -> Callable[[], None]:
    """A no-argument tick for data generation that reports ``(phase, done, total)`` to ``callback``."""
    done = [0]

    def tick():
        done[0] += 1
        if callback is not None:
            callback("data", done[0], total)
    return tick


def make_dataset(material: Material, solver: MPMSolver, cfg: PriorTrainConfig, seed: int, callback=None):
    """Training and held-out trajectories of ``material`` (disjoint seed streams)."""
    tick = _progress(cfg.n_train + cfg.n_heldout, callback)
    seeds = {split: [trajectory_seed(seed, split, i) for i in range(n)]
             for split, n in (("train", cfg.n_train), ("heldout", cfg.n_heldout))}
    return {split: make_trajectories(solver, material, cfg.data, s, tick) for split, s in seeds.items()}


@contextlib.contextmanager
def _timed(seconds: dict, phase: str):
    """Add the wall-clock seconds of the block to ``seconds[phase]``."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        seconds[phase] = seconds.get(phase, 0.0) + time.perf_counter() - t0


@contextlib.contextmanager
def _cpu_threads(device: torch.device, n: int):
    """Limit torch's intra-op threads while simulating on the CPU (restored afterwards)."""
    before = torch.get_num_threads()
    if device.type == "cpu" and n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def pretrain_prior(preset: Mapping, law_cfg: NeuralLawConfig, cfg: PriorTrainConfig, seed: int = 0,
                   device: str | torch.device = "cpu", callback=None, checkpoint=None,
                   checkpoint_every: int = 100) -> PriorResult:
    """The whole prior stage for one family: data, warm start, teacher forcing, evaluation.

    The held-out RMSE and the response error are measured after each phase: ``untrained`` (the
    initialisation), ``warm`` (after the warm start, if any) and ``trained``.

    Args:
        preset: the family's analytic material (a ``material_from_preset`` mapping).
        law_cfg: architecture and scaling of the networks (params ``laws.neural``).
        cfg: stage knobs.
        seed: seeds the data, the network initialisation and the window sampling.
        device: torch device of the simulation.
        callback: optional ``callback(phase, i, n, **values)`` for progress bars and logging.
        checkpoint: a file path: teacher forcing saves its state there every ``checkpoint_every`` iterations and,
            on SIGTERM, at the end of the step in progress before stopping (:func:`gca.stop.deferred` around the
            loop; a SIGTERM before it stops at once); a run finding one goes on from it: the data are made
            again (from the seed), the warm start and the earlier evaluations come from the checkpoint. The
            caller removes it when the stage is done and guards it against other params
            (:func:`gca.stamp.guard_checkpoint`).

    Returns:
        :class:`PriorResult` (networks on the CPU in float32).
    """
    with _cpu_threads(torch.device(device), cfg.cpu_threads):
        return _pretrain(preset, law_cfg, cfg, seed, device, callback, checkpoint, checkpoint_every)


def _pretrain(preset, law_cfg, cfg, seed, device, callback, checkpoint=None, checkpoint_every=100) -> PriorResult:
    seconds: dict[str, float] = {}
    say = callback or (lambda *a, **k: None)
    solver = MPMSolver(cfg.sim, device)
    reference = material_from_preset(preset, dt=cfg.sim.dt)
    with _timed(seconds, "data"):
        data = make_dataset(reference, solver, cfg, seed, callback)
    e, p = make_networks(law_cfg, seed, solver.dtype, solver.device)
    material = Material(e, p, float(reference.rho)).to(dtype=solver.dtype, device=solver.device)
    evaluation, untrained = {}, copy.deepcopy(material.elasticity)

    def evaluate(phase):
        with _timed(seconds, "evaluate"):
            evaluation[phase] = {"rmse": heldout_rmse(solver, material, data["heldout"]),
                                 "response": response_error_pct(material.elasticity, reference.elasticity,
                                                                cfg.response_max_strain)}
    # loaded onto the CPU whatever the solver's device: the window sampler's RNG state must be a CPU ByteTensor (a
    # CUDA-mapped load failed the first resume on the H100, session 14); load_state_dict moves the rest
    resume = torch.load(checkpoint, map_location="cpu", weights_only=False) \
        if checkpoint is not None and Path(checkpoint).is_file() else None
    if resume is None:
        evaluate("untrained")
        with _timed(seconds, "warm_start"):
            fit = warm_start(material, reference, cfg) if cfg.warm_start else {}
        if cfg.warm_start:
            evaluate("warm")
    else:  # the phases before teacher forcing as the interrupted run did them
        material.load_state_dict(resume["material"])
        untrained.load_state_dict(resume["untrained"])
        evaluation, fit = resume["evaluation"], resume["fit"]
        for phase, value in resume["seconds"].items():
            if phase != "train":
                seconds[phase] = seconds.get(phase, 0.0) + value
        say("resume", int(resume["loop"]["iteration"]), cfg.iterations)

    def save(loop: dict) -> None:
        save_torch({"loop": loop, "material": material.state_dict(), "untrained": untrained.state_dict(),
                    "evaluation": evaluation, "fit": fit, "seconds": dict(seconds)}, checkpoint)

    with _timed(seconds, "train"), (stop.deferred() if checkpoint is not None else contextlib.nullcontext()):
        history = train_teacher_forced(material, solver, data["train"], cfg, seed,
                                       lambda it, loss: say("train", it + 1, cfg.iterations, loss=loss),
                                       save=None if checkpoint is None else save,
                                       resume=None if resume is None else resume["loop"],
                                       checkpoint_every=checkpoint_every)
    evaluate("trained")
    metrics = {**_metrics(evaluation, fit, history, data, cfg), "seconds": seconds}
    seconds["total"] = sum(seconds.values())
    curves = response_curves({"reference": reference.elasticity, "untrained": untrained,
                              "trained": material.elasticity}, cfg.response_max_strain)
    e_out, p_out = (copy.deepcopy(m).cpu().float() for m in (material.elasticity, material.plasticity))
    return PriorResult(e_out, p_out, metrics, history, curves)


def _metrics(evaluation: dict, fit: dict, history: list, data: dict, cfg: PriorTrainConfig) -> dict:
    """Metrics JSON of the stage (RMSE in m and cells, response errors in %)."""
    rmse = {phase: ev["rmse"] for phase, ev in evaluation.items()}
    ratio = (rmse["untrained"] / rmse["trained"] if 0 < rmse["trained"] < math.inf  # a diverged prior scores 0
             else (0.0 if rmse["trained"] == math.inf else math.inf))
    tail = [loss for _, loss in history[-max(1, len(history) // 10):]]
    trajectories = data["train"] + data["heldout"]
    return {
        "heldout_rmse_m": rmse,
        "heldout_rmse_cells": {k: v / cfg.sim.dx for k, v in rmse.items()},
        "heldout_ratio": ratio,  # untrained / trained position RMSE
        "response_error_pct": {phase: ev["response"] for phase, ev in evaluation.items()},
        "warm_start_fit_loss": fit,
        "train_loss_cells2": {"first": history[0][1] if history else None,
                              "last_10pct": sum(tail) / len(tail) if history else None},
        "data": {"n_train": len(data["train"]), "n_heldout": len(data["heldout"]),
                 "n_particles": [t.x.shape[1] for t in trajectories],
                 "shapes": [t.info["shape"] for t in trajectories]},
    }


def plot_prior(result: PriorResult, path, family: str = "") -> None:
    """Training curve and elastic response curves side by side, written atomically as PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 3.8))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 3, 1)
    if result.history:
        its, losses = zip(*result.history)
        width = max(1, len(losses) // 20)
        smooth = torch.tensor(losses).unfold(0, width, 1).mean(dim=1).tolist()
        ax.semilogy([i + 1 for i in its], losses, lw=0.5, alpha=0.5, label="per iteration")
        ax.semilogy([i + width for i in its[:len(smooth)]], smooth, lw=1.5, label=f"running mean ({width})")
        ax.legend(fontsize=8)
    ax.set(xlabel="iteration", ylabel="window position loss [cells$^2$]", title=f"prior {family}: teacher forcing")
    for k, (name, label) in enumerate((("uniaxial", r"$\tau_{xx}$"), ("shear", r"$\tau_{xy}$"))):
        ax = fig.add_subplot(1, 3, k + 2)
        curve = result.curves[name]
        for law, style in (("reference", "k-"), ("untrained", "C1:"), ("trained", "C0--")):
            ax.plot(curve["strain"], curve[law], style, label=law)
        ax.set(xlabel=f"{name} strain [1]", ylabel=f"{label} [Pa]", title=f"{name} response")
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
