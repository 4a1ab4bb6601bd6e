"""Ground-truth video generation: simulate a scene with its analytic law, render it from one fixed camera.

What makes the benchmark hard, as in the paper (docs/benchmark.md): (1) randomized lighting interference:
per-frame light direction/intensity/colour shading the Gaussians at their deformed state, self- and cast
shadows from their occupancy, optional highlights, per-frame exposure and white-balance drift, so pixel
colour is not a reliable signal; (2) a reduced frame rate (every k-th simulated frame); (3) composite
materials. Observations go to the scene directory, ground truth to the ground-truth directory.

Seeds (issue 22 item 4): the scene is simulated once; each training seed k of ``train.seeds`` also gets its own
nuisance draw of the training views, rendered from that one true trajectory into ``<scene dir>/seed<k>``
(:func:`gca.scenes.store.seed_dir`): its lights, exposure and white-balance walk from
``nuisance_seed(light_seed, k)``, its depth-estimator noise from ``nuisance_seed(seed, k)``; the segmentation
noise follows, since preprocessing segments each seed's own lit frames against its own plate. Seed 0's draw is
the top level, unchanged. The ground truth (trajectory, true alpha and depth, unlit render) does not depend on
the draw and is written once.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Mapping, Sequence

import imageio.v3 as iio
import numpy as np
import torch
from tqdm import tqdm

from gca.io import write_json
from gca.laws.presets import material_from_preset
from gca.render import shading
from gca.render.follow import smallest_axis_normal
from gca.render.camera import Camera, look_at
from gca.render.shadow import light_visibility
from gca.scenes.config import OrbitCamera, SceneConfig, VideoConfig, scene_video
from gca.scenes.store import TRAIN_VIEW, frame_name, nuisance_seed, seed_dir, view_dir
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
    """Roll the ground-truth material out for ``video.n_frames`` frames of the scene's timing (no gradients)."""
    video = scene_video(video, scene)
    solver = MPMSolver(dataclasses.replace(sim, dt=scene.dt), device)
    dtype = body.x0.dtype
    v = initial_velocity(body.x0, torch.tensor(scene.v0, dtype=dtype, device=body.x0.device),
                         torch.tensor(scene.w0, dtype=dtype, device=body.x0.device))
    with torch.no_grad():
        return rollout(solver, material, body.x0, v, body.vol, body.mass,
                       n_steps=video.n_frames * video.substeps, steps_per_frame=video.substeps, checkpoint=False)


def _render_view(body: Body, traj: Rollout, frames: list[int], camera: Camera, lights, bg,
                 cfg: "shading.LightingConfig" = shading.LightingConfig(), unlit: bool = False) -> dict:
    """Render the kept frames of one view with per-frame lighting interference. Returns numpy stacks.

    Per frame: the Gaussians' normals at the deformed state, their visibility from the light (self- and
    cast shadows, ``cfg.shadows``), Lambert + optional specular shading, the object composited over the lit
    floor with its cast shadow (``cfg.floor_shadow``), then the camera response (exposure, white balance).
    ``unlit``: also the render with the base colours over the plain background (the lighting statistic's
    reference; ground truth only).
    """
    rgb, alpha, depth, plain = [], [], [], []
    dtype, device = body.x0.dtype, body.x0.device
    pts, hit = shading.floor_points(camera, dtype, device) if cfg.floor_shadow else (None, None)
    eye = torch.tensor(camera.center.tolist(), dtype=dtype, device=device)
    black = torch.zeros(3, dtype=dtype, device=device)
    for j, f in enumerate(frames):
        light = lights[j]
        means, covs = gaussians_at(body, traj.x[f], traj.F[f])
        vis, vis_floor = (light_visibility(means, covs, body.opacities, light.direction, cfg.shadow_resolution,
                                           pts[hit] if pts is not None else None)
                          if cfg.shadows else (None, None))
        if vis_floor is not None:
            full = torch.ones(hit.shape[0], dtype=dtype, device=device)
            full[hit] = vis_floor
            vis_floor = full
        view_dirs = torch.nn.functional.normalize(eye - means, dim=-1)
        colors = shading.shade(body.colors, smallest_axis_normal(covs), light, vis, view_dirs, cfg.specular,
                               cfg.shininess)
        out = render_gaussians(body, means, covs, colors, camera, black)
        a = out["alpha"][..., None]
        scene_bg = shading.background_image(camera, bg, light, vis_floor, hit)
        lit = shading.camera_response(out["rgb"] + (1.0 - a) * scene_bg, light)
        rgb.append(lit.clamp(0, 1).cpu().numpy())
        alpha.append(out["alpha"].cpu().numpy())
        depth.append(out["depth_expected"].cpu().numpy())  # alpha-normalised z: "depth" is sum_i w_i z_i (alpha z at edges)
        if unlit:
            plain.append(render_gaussians(body, means, covs, body.colors, camera, bg)["rgb"].clamp(0, 1).cpu().numpy())
    images = {"rgb": np.stack(rgb), "alpha": np.stack(alpha), "depth": np.stack(depth)}
    if unlit:
        images["unlit"] = np.stack(plain)
    return images


