"""Evaluate one trained method on its scene: the metrics JSON the report stage reads.

Rolls the learned law out from the method's initial velocity over the whole video (no gradients),
and compares with the ground truth the method never saw: Chamfer distance between predicted and
ground-truth particles at every video frame, PSNR/SSIM on the training view and on the held-out
views, LPIPS when its weights exist locally, the law-level response error against the analytic
ground truth (for scenes that ask for it), and efficiency (training time, peak memory, rollout time).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Mapping

import imageio.v3 as iio
import numpy as np
import torch

from gca.eval.config import MetricsConfig
from gca.efficiency import synced_clock
from gca.io import atomic_path
from gca.eval.geometry import CHAMFER_DEFINITION, CHAMFER_DEFINITION_SQUARED, chamfer_over_time
from gca.eval.image import lpips_or_reason, psnr, ssim
from gca.eval.law_response import law_response_curve, law_response_error
from gca.laws.presets import material_from_preset
from gca.scenes import load_trajectory, load_views, read_meta
from gca.scenes.store import frame_substeps
from gca.scenes.world import Body, gaussians_at, initial_velocity, render_gaussians
from gca.sim.cfl import CFLError
from gca.sim.rollout import Rollout, SimulationDiverged, rollout
from gca.sim.solver import MPMSolver


def device_name(device: torch.device | str) -> str:
    """Human-readable device for metrics headers (the GPU model, or the CPU architecture)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    import platform
    return f"cpu ({platform.machine()}, {torch.get_num_threads()} threads)"


def rollout_from(solver: MPMSolver, material, body: Body, velocity: tuple[list, list], video_frames: list[int],
                 substeps: int) -> Rollout:
    """One no-grad rollout of ``material`` from (v0 [3] m/s, w0 [3] rad/s) through the last video frame."""
    v = initial_velocity(body.x0, *(torch.tensor(u, dtype=body.x0.dtype, device=body.x0.device) for u in velocity))
    with torch.no_grad():
        return rollout(solver, material, body.x0, v, body.vol, body.mass, n_steps=video_frames[-1] * substeps,
                       steps_per_frame=substeps, checkpoint=False)


def predict(solver: MPMSolver, material, body: Body, velocity: tuple[list, list], video_frames: list[int],
            substeps: int) -> tuple[Rollout, float]:
    """Full rollout of the learned law (no grad) from (v0, w0); returns the rollout and its wall time [s].

    The timed rollout is the second of two identical ones (:func:`rollout_from`): the first pays the one-off costs
    (kernel loading, CUDA-graph capture) that a user rolling a trained law out repeatedly pays once. The clock
    stops after the device has finished (synchronised).
    """
    rollout_from(solver, material, body, velocity, video_frames, substeps)
    t0 = synced_clock(body.x0.device)
    traj = rollout_from(solver, material, body, velocity, video_frames, substeps)
    return traj, synced_clock(body.x0.device) - t0


def chamfer_to_truth(traj: Rollout, video_frames: list[int], scene_dir: Path, cfg: MetricsConfig) -> torch.Tensor:
    """Chamfer distance [m] per frame [T+1] (frame 0, then each video frame) of a rollout against the true
    trajectory (evaluation only)."""
    gt = torch.as_tensor(load_trajectory(scene_dir), dtype=traj.x.dtype, device=traj.x.device)
    return chamfer_over_time(traj.x[[0] + video_frames], gt, squared=cfg.chamfer_squared)


def image_metrics(body: Body, traj: Rollout, scene_dir: Path, views: list[str], video_frames: list[int],
                  background, cfg: MetricsConfig = MetricsConfig()) -> tuple[dict, dict]:
    """PSNR/SSIM per view (mean over frames) and the rendered frames of each view [T, H, W, 3]."""
    data = load_views(scene_dir, views)
    bg = torch.tensor(background, dtype=body.x0.dtype, device=body.x0.device)
    metrics, frames = {}, {}
    for name, view in data.items():
        renders = []
        t0 = synced_clock(body.x0.device)
        for f in video_frames:
            means, covs = gaussians_at(body, traj.x[f], traj.F[f])
            renders.append(render_gaussians(body, means, covs, body.colors, view.camera, bg)["rgb"].clamp(0, 1))
        pred = torch.stack(renders).permute(0, 3, 1, 2)
        metrics.setdefault("render_seconds", {})[name] = synced_clock(body.x0.device) - t0
        ref = torch.as_tensor(view.rgb, device=pred.device).permute(0, 3, 1, 2)
        metrics[name] = {"psnr": float(psnr(pred, ref, max_val=cfg.image_max_val).mean()),
                         "ssim": float(ssim(pred, ref, max_val=cfg.image_max_val, window=cfg.ssim_window).mean())}
        lp, reason = lpips_or_reason(pred, ref, net=cfg.lpips_net, max_val=cfg.image_max_val)
        metrics[name]["lpips"] = None if lp is None else float(lp.mean())
        metrics["lpips_reason"] = reason
        frames[name] = pred.permute(0, 2, 3, 1).cpu().numpy()
    return metrics, frames


