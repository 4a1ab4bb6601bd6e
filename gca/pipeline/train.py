"""Assemble a scene's training data from the pipeline's files and train one method on it.

    runs/<scene>/velocity.json           seed 0's initial velocity estimate (prior law, first frames of its observations)
    runs/<scene>/velocity@seed<k>.json   seed k's, from seed k's own observations (:func:`velocity_path`)
    runs/<scene>/<run>/law.pt            what training changed (adapter / full weights / explicit params)
    runs/<scene>/<run>/checkpoint.pt     resumable optimiser state (removed when the run completes)
    runs/<scene>/<run>/train.json        status, seconds, peak memory, MLflow run id, last losses
    runs/<scene>/<run>/history.json      per-iteration losses
    runs/<scene>/<run>/loss.png          loss curve

``<run>`` is the method's name for seed 0 and ``<method>@seed<k>`` for seed k (``train.seeds``,
:func:`gca.train.config.run_dir_name`). The seed fixes the law's initialisation and the nuisance draw the run
observes: seed k's runs (every method's, the launch velocity's) read seed k's observations,
``data/scenes/<scene>/seed<k>`` and ``data/prep/<scene>/seed<k>`` (:func:`observed_inputs`; seed 0: the top
level); evaluation stays against the one true trajectory.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

from gca import config, gpu_slot
from gca.efficiency import measure
from gca.eval.evaluate import device_name
from gca.io import atomic_path, read_json, save_torch, write_json
from gca.laws.base import Material
from gca.laws.checkpoint import load_adapter, load_prior, save_adapter, save_prior
from gca.laws.neural import mlp_kernel_problem
from gca.laws.presets import material_category
from gca.pipeline.settings import Settings
from gca.pipeline.track import git_commit
from gca.scenes import SceneConfig, read_meta, load_views
from gca.scenes.preprocess import load_prep
from gca.scenes.store import frame_substeps, seed_dir
from gca.scenes.world import Body, initial_velocity
from gca.sim.solver import MPMSolver
from gca.train.config import TrainConfig, neuma_recipe, run_dir_name
from gca.train.law import LearnedLaw, build_law
from gca.train.loop import TrainResult, train
from gca.train.objective import Objective, TrainData
from gca.train.methods import Method
from gca.train.velocity import estimate_velocity

MULTI_VIEWS = ("train0", "train1", "train2")


@dataclasses.dataclass
class SceneInputs:
    """Paths of one scene's pipeline inputs."""

    scene_dir: Path
    prep_dir: Path
    particles: Path
    gaussians: Path
    prior: Path


def observed_inputs(settings: Settings, scene_name: str, inputs: SceneInputs, seed: int) -> SceneInputs:
    """``inputs`` with the observations of training seed ``seed``: its nuisance draw's scene and preprocessing
    directories (:func:`gca.scenes.store.seed_dir`). A capture scene has one real video, so every seed observes
    it (its seeds differ in the law's initialisation only)."""
    if settings.scene(scene_name).is_capture:
        return inputs
    return dataclasses.replace(inputs, scene_dir=seed_dir(inputs.scene_dir, seed),
                               prep_dir=None if inputs.prep_dir is None else seed_dir(inputs.prep_dir, seed))


def velocity_path(runs_dir: Path, seed: int) -> Path:
    """The launch-velocity estimate the runs of ``seed`` start from: ``runs/<scene>/velocity.json`` (seed 0) or
    ``velocity@seed<k>.json``, each fitted to that seed's own observations."""
    return Path(runs_dir) / ("velocity.json" if seed == 0 else f"velocity@seed{seed}.json")