def unexplained_colour_share(lit: np.ndarray, unlit: np.ndarray, mask: np.ndarray) -> float:
    """Share of the in-object colour variance of the lit video that the best per-frame affine colour map of
    the unlit render cannot explain (issue 21, item 2).

    Per frame t, over the object pixels p (``mask``): least squares ``lit_p ~ A_t unlit_p + b_t`` (A_t 3x3,
    b_t [3]); returns ``sum_t |residual_t|^2 / sum_t |lit_t - mean_t(lit_t)|^2`` (0: lighting is a global
    colour change; 1: nothing of it is).

    Args:
        lit, unlit: [T, H, W, 3] in [0, 1]; mask: [T, H, W] bool.
    """
    res, tot = 0.0, 0.0
    for L, U, m in zip(lit, unlit, mask):
        if m.sum() < 8:
            continue
        y, x = L[m].astype(np.float64), U[m].astype(np.float64)
        X = np.concatenate([x, np.ones((len(x), 1))], 1)
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        res += float(((X @ coef - y) ** 2).sum())
        tot += float(((y - y.mean(0)) ** 2).sum())
    return res / tot if tot > 0 else 0.0


def _write_view(out_dir: Path, name: str, images: dict) -> None:
    """The observable part of one view: its lit frames (nothing else of the render leaves for training)."""
    folder = view_dir(out_dir, name)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    for i, rgb in enumerate(images["rgb"]):
        iio.imwrite(folder / "rgb" / frame_name(i), (rgb * 255 + 0.5).astype(np.uint8))


def _observe(out_dir: Path, name: str, images: dict, camera: Camera, lights, bg, depth_cfg: SimulatedDepthConfig,
             depth_seed: int, mask_threshold: float) -> None:
    """What the camera of view ``name`` records under one nuisance draw (``lights``; ``depth_seed`` for the
    simulated estimator of the monocular view): the lit frames, the clean plate and, for ``train0``, the
    estimator's depth (an observation the ground truth makes: it needs the true depth)."""
    _write_view(out_dir, name, images)
    plate = shading.camera_response(shading.background_image(camera, bg, lights[0]), lights[0])
    iio.imwrite(view_dir(out_dir, name) / "plate.png", (plate.cpu().numpy() * 255 + 0.5).astype(np.uint8))
    if name == TRAIN_VIEW:
        mask = images["alpha"] > mask_threshold
        rgb8 = (images["rgb"] * 255 + 0.5).astype(np.uint8)
        est = SimulatedDepth(depth_cfg, depth_seed).estimate(rgb8, np.where(mask, images["depth"], 0.0), mask)
        np.save(view_dir(out_dir, name) / "depth_sim.npy", est.astype(np.float32))


def _lighting_stats(images: dict, unlit: np.ndarray, mask: np.ndarray) -> dict:
    return {"lighting_unexplained_share": unexplained_colour_share(images["rgb"], unlit, mask),
            "image_mean_range": float(np.ptp(images["rgb"].mean(axis=(1, 2, 3))))}