def law_metrics(material, reference_preset: Mapping, dt: float, cfg: MetricsConfig = MetricsConfig()) -> dict:
    """Law-level response error [%] (uniaxial, shear) of the learned elasticity vs the analytic one."""
    reference = material_from_preset(reference_preset, dt=dt).elasticity.float()
    learned = copy.deepcopy(material.elasticity).cpu().float()  # the sweeps are small host tensors
    out, curves = {}, {}
    for kind in cfg.response_sweeps:
        with torch.no_grad():
            out[f"law_error_{kind}_pct"] = law_response_error(learned, reference, kind, cfg.response_points)
            ours = law_response_curve(learned, kind, cfg.response_points)
            ref = law_response_curve(reference, kind, cfg.response_points)
        curves[kind] = {"strain": ours["strain"].tolist(), "ours": ours["component"].tolist(),
                        "reference": ref["component"].tolist()}
    out["law_curves"] = curves
    return out


def write_strip(path: Path, frames: np.ndarray, gt: np.ndarray, n: int = 4) -> None:
    """A qualitative strip: top row ground truth, bottom row prediction, ``n`` frames."""
    idx = np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int)
    top = np.concatenate([gt[i] for i in idx], axis=1)
    bottom = np.concatenate([frames[i] for i in idx], axis=1)
    with atomic_path(path) as tmp:  # a stage stopped while it writes leaves no half-written image
        iio.imwrite(tmp, (np.concatenate([top, bottom], axis=0) * 255 + 0.5).astype(np.uint8), extension=".png")


def chamfer_from_launch(solver: MPMSolver, material, body: Body, velocity: tuple[list, list], scene_dir: Path,
                        cfg: MetricsConfig = MetricsConfig()) -> float | None:
    """Mean Chamfer distance [m] over the video frames of one no-grad rollout of ``material`` from ``velocity``
    (v0 [3] m/s, w0 [3] rad/s) against the true trajectory (evaluation only), as :func:`evaluate_run` measures
    ``chamfer_mean``; None when the rollout diverges. With the scene's true launch it is a diagnostic of the law
    alone: a law's CD from its launch estimate mixes the law's error with the estimate's (session 21)."""
    meta = read_meta(scene_dir)
    frames_idx = list(meta["video_frames"])
    try:
        traj = rollout_from(solver, material, body, velocity, frames_idx, frame_substeps(meta, solver.cfg.dt, scene_dir))
    except (SimulationDiverged, CFLError):
        return None
    return float(chamfer_to_truth(traj, frames_idx, scene_dir, cfg)[1:].mean())


def evaluate_run(solver: MPMSolver, material, body: Body, velocity: tuple[list, list], scene_dir: Path, background,
                 out_dir: Path, cfg: MetricsConfig = MetricsConfig()) -> dict:
    """All trajectory and image metrics of one trained law; writes strip.png and rollout.gif to ``out_dir``."""
    meta = read_meta(scene_dir)
    frames_idx = list(meta["video_frames"])
    metrics: dict = {"chamfer_definition": CHAMFER_DEFINITION_SQUARED if cfg.chamfer_squared else CHAMFER_DEFINITION}
    try:
        traj, seconds = predict(solver, material, body, velocity, frames_idx,
                                frame_substeps(meta, solver.cfg.dt, scene_dir))
    except (SimulationDiverged, CFLError) as exc:  # CFL: the law is too stiff for the scene's dt
        return {**metrics, "status": "diverged", "message": str(exc)}
    cd = chamfer_to_truth(traj, frames_idx, scene_dir, cfg)
    metrics.update(status="ok", rollout_seconds=seconds, chamfer_per_frame=cd.tolist(), chamfer_mean=float(cd[1:].mean()))
    views = ["train0"] + list(meta["views"]["eval"])
    img, rendered = image_metrics(body, traj, scene_dir, views, frames_idx, background, cfg)
    # the video as a user gets it: the rollout plus the training view's frames rendered [s]
    metrics["rollout_render_seconds"] = seconds + img["render_seconds"]["train0"]
    metrics.update(psnr_train=img["train0"]["psnr"], ssim_train=img["train0"]["ssim"],
                   lpips_train=img["train0"]["lpips"], lpips_reason=img["lpips_reason"])
    held = [img[v] for v in meta["views"]["eval"]]
    if held:
        metrics.update(psnr_heldout=float(np.mean([h["psnr"] for h in held])),
                       ssim_heldout=float(np.mean([h["ssim"] for h in held])))
    gt_rgb = load_views(scene_dir, ["train0"])["train0"].rgb
    out_dir.mkdir(parents=True, exist_ok=True)
    write_strip(out_dir / "strip.png", rendered["train0"], gt_rgb)
    with atomic_path(out_dir / "rollout.gif") as tmp:
        iio.imwrite(tmp, (rendered["train0"] * 255 + 0.5).astype(np.uint8), extension=".gif", duration=80, loop=0)
    metrics["strip_png"] = str(out_dir / "strip.png")
    plot_chamfer(out_dir / "cd_time.png", meta["times"], metrics["chamfer_per_frame"][1:])
    return metrics


def plot_chamfer(path: Path, times: list[float], cd: list[float]) -> None:
    """Chamfer distance [m] against simulated time [s] of one run (an MLflow artifact)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.5, 3), dpi=100)
    ax.plot(times, cd, marker="o", ms=3)
    ax.set(xlabel="time [s]", ylabel="Chamfer distance [m]", title="CD over time")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": None})
    plt.close(fig)