def default_device() -> str:
    """``cuda`` when a GPU is visible, else ``cpu``."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def solver_for(settings: Settings, scene: SceneConfig, device="cpu") -> MPMSolver:
    """The ``sim`` section's solver at the scene's ``dt``."""
    return MPMSolver(dataclasses.replace(settings.sim, dt=scene.dt), device)


def load_train_data(settings: Settings, inputs: SceneInputs, method: Method, velocity: tuple[list, list], background,
                    device="cpu", *, dt: float) -> TrainData:
    """Everything the method may observe: training views, preprocessed depth/masks/keypoints.

    ``dt``: the training simulation's time step [s]; the scene must have been made at it
    (:func:`gca.scenes.store.frame_substeps`)."""
    meta = read_meta(inputs.scene_dir)
    names = MULTI_VIEWS if method.views == "multi" else MULTI_VIEWS[:1]
    views = load_views(inputs.scene_dir, [n for n in names if n in meta["views"]["train"]])
    depth, masks, keypoints = load_prep(inputs.prep_dir, len(meta["video_frames"]))
    views["train0"].mask = masks  # a monocular method sees its own masks, not the renderer's alpha
    body = settings.load_body(inputs.particles, inputs.gaussians, device)
    return TrainData(body=body, views=views, video_frames=list(meta["video_frames"]),
                     substeps=frame_substeps(meta, dt, inputs.scene_dir),
                     est_depth=depth, keypoints=keypoints, v_init=velocity_field(body, velocity),
                     background=tuple(background))


def estimate_scene_velocity(settings: Settings, scene_name: str, inputs: SceneInputs, out: Path, device="cpu") -> dict:
    """Fit the launch velocity with the prior law; write ``velocity.json``."""
    scene = settings.scene(scene_name)
    meta = read_meta(inputs.scene_dir)
    view = load_views(inputs.scene_dir, ["train0"])["train0"]
    view.mask = load_prep(inputs.prep_dir, len(meta["video_frames"]))[1]
    body = settings.load_body(inputs.particles, inputs.gaussians, device)
    prior = load_prior(inputs.prior, family=scene.prior)
    material = Material(prior.elasticity, prior.plasticity, float(body.mass.sum() / body.vol.sum())).to(device)
    v0, w0, history = estimate_velocity(solver_for(settings, scene, device), material, body, view, meta["video_frames"],
                                        frame_substeps(meta, scene.dt, inputs.scene_dir), settings.velocity,
                                        settings.video.background, settings.match)
    result = {"v0": v0.tolist(), "w0": w0.tolist(), "loss_first": history[0] if history else None,
              "loss_last": history[-1] if history else None, "iterations": len(history)}
    write_json(out, result)
    return result


def run_seeds(settings: Settings, method: Method, chosen: Sequence[int] | None = None) -> list[int]:
    """The seeds ``method`` runs with: ``chosen`` (checked against ``train.seeds``) or all of ``train.seeds``.
    A method that does not train (the prior as is) runs every seed too: its law does not depend on the seed, but
    its launch velocity is estimated from the seed's own nuisance draw (:func:`velocity_path`)."""
    seeds = list(settings.train.seeds)
    unknown = sorted(set(chosen or ()) - set(seeds))
    if unknown:
        raise config.ConfigError(f"seeds {unknown} are not in train.seeds {seeds}")
    return [s for s in seeds if s in chosen] if chosen else seeds


def seed_runs(settings: Settings, methods: Sequence[Method], chosen: Sequence[int] | None = None
              ) -> list[tuple[Method, int, str]]:
    """Every ``(method, seed, run name)`` of ``methods`` (:func:`run_seeds` each), seeds outermost in their
    params order, methods in the given order within a seed: a whole table's first seed comes first."""
    per_method = {m.name: run_seeds(settings, m, chosen) for m in methods}
    return [(m, s, run_dir_name(m.name, s)) for s in settings.train.seeds for m in methods
            if s in per_method[m.name]]


def train_config(settings: Settings, method: Method, scene: SceneConfig, seed: int | None = None) -> TrainConfig:
    """``train`` for the run of ``seed``, with NeuMA's published recipe for a method that declares it
    (``gca.train.config.neuma_recipe``: optimiser, learning rates by prior family, schedule, rollout weighting)."""
    tcfg = settings.train_for(seed)
    return neuma_recipe(tcfg, scene.prior) if method.recipe == "neuma" else tcfg


def law_for(settings: Settings, method: Method, scene: SceneConfig, inputs: SceneInputs, rho: float,
            device="cpu", seed: int | None = None, velocity: tuple[list, list] | None = None) -> LearnedLaw:
    """The method's law to train (or its trained law's skeleton) for the run of ``seed``, density ``rho`` [kg/m^3].

    An explicit (PAC-NeRF-style) method is told the scene's material category (ground truth it assumes given:
    ``gca.laws.presets.material_category`` of ``materials.<scene material>``) and learns its launch from
    ``velocity``, the shared estimate (None when a trained state is loaded next)."""
    tcfg = train_config(settings, method, scene, seed)
    category = material_category(settings.material(scene.material)) if method.law == "explicit" else None
    law = build_law(method, inputs.prior, scene.prior, rho, settings.lora, tcfg.lr_elasticity, tcfg.lr_plasticity,
                    tcfg.lr_explicit, family_presets=settings.prior_families, dt=scene.dt,
                    seed=tcfg.seed, category=category, velocity=velocity)
    law.material.to(device)
    if law.launch is not None:
        law.launch.to(device)
    return law


