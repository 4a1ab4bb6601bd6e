"""A worked capture the pipeline films itself (README, "Your own object"): a procedural object thrown onto the
floor, simulated with a known law, rendered from one fixed camera with sensor noise over a textured
background, and exported exactly as a user's capture comes:

    <out>/scan.ply          the static 3DGS scan, in the capture's frame: z up, centimetres (so the
                            example exercises scan_options up: "+z", metres_per_unit: 0.01)
    <out>/frames/00000.png  the video [H, W] at ``fps`` (rendered, Gaussian noise of ``noise`` std)
    <out>/transforms.json   the video camera (nerfstudio layout, OpenGL axes), calibrated in the scan's frame
    <out>/plate.png         the empty scene (optional for a user: the median of the frames otherwise)
    <out>/truth.json        the law and launch velocity it was made with (never read by the pipeline)

    python -m gca.capture.example --out captures/example

The defaults match ``scenes.example_capture`` of params.yaml (fps; dt at the paper profile; particles at the CI
profile).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from gca import io
from gca.assets.objects import gaussians_from_mesh, make_object
from gca.assets.particles import ParticleConfig, convert
from gca.assets.ply import covariances, opacities, sh0_to_rgb, write_ply
from gca.assets.scan import ScanConfig, prepare_scan, transform_cloud, up_rotation
from gca.capture.cameras import transform_camera, write_transforms_json
from gca.laws.presets import material_from_preset
from gca.render.camera import look_at
from gca.render.follow import Binding, follow
from gca.render.rasterize import render
from gca.sim.rollout import rollout
from gca.sim.solver import MPMSolver, SimConfig

SCAN_OPTIONS = ScanConfig(up="+z", metres_per_unit=0.01)  # what params.yaml's objects.example_capture states


@dataclasses.dataclass(frozen=True)
class ExampleConfig:
    """The example capture's settings (SI units)."""

    shape: str = "ball"  # gca.assets.objects shape
    size: float = 0.12  # largest side [m]
    n_gaussians: int = 1500
    seed: int = 0
    density: float = 1000.0  # [kg/m^3]
    law: tuple = (("elasticity", "corotated"), ("plasticity", "identity"), ("E", 5.0e4), ("nu", 0.3), ("rho", 1000.0))
    v0: tuple[float, float, float] = (0.3, -1.5, 0.0)  # launch velocity [m/s, sim frame]
    fps: float = 50.0  # video frame rate [1/s]
    dt: float = 1.0e-3  # MPM step it is filmed with [s] (scenes.example_capture.dt at the paper profile; CI: 2e-3)
    n_frames: int = 10
    width: int = 64  # [px]
    height: int = 48
    noise: float = 0.01  # sensor noise std [0-1 colour units]
    n_grid: int = 16  # the CI profile's grid
    particles: ParticleConfig = ParticleConfig(spacing=0.03, floor_gap=0.08)  # params.yaml particles at ci