def generate(out_dir: Path, gt_dir: Path, body: Body, scene_name: str, scene: SceneConfig, video: VideoConfig,
             sim: SimConfig, material_preset: Mapping, light_cfg: "shading.LightingConfig",
             depth_cfg: SimulatedDepthConfig = SimulatedDepthConfig(), seed: int = 0,
             device: str | torch.device = "cpu", seeds: Sequence[int] = (0,)) -> dict:
    """Simulate and render every view of a scene: observations into ``out_dir``, ground truth into ``gt_dir``
    (two empty directories; layouts in :mod:`gca.scenes.store` and :mod:`gca.scenes.truth`).

    Args:
        seed: the global seed (seed 0's depth-estimator draw; the lighting's is ``scene.light_seed``).
        seeds: the training seeds (``train.seeds``); each k > 0 gets its own nuisance draw of the training views
            in ``out_dir/seed<k>`` (module doc), from the same simulated trajectory. Seed 0's draw is the top level
            whether or not 0 is among them (evaluation views, nuisance statistics).

    Returns:
        Summary metrics (counts, mean mask coverage, displacement of the centre of mass); seed k's lighting
        statistics as ``seed<k>/<name>``.
    """
    video = scene_video(video, scene)
    material = material_from_preset(material_preset, dt=scene.dt, n_particles=body.n_particles).to(device=device, dtype=body.x0.dtype)
    traj = simulate_scene(body, material, scene, video, sim, device)
    frames = video.video_frames()
    cameras = scene_cameras(scene, video.resolution)
    lights = shading.sample_lights(light_cfg, len(frames), seed=scene.light_seed)
    bg = torch.tensor(video.background, dtype=body.x0.dtype, device=body.x0.device)
    coverage, stats, unlit = {}, {}, None
    for name, camera in tqdm(cameras.items(), desc=f"render {scene_name}", unit="view"):
        images = _render_view(body, traj, frames, camera, lights, bg, light_cfg, unlit=name == TRAIN_VIEW)
        _observe(out_dir, name, images, camera, lights, bg, depth_cfg, seed, video.mask_threshold)
        write_view_truth(gt_dir, name, images["alpha"], images["depth"], video.mask_threshold, images.get("unlit"))
        mask = images["alpha"] > video.mask_threshold
        coverage[name] = float(mask.mean())
        if name == TRAIN_VIEW:
            unlit = images["unlit"]
            stats.update(_lighting_stats(images, unlit, mask))
    x = traj.x[[0] + frames].cpu().numpy().astype(np.float32)
    write_truth(gt_dir, x, {"scene": scene_name, "material": scene.material, "preset": dict(material_preset),
                            "v0": list(scene.v0), "w0": list(scene.w0), "light_seed": scene.light_seed})
    write_json(out_dir / "cameras.json", {n: c.to_dict() for n, c in cameras.items()})
    times = [f * video.substeps * scene.dt for f in frames]
    meta = {"scene": scene_name, "object": scene.object, "material": scene.material, "dt": scene.dt,
            "substeps": video.substeps, "frame_every": video.frame_every, "n_frames": video.n_frames,
            "video_frames": frames, "times": times, "n_particles": body.n_particles,
            "timing": video.timing, "fps": 1.0 / (video.substeps * video.frame_every * scene.dt),
            "duration_s": frames[-1] * video.substeps * scene.dt,
            "n_gaussians": body.n_gaussians, "resolution": video.resolution,
            "views": {"train": [n for n in cameras if n.startswith("train")],
                      "eval": [n for n in cameras if n.startswith("eval")]}}
    write_json(out_dir / "meta.json", meta)
    _write_preview(out_dir)
    for k in sorted(set(seeds) - {0}):  # the other seeds' draws of the training views, from the same trajectory
        folder = seed_dir(out_dir, k)
        lights_k = shading.sample_lights(light_cfg, len(frames), seed=nuisance_seed(scene.light_seed, k))
        train_views = {n: c for n, c in cameras.items() if n.startswith("train")}
        for name, camera in tqdm(train_views.items(), desc=f"render {scene_name} seed {k}", unit="view"):
            images = _render_view(body, traj, frames, camera, lights_k, bg, light_cfg)
            _observe(folder, name, images, camera, lights_k, bg, depth_cfg, nuisance_seed(seed, k), video.mask_threshold)
            if name == TRAIN_VIEW:
                mask = images["alpha"] > video.mask_threshold
                stats.update({f"seed{k}/{key}": v for key, v in _lighting_stats(images, unlit, mask).items()})
        write_json(folder / "cameras.json", {n: c.to_dict() for n, c in train_views.items()})
        write_json(folder / "meta.json", {**meta, "views": {"train": list(train_views), "eval": []}, "seed": k})
    com = x.mean(axis=1)
    return {"n_particles": body.n_particles, "n_gaussians": body.n_gaussians, "n_video_frames": len(frames),
            "mask_coverage_train0": coverage[TRAIN_VIEW], "com_drop_m": float(com[0, 1] - com[:, 1].min()),
            "max_clamped": int(max(traj.clamped)), **stats}


def _write_preview(out_dir: Path) -> None:
    """Animated GIF of the monocular view."""
    folder = view_dir(out_dir, TRAIN_VIEW) / "rgb"
    frames = [iio.imread(p) for p in sorted(folder.glob("*.png"))]
    iio.imwrite(out_dir / "preview.gif", np.stack(frames), duration=80, loop=0)