def objective_for(settings: Settings, method: Method, data: TrainData, scene: SceneConfig,
                  seed: int | None = None) -> Objective:
    """The method's training objective on ``data`` for the run of ``seed``."""
    return Objective(method, data, train_config(settings, method, scene, seed), settings.rdga, settings.cpr, settings.match,
                     cpr_target=scene.cpr_target)


def velocity_field(body: Body, velocity: tuple[list, list]) -> torch.Tensor:
    """Per-particle initial velocity [P, 3] from the estimated (v0, w0)."""
    v0, w0 = (torch.tensor(v, dtype=body.x0.dtype, device=body.x0.device) for v in velocity)
    return initial_velocity(body.x0, v0, w0)


@dataclasses.dataclass
class TrainJob:
    """What one training run is made of, as the train stage builds it (:func:`train_job`)."""
    cfg: TrainConfig
    data: TrainData
    law: LearnedLaw
    objective: Objective
    solver: MPMSolver


def check_mlp_kernel(kernel: str, device) -> None:
    """One ``ConfigError`` line when ``train.mlp_kernel`` ``kernel`` cannot run on ``device`` (the paper profile's
    ``triton_tf32`` on a CPU: :func:`gca.laws.neural.mlp_kernel_problem`); the stage and the tuning call it before
    their launch-velocity fits, :func:`train_job` before reading any input."""
    problem = mlp_kernel_problem(kernel, device)
    if problem:
        raise config.ConfigError(f"params.yaml: train.mlp_kernel={kernel} {problem}; on this machine run the ci "
                                 f"profile or set train.mlp_kernel: torch (FP32)")


def train_job(settings: Settings, scene_name: str, method: Method, inputs: SceneInputs, velocity: tuple[list, list],
              device="cpu", seed: int | None = None) -> TrainJob:
    """The run of ``method`` on a scene with ``seed``: its config, observed data (its seed's, :func:`observed_inputs`),
    law, objective and solver; ``velocity`` is its seed's estimate. The one place a run is assembled (the stage and
    ``benchmarks/profile_train.py`` both call it)."""
    scene = settings.scene(scene_name)
    tcfg = train_config(settings, method, scene, seed)
    check_mlp_kernel(tcfg.mlp_kernel, device)  # before any data is read (the stage and the tuning check earlier)
    data = load_train_data(settings, observed_inputs(settings, scene_name, inputs, tcfg.seed), method, velocity,
                           settings.video.background, device, dt=scene.dt)
    law = law_for(settings, method, scene, inputs, float(data.body.mass.sum() / data.body.vol.sum()), device, tcfg.seed,
                  velocity)
    return TrainJob(tcfg, data, law, objective_for(settings, method, data, scene, tcfg.seed),
                    solver_for(settings, scene, device))