def _plate(width: int, height: int, seed: int) -> np.ndarray:
    """A textured empty scene [H, W, 3] float in [0, 1]: a wall gradient over a darker floor, with blotches."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    wall = np.stack([0.55 + 0.2 * xx, 0.6 + 0.1 * yy, 0.7 - 0.1 * xx], -1)
    floor = np.stack([0.35 + 0.05 * xx, 0.3 + 0.05 * yy, 0.25 + 0 * xx], -1)
    img = np.where((yy > 0.55 * height / max(height, width))[..., None], floor, wall)
    return np.clip(img + 0.03 * rng.standard_normal((height, width, 1)), 0, 1)


def make_example(out: str | Path, cfg: ExampleConfig = ExampleConfig()) -> dict:
    """Film the example and write it to ``out`` (replaced whole, atomically); returns its facts."""
    mesh, colour = make_object(cfg.shape, cfg.seed, cfg.size)
    obj = gaussians_from_mesh(mesh, colour, cfg.n_gaussians - cfg.n_gaussians // 10, cfg.n_gaussians // 10,
                              seed=cfg.seed)
    scan = transform_cloud(obj, up_rotation(SCAN_OPTIONS.up).T, 1.0 / SCAN_OPTIONS.metres_per_unit)
    clean, object_from_scan, _ = prepare_scan(scan, SCAN_OPTIONS, name="example scan")  # as the assets stage will
    parts = convert(clean, cfg.particles, cfg.density)
    sim_from_scan = parts.sim_from_world @ object_from_scan
    kept = clean.subset(parts.gaussian_index)
    A = parts.sim_from_world
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    means0, covs0 = t(kept.means @ A[:3, :3].T + A[:3, 3]), t(A[:3, :3] @ covariances(kept) @ A[:3, :3].T)
    binding = Binding(rows=torch.as_tensor(parts.binding_rows, dtype=torch.long),
                      cols=torch.as_tensor(parts.binding_cols, dtype=torch.long),
                      weights=t(parts.binding_weights), n_gaussians=kept.n, n_particles=parts.n)
    colors, alphas = t(np.clip(sh0_to_rgb(kept.sh_dc), 0, 1)), t(opacities(kept))

    substeps = max(1, int(round(1.0 / (cfg.fps * cfg.dt))))
    solver = MPMSolver(SimConfig(n_grid=cfg.n_grid, dt=cfg.dt, bound=1, boundary="friction", friction=0.4), "cpu")
    material = material_from_preset(dict(cfg.law), dt=cfg.dt)
    x0 = t(parts.x)
    with torch.no_grad():
        traj = rollout(solver, material, x0, t(cfg.v0).expand_as(x0).contiguous(), t(parts.vol), t(parts.mass),
                       n_steps=cfg.n_frames * substeps, steps_per_frame=substeps, checkpoint=False)
    centre = parts.x.mean(axis=0)
    camera = look_at(eye=centre + np.array([0.15, 0.25, 1.1]), target=centre - np.array([0, 0.05, 0]),
                     up=np.array([0.0, 1.0, 0.0]), fov_deg=50.0, width=cfg.width, height=cfg.height)
    plate = _plate(cfg.width, cfg.height, cfg.seed)
    rng = np.random.default_rng(cfg.seed + 1)
    frames = []
    with torch.no_grad():
        for f in range(1, cfg.n_frames + 1):  # image k is simulated frame k + 1 (gca.scenes.capture)
            means, covs = follow(binding, means0, covs0, x0, traj.x[f], traj.F[f])
            image = render(means, covs, colors, alphas, camera, torch.zeros(3))
            rgb = image["rgb"].numpy() + (1 - image["alpha"].numpy()[..., None]) * plate
            frames.append(np.clip(rgb + cfg.noise * rng.standard_normal(rgb.shape), 0, 1))
    camera_scan = transform_camera(camera, np.linalg.inv(sim_from_scan))
    with io.atomic_path(out, is_dir=True) as tmp:
        write_ply(tmp / "scan.ply", scan)
        (tmp / "frames").mkdir()
        for i, img in enumerate(frames):
            iio.imwrite(tmp / "frames" / f"{i:05d}.png", (img * 255 + 0.5).astype(np.uint8))
        iio.imwrite(tmp / "plate.png", (plate * 255 + 0.5).astype(np.uint8))
        write_transforms_json(tmp / "transforms.json", {"video": camera_scan})
        io.write_json(tmp / "truth.json", {"law": dict(cfg.law), "v0": list(cfg.v0), "fps": cfg.fps, "dt": cfg.dt,
                                           "note": "how the example was made; the pipeline never reads this file"})
    return {"n_frames": cfg.n_frames, "substeps": substeps, "n_gaussians": scan.n, "n_particles": parts.n}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("captures/example"))
    ap.add_argument("--frames", type=int, default=ExampleConfig.n_frames)
    args = ap.parse_args(argv)
    facts = make_example(args.out, dataclasses.replace(ExampleConfig(), n_frames=args.frames))
    print(f"wrote {args.out}: {facts['n_frames']} frames, scan of {facts['n_gaussians']} Gaussians")
    return facts


if __name__ == "__main__":
    main(sys.argv[1:])
