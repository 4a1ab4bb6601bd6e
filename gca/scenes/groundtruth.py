"""Ground-truth video generation: simulate a scene with its analytic law, render it from one fixed camera.

What makes the benchmark hard, as in the paper: (1) randomized lighting interference, per-frame light
direction/intensity/colour applied as shading on the Gaussians, so pixel colour is not a reliable
signal; (2) a reduced frame rate (every k-th simulated frame); (3) composite materials.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Mapping

import imageio.v3 as iio
import numpy as np
import torch
from tqdm import tqdm

from gca.io import write_json
from gca.laws.presets import material_from_preset
from gca.render import shading
from gca.render.follow import smallest_axis_normal
from gca.render.camera import Camera, look_at
from gca.scenes.config import OrbitCamera, SceneConfig, VideoConfig
from gca.scenes.store import TRAIN_VIEW, frame_name, view_dir
from gca.scenes.truth import write_truth, write_view_truth
from gca.vision.depth import SimulatedDepth, SimulatedDepthConfig
from gca.scenes.world import Body, gaussians_at, initial_velocity, render_gaussians
from gca.sim.rollout import Rollout, rollout
from gca.sim.solver import MPMSolver, SimConfig


def make_camera(spec: OrbitCamera, resolution: int) -> Camera:
    """Square-image pinhole camera for an orbit spec."""
    return look_at(spec.eye(), spec.target, (0.0, 1.0, 0.0), spec.fov_deg, resolution, resolution)


def scene_cameras(scene: SceneConfig, resolution: int) -> dict[str, Camera]:
    """``train0`` (monocular), ``train1..`` (extra training views), ``eval0..`` (held out)."""
    cams = {TRAIN_VIEW: make_camera(scene.camera, resolution)}
    cams.update({f"train{i + 1}": make_camera(c, resolution) for i, c in enumerate(scene.extra_train_cameras)})
    cams.update({f"eval{i}": make_camera(c, resolution) for i, c in enumerate(scene.eval_cameras)})
    return cams


def simulate_scene(body: Body, material, scene: SceneConfig, video: VideoConfig, sim: SimConfig,
                   device: str | torch.device = "cpu") -> Rollout:
    """Roll the ground-truth material out for ``video.n_frames`` frames (no gradients)."""
    solver = MPMSolver(dataclasses.replace(sim, dt=scene.dt), device)
    dtype = body.x0.dtype
    v = initial_velocity(body.x0, torch.tensor(scene.v0, dtype=dtype, device=body.x0.device),
                         torch.tensor(scene.w0, dtype=dtype, device=body.x0.device))
    with torch.no_grad():
        return rollout(solver, material, body.x0, v, body.vol, body.mass,
                       n_steps=video.n_frames * video.substeps, steps_per_frame=video.substeps, checkpoint=False)


def _render_view(body: Body, traj: Rollout, frames: list[int], camera: Camera, lights, bg) -> dict:
    """Render the kept frames of one view with per-frame shading. Returns numpy stacks."""
    rgb, alpha, depth = [], [], []
    for j, f in enumerate(frames):
        means, covs = gaussians_at(body, traj.x[f], traj.F[f])
        colors = shading.shade(body.colors, smallest_axis_normal(covs), lights[j])
        out = render_gaussians(body, means, covs, colors, camera, bg)
        rgb.append(out["rgb"].clamp(0, 1).cpu().numpy())
        alpha.append(out["alpha"].cpu().numpy())
        depth.append(out["depth"].cpu().numpy())
    return {"rgb": np.stack(rgb), "alpha": np.stack(alpha), "depth": np.stack(depth)}


def _write_view(out_dir: Path, name: str, images: dict) -> None:
    """The observable part of one view: its lit frames (nothing else of the render leaves for training)."""
    folder = view_dir(out_dir, name)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    for i, rgb in enumerate(images["rgb"]):
        iio.imwrite(folder / "rgb" / frame_name(i), (rgb * 255 + 0.5).astype(np.uint8))


def generate(out_dir: Path, gt_dir: Path, body: Body, scene_name: str, scene: SceneConfig, video: VideoConfig,
             sim: SimConfig, material_preset: Mapping, light_cfg: "shading.LightingConfig",
             depth_cfg: SimulatedDepthConfig = SimulatedDepthConfig(), seed: int = 0,
             device: str | torch.device = "cpu") -> dict:
    """Simulate and render every view of a scene: observations into ``out_dir``, ground truth into ``gt_dir``
    (two empty directories; layouts in :mod:`gca.scenes.store` and :mod:`gca.scenes.truth`).

    Returns:
        Summary metrics (counts, mean mask coverage, displacement of the centre of mass).
    """
    material = material_from_preset(material_preset, dt=scene.dt, n_particles=body.n_particles).to(device=device, dtype=body.x0.dtype)
    traj = simulate_scene(body, material, scene, video, sim, device)
    frames = video.video_frames()
    cameras = scene_cameras(scene, video.resolution)
    lights = shading.sample_lights(light_cfg, len(frames), seed=scene.light_seed)
    bg = torch.tensor(video.background, dtype=body.x0.dtype, device=body.x0.device)
    coverage = {}
    for name, camera in tqdm(cameras.items(), desc=f"render {scene_name}", unit="view"):
        images = _render_view(body, traj, frames, camera, lights, bg)
        _write_view(out_dir, name, images)
        write_view_truth(gt_dir, name, images["alpha"], images["depth"], video.mask_threshold)
        mask = images["alpha"] > video.mask_threshold
        coverage[name] = float(mask.mean())
        if name == TRAIN_VIEW:  # the simulated estimator's output: an observation the ground truth makes
            rgb8 = (images["rgb"] * 255 + 0.5).astype(np.uint8)
            est = SimulatedDepth(depth_cfg, seed).estimate(rgb8, np.where(mask, images["depth"], 0.0), mask)
            np.save(view_dir(out_dir, name) / "depth_sim.npy", est.astype(np.float32))
    x = traj.x[[0] + frames].cpu().numpy().astype(np.float32)
    write_truth(gt_dir, x, {"scene": scene_name, "material": scene.material, "preset": dict(material_preset),
                            "v0": list(scene.v0), "w0": list(scene.w0), "light_seed": scene.light_seed})
    write_json(out_dir / "cameras.json", {n: c.to_dict() for n, c in cameras.items()})
    times = [f * video.substeps * scene.dt for f in frames]
    meta = {"scene": scene_name, "object": scene.object, "material": scene.material, "dt": scene.dt,
            "substeps": video.substeps, "frame_every": video.frame_every, "n_frames": video.n_frames,
            "video_frames": frames, "times": times, "n_particles": body.n_particles,
            "n_gaussians": body.n_gaussians, "resolution": video.resolution,
            "views": {"train": [n for n in cameras if n.startswith("train")],
                      "eval": [n for n in cameras if n.startswith("eval")]}}
    write_json(out_dir / "meta.json", meta)
    _write_preview(out_dir)
    com = x.mean(axis=1)
    return {"n_particles": body.n_particles, "n_gaussians": body.n_gaussians, "n_video_frames": len(frames),
            "mask_coverage_train0": coverage[TRAIN_VIEW], "com_drop_m": float(com[0, 1] - com[:, 1].min()),
            "max_clamped": int(max(traj.clamped))}


def _write_preview(out_dir: Path) -> None:
    """Animated GIF of the monocular view."""
    folder = view_dir(out_dir, TRAIN_VIEW) / "rgb"
    frames = [iio.imread(p) for p in sorted(folder.glob("*.png"))]
    iio.imwrite(out_dir / "preview.gif", np.stack(frames), duration=80, loop=0)