def train_method(settings: Settings, scene_name: str, method: Method, inputs: SceneInputs, velocity: tuple[list, list],
                 out_dir: Path, run=None, device="cpu", seed: int | None = None, keep_checkpoint: bool = False) -> dict:
    """Train ``method`` on a scene with ``seed`` (one of ``train.seeds``; None: the first) into ``out_dir``
    (``runs/<scene>/<run>``); write ``law.pt``, ``history.json``, ``train.json``; return train.json.

    ``keep_checkpoint``: leave ``checkpoint.pt`` (the last iteration's; a diverged run's last periodic one) for the
    caller to clear once what it makes of the run is safe (a tuning unit's evaluation,
    :func:`gca.pipeline.tune.run_unit`): a run started again from it resumes at its end and only selects its law
    (:func:`gca.train.loop.train`), instead of training anew.

    ``inputs`` are the scene's (seed 0's directories); the run reads its seed's observations
    (:func:`observed_inputs`), and ``velocity`` must be its seed's estimate (:func:`velocity_path`).

    A run stopped (its deadline, checkpointed) and resumed by a later process may have shared its GPU otherwise in
    each: train.json's ``processes`` lists every process that trained it (:func:`gpu_sharing`'s fields and the
    iteration it ``resumed_at``, from the checkpoint), and its ``runs_per_gpu``, ``mps`` and ``mps_priority`` merge
    them (:func:`merged_sharing`: ``"mixed"`` for priorities that differ)."""
    scene = settings.scene(scene_name)
    job = train_job(settings, scene_name, method, inputs, velocity, device, seed)
    tcfg, data, law = job.cfg, job.data, job.law
    out_dir.mkdir(parents=True, exist_ok=True)
    log = (lambda it, rec: run.log_metrics({k: v for k, v in rec.items() if k != "iteration"}, step=it)) if run else None
    with measure(device) as cost:
        result: TrainResult = train(job.solver, law, data, job.objective, tcfg,
                                    checkpoint_path=out_dir / "checkpoint.pt", on_iteration=log, process=gpu_sharing())
    save_law(out_dir / "law.pt", law, scene.prior, {"method": method.name, "scene": scene_name})
    write_json(out_dir / "history.json", {"history": result.history})
    if not keep_checkpoint:
        (out_dir / "checkpoint.pt").unlink(missing_ok=True)
    # a resumed run's time includes its earlier processes' (from the checkpoint); its peak is this process's
    summary = {"scene": scene_name, "method": method.name, "seed": tcfg.seed, "status": result.status, "message": result.message,
               "iterations": result.iterations, "train_seconds": cost.wall_s + result.seconds_before,
               "resumed_at": result.resumed_at, "peak_memory_gib": cost.peak_bytes / 2 ** 30,
               "memory_source": cost.source, "render_backend": data.body.backend, "matmul_precision": tcfg.matmul_precision, "mlp_kernel": tcfg.mlp_kernel, "mlflow_run_id": run.run_id if run else None,
               "rejected_updates": result.rejected, "selected": result.selected,
               **merged_sharing(result.processes), "processes": result.processes,  # this process last
               "commit": git_commit(), "device": device_name(device),  # what made it (a resumed run: what finished it)
               "velocity": {"v0": list(map(float, velocity[0])), "w0": list(map(float, velocity[1]))},  # it trained with
               "term_shares": mean_term_shares(result.history),
               "last": result.history[-1] if result.history else {}}
    write_json(out_dir / "train.json", summary)
    _plot_history(result.history, out_dir / "loss.png", f"{scene_name} / {method.name}")
    return summary


def gpu_sharing() -> dict:
    """How the run shared its GPU, from the launcher (``gca.pipeline.grid`` sets ``GCA_RUNS_PER_GPU``, its slots per
    GPU, and ``GCA_MPS``; DVC queue workers set the first, and ``gca.gpu_slot`` the second from the MPS daemon it
    finds): ``runs_per_gpu`` [count] and ``mps`` [bool], and ``mps_priority``: None where the grid gave no priorities,
    else ``"below_normal"`` (its unit yielded the GPU to heavier ones: ``gca.pipeline.grid.below_normal``) or
    ``"normal"`` (beside such runs: faster than an equal share). A time measured with 8 runs on one GPU is not a solo
    time (Table 4 says so); a run started otherwise (dvc repro, by hand) counts as alone. This process's only: a run
    that several processes trained records them all, merged (:func:`merged_sharing`)."""
    mps = os.environ.get(gpu_slot.MPS_ENV) == "1"
    priority = None
    if mps and os.environ.get(gpu_slot.PRIORITY_GRID_ENV) == "1":
        low = os.environ.get(gpu_slot.MPS_PRIORITY_ENV) == gpu_slot.MPS_BELOW_NORMAL
        priority = "below_normal" if low else "normal"
    return {"runs_per_gpu": gpu_slot.runs_per_gpu(), "mps": mps, "mps_priority": priority}


def merged_sharing(processes: list[dict]) -> dict:
    """The GPU sharing of a run that ``processes`` trained (each with :func:`gpu_sharing`'s fields; a field missing:
    alone, no MPS, no priority): ``runs_per_gpu`` their largest [count], ``mps`` whether any ran under MPS [bool],
    ``mps_priority`` theirs where all had the same, else ``"mixed"`` (say 90 % of the iterations below normal, the
    rest at normal after a resume: neither an equal share nor a yielding one throughout)."""
    priorities = {p.get("mps_priority") for p in processes}
    return {"runs_per_gpu": max(int(p.get("runs_per_gpu") or 1) for p in processes),
            "mps": any(bool(p.get("mps")) for p in processes),
            "mps_priority": priorities.pop() if len(priorities) == 1 else "mixed"}


