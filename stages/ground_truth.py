"""DVC stage ``ground_truth``: simulate a scene with its ground-truth law and render its videos.

    python stages/ground_truth.py --scene duck --assets data/assets/duck \
        --particles data/particles/duck.npz --out data/scenes/duck --gt data/gt/duck \
        --metrics metrics/ground_truth/duck.json

``--out`` gets what a monocular method observes (frames, cameras, timing); ``--gt`` the ground-truth-only
data (trajectory, true alpha and depth, the unlit render, the true law) that only evaluation reads. The scene is
simulated once; each seed k > 0 of ``train.seeds`` gets its own nuisance draw of the training views in
``--out``/seed<k> (:mod:`gca.scenes.ground_truth`), from the same trajectory.

A capture scene (``scenes.<name>.capture``: the user's video) is imported instead (:mod:`gca.scenes.capture`):
its frames, plate and camera (brought to the sim frame) into ``--out``; ``--gt`` only says there is none.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from gca.pipeline import cli
from gca.assets.particles import load_particles
from gca.capture.cameras import CaptureError
from gca.capture.objects import read_object_from_scan
from gca.config import ConfigError
from gca.io import atomic_path, write_json
from gca.pipeline.settings import Settings
from gca.pipeline.track import stage_run
from gca.scenes.capture import write_capture
from gca.scenes.ground_truth import generate
from gca.scenes.store import SceneDataError
from gca.vision.depth import DepthConfig


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="a key of `scenes:` in params.yaml (e.g. duck)")
    ap.add_argument("--assets", type=Path, required=True, help="data/assets/<object> (gaussians.ply)")
    ap.add_argument("--particles", type=Path, required=True, help="data/particles/<object>.npz")
    ap.add_argument("--out", type=Path, required=True, help="scene directory (replaced atomically)")
    ap.add_argument("--gt", type=Path, required=True, help="ground-truth-only directory (replaced atomically)")
    ap.add_argument("--metrics", type=Path, required=True, help="metrics .json")
    cli.add_common(ap, device="cuda" if torch.cuda.is_available() else "cpu")
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    settings = Settings.load(f"ground_truth@{args.scene}", args.params)
    try:
        scene = settings.scene(args.scene)
    except (CaptureError, ConfigError) as exc:
        raise SystemExit(f"ground_truth@{args.scene}: {exc}") from None
    if scene.is_capture:
        return _capture(args, settings, scene)
    depth_cfg = settings.section_as(DepthConfig, "vision.depth").simulated
    body = settings.load_body(args.particles, args.assets / "gaussians.ply", args.device)
    with stage_run("ground_truth", settings.params, scene=args.scene) as run:
        with atomic_path(args.out, is_dir=True) as tmp, atomic_path(args.gt, is_dir=True) as gt_tmp, \
                cli.phase("ground_truth", f"{args.scene}: simulating, then rendering"):
            metrics = generate(tmp, gt_tmp, body, args.scene, scene, settings.video, settings.sim,
                               settings.material(scene.material), settings.lighting, depth_cfg, settings.seed,
                               args.device, seeds=settings.seeds)
        write_json(args.metrics, metrics)
        run.log_metrics(metrics)
        run.log_artifact(args.out / "preview.gif")
    return metrics


def _capture(args, settings: Settings, scene) -> dict:
    """The capture branch: the user's video into the scene layout (user errors: one line, nothing written)."""
    sim_from_scan = load_particles(args.particles).sim_from_world @ read_object_from_scan(args.assets)
    try:
        with stage_run("ground_truth", settings.params, scene=args.scene) as run:
            with atomic_path(args.out, is_dir=True) as tmp, atomic_path(args.gt, is_dir=True) as gt_tmp:
                metrics = write_capture(tmp, gt_tmp, args.scene, scene.object, scene.capture, scene.dt, sim_from_scan,
                                        max_side=settings.video.resolution)
            write_json(args.metrics, metrics)
            run.log_metrics(metrics)
    except (CaptureError, SceneDataError, ConfigError) as exc:
        raise SystemExit(f"ground_truth@{args.scene}: {exc}") from None
    print(f"ground_truth@{args.scene}: capture, {metrics['n_train_frames']} training + {metrics['n_heldout_frames']} "
          f"held-out frames at {metrics['width']}x{metrics['height']}, {metrics['substeps']} MPM steps per frame")
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
