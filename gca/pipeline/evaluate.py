"""The evaluate stage's glue: one trained run of a scene (params -> typed configs -> ``gca.eval``)."""

from __future__ import annotations

import math
from pathlib import Path

from gca.eval.capture import evaluate_capture
from gca.eval.evaluate import chamfer_from_launch, device_name, evaluate_run, law_metrics
from gca.io import read_json
from gca.pipeline.settings import Settings
from gca.pipeline.track import git_commit
from gca.pipeline.train import load_learned_law, solver_for, trained_velocity, velocity_path
from gca.scenes.world import Body
from gca.train.config import run_dir_name


def _trained_run(settings: Settings, scene_name: str, method, inputs, body: Body, runs_dir: Path, device: str,
                 seed: int | None):
    """(scene, seed, run name, train.json, the run's learned law, its launch velocity [v0, w0]) of one trained run;
    an explicit row's launch is its own learned one, every other row's the estimate from its seed's observations
    (:func:`gca.pipeline.train.trained_velocity`: the one the run trained with)."""
    scene = settings.scene(scene_name)
    seed = settings.train_for(seed).seed
    name = run_dir_name(method.name, seed)
    train = read_json(runs_dir / name / "train.json")
    law = load_learned_law(settings, scene_name, method, inputs, runs_dir / name,
                           float(body.mass.sum() / body.vol.sum()), device, seed)
    estimate, source = trained_velocity(train, runs_dir, name, seed)
    train = {**train, "velocity_source": source}
    return scene, seed, name, train, law, law.launch_velocity(estimate)


def evaluate_trained(settings: Settings, scene_name: str, method, inputs, body: Body, runs_dir: Path, out_dir: Path,
                     device: str = "cpu", seed: int | None = None) -> dict:
    """The metrics JSON of one trained run (``runs_dir/<run>``: ``method`` with ``seed``) on its scene, as the
    report reads it.

    Args:
        settings: the stage's typed params; scene_name: key of ``scenes``; method: a registry :class:`Method`.
        inputs: the scene's :class:`gca.pipeline.train.SceneInputs` (the prior checkpoint).
        body: the scene's particles and Gaussians on ``device``.
        runs_dir: ``runs/<scene>`` (the seed's velocity estimate and the method's trained law).
        out_dir: ``metrics/eval/<scene>``; the strip, GIF and CD plot go to ``out_dir/<run>/``.
        seed: one of ``train.seeds`` (None: the first); ``<run>`` is
            :func:`gca.train.config.run_dir_name` of (method, seed).
    """
    scene, seed, name, train, law, velocity = _trained_run(settings, scene_name, method, inputs, body, runs_dir,
                                                           device, seed)
    cfg = settings.metrics
    solver = solver_for(settings, scene, device)
    metrics = evaluate_run(solver, law.material, body, velocity, inputs.scene_dir, settings.video.background,
                           out_dir / name, cfg)
    if train["status"] != "ok":
        metrics["status"] = train["status"]
    if scene.law_level:
        metrics.update(law_metrics(law.material, settings.material(scene.material), scene.dt, cfg))
    metrics.update(launch_error(velocity[0], scene.v0))
    # the law alone, from the true launch (a diagnostic, not the paper's); None where the rollout gave no CD
    metrics["chamfer_mean_true_launch"] = chamfer_from_launch(
        solver, law.material, body, (list(scene.v0), list(scene.w0)), inputs.scene_dir, cfg) \
        if "chamfer_mean" in metrics else None
    return {**metrics, "scene": scene_name, "method": method.name, "object": scene.object, "material": scene.material,
            "seed": seed, "profile": settings.profile, "device": device_name(body.x0.device), "commit": git_commit(),
            "train_seconds": train["train_seconds"], "peak_memory_gib": train["peak_memory_gib"],
            "train_device": train.get("device", "not recorded"), "train_commit": train.get("commit", "not recorded"),
            "velocity_source": train["velocity_source"],
            "term_shares": train.get("term_shares", {}), "runs_per_gpu": train.get("runs_per_gpu", 1),
            "mps": train.get("mps", False), "mps_priority": train.get("mps_priority")}


def launch_error(v0, v0_true) -> dict:
    """The launch velocity a run was evaluated from (``launch_v0`` [3], m/s) and its distance to the scene's true
    one (``launch_v0_error_m_s``; ground truth, read here at evaluation only). The report relates it to the CD
    (``gca.report.tables.launch_note``)."""
    v0 = [float(v) for v in v0]
    return {"launch_v0": v0, "launch_v0_error_m_s": math.dist(v0, [float(v) for v in v0_true])}


def evaluate_capture_trained(settings: Settings, scene_name: str, method, inputs, body: Body, runs_dir: Path,
                             out_dir: Path, device: str = "cpu", seed: int | None = None) -> dict:
    """:func:`evaluate_trained` for a capture scene (no ground truth): :func:`gca.eval.capture.evaluate_capture`
    on the held-out frames, CPR's nearest classical law; ``inputs.prep_dir`` holds the held-out masks."""
    scene, seed, name, train, law, velocity = _trained_run(settings, scene_name, method, inputs, body, runs_dir,
                                                           device, seed)
    metrics = evaluate_capture(solver_for(settings, scene, device), law.material, body,
                               velocity, inputs.scene_dir, inputs.prep_dir,
                               settings.video.background, out_dir / name, settings.metrics, settings.cpr, seed)
    if train["status"] != "ok":
        metrics["status"] = train["status"]
    return {**metrics, "scene": scene_name, "method": method.name, "object": scene.object, "seed": seed,
            "profile": settings.profile, "device": device_name(body.x0.device), "commit": git_commit(),
            "train_device": train.get("device", "not recorded"), "train_commit": train.get("commit", "not recorded"),
            "velocity": train.get("velocity") or read_json(velocity_path(runs_dir, seed)),
            "velocity_source": train["velocity_source"],
            "train_seconds": train["train_seconds"], "peak_memory_gib": train["peak_memory_gib"]}