def mean_term_shares(history: list[dict]) -> dict[str, float]:
    """Mean over the iterations that measured them (``train.term_shares_every``) of each ``share/<term>/<norm|cos>``
    of the history; ``{}`` when none did."""
    keys = sorted({k for rec in history for k in rec if k.startswith("share/")})
    out = {}
    for key in keys:
        values = [rec[key] for rec in history if key in rec and rec[key] == rec[key]]
        if values:
            out[key] = sum(values) / len(values)
    return out


def _plot_history(history: list[dict], path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=100)
    if history:
        ax.plot([h["iteration"] for h in history], [h["loss"] for h in history], marker="o", ms=3)
    ax.set(xlabel="iteration", ylabel="loss", title=title)
    ax.set_yscale("symlog", linthresh=1e-3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": None})
    plt.close(fig)


def load_learned_law(settings: Settings, scene_name: str, method: Method, inputs: SceneInputs, run_dir: Path,
                     rho: float, device="cpu", seed: int | None = None) -> LearnedLaw:
    """Rebuild a trained method's law from ``run_dir/law.pt`` (the prior + what training changed)."""
    scene = settings.scene(scene_name)
    law = law_for(settings, method, scene, inputs, rho, device, seed)
    path = run_dir / "law.pt"
    if path.is_file():
        load_law(path, law, scene.prior)
    elif method.trains:
        raise FileNotFoundError(f"{path}: missing trained law of {method.name} (run the train stage)")
    return law


def save_law(path: Path, law: LearnedLaw, family: str, metadata: Mapping) -> None:
    """What training changed: LoRA adapters (checked against their prior on load), all network weights
    (full fine-tuning, a prior checkpoint), or the explicit law's parameters; nothing when untrained."""
    e, p = law.material.elasticity, law.material.plasticity
    if law.kind == "lora":
        save_adapter(path, e, p, family, metadata=metadata)
    elif law.kind == "full":
        save_prior(path, e, p, family, metadata=dict(metadata))
    elif law.kind == "explicit":
        save_torch({"kind": "explicit", "state": law.state(), "metadata": dict(metadata)}, path)


def load_law(path: Path, law: LearnedLaw, family: str) -> None:
    """Inverse of :func:`save_law` into a freshly built law of the same method (mismatches are refused)."""
    e, p = law.material.elasticity, law.material.plasticity
    if law.kind == "lora":
        load_adapter(path, e, p, family)
    elif law.kind == "full":
        trained = load_prior(path, family=family, config=e.cfg)
        e.load_state_dict(trained.elasticity.state_dict())
        p.load_state_dict(trained.plasticity.state_dict())
    elif law.kind == "explicit":
        payload = torch.load(path, weights_only=False, map_location=law.trainable()[0].device)
        if payload.get("kind") != "explicit":
            raise ValueError(f"{path}: not an explicit-law checkpoint (kind {payload.get('kind')!r})")
        law.load_state(payload["state"])


def read_velocity(path: Path, raw: Mapping | None = None) -> tuple[list[float], list[float]]:
    """(v0 [3] m/s, w0 [3] rad/s) from ``velocity.json`` (or ``raw``, read from ``path``: a run's ``train.json``
    ``velocity``), validated."""
    raw = read_json(path) if raw is None else raw
    for key in ("v0", "w0"):
        v = raw.get(key)
        if v is None or len(v) != 3 or not all(np.isfinite(v)):
            raise ValueError(f"{path}: {key} must be 3 finite numbers, got {v}")
    return raw["v0"], raw["w0"]


def trained_velocity(train: Mapping, runs_dir: Path, name: str,
                     seed: int) -> tuple[tuple[list[float], list[float]], str]:
    """((v0, w0), where from) of a trained run (``train``: its ``runs_dir/<name>/train.json``): the estimate it trained
    with, kept in its ``train.json`` (since session 20), else its seed's shared ``velocity.json`` (older runs). The
    shared file may have been estimated again after the run (a grid going on on another machine, whose remade
    inputs differ in float32 noise, session 20): evaluating a run with the launch velocity it trained with keeps its
    law and its launch one measurement."""
    if "velocity" in train:
        return read_velocity(runs_dir / name / "train.json", train["velocity"]), "train.json"
    return read_velocity(velocity_path(runs_dir, seed)), velocity_path(runs_dir, seed).name
