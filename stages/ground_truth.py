"""DVC stage ``ground_truth``: simulate a scene with its ground-truth law and render its videos.

    python stages/ground_truth.py --scene duck --assets data/assets/duck \
        --particles data/particles/duck.npz --out data/scenes/duck --gt data/gt/duck \
        --metrics metrics/ground_truth/duck.json

``--out`` gets what a monocular method observes (frames, cameras, timing); ``--gt`` the ground-truth-only
data (trajectory, true alpha and depth, the unlit render, the true law) that only evaluation reads.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from gca.io import atomic_path, write_json
from gca.pipeline.settings import Settings
from gca.pipeline.track import stage_run
from gca.scenes.groundtruth import generate
from gca.vision.depth import DepthConfig


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--assets", type=Path, required=True, help="data/assets/<object> (gaussians.ply)")
    ap.add_argument("--particles", type=Path, required=True, help="data/particles/<object>.npz")
    ap.add_argument("--out", type=Path, required=True, help="scene directory (replaced atomically)")
    ap.add_argument("--gt", type=Path, required=True, help="ground-truth-only directory (replaced atomically)")
    ap.add_argument("--metrics", type=Path, required=True)
    ap.add_argument("--params", type=Path, default=Path("params.yaml"))
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    settings = Settings.load(f"ground_truth@{args.scene}", args.params)
    scene = settings.scene(args.scene)
    depth_cfg = settings.section_as(DepthConfig, "vision.depth").simulated
    body = settings.load_body(args.particles, args.assets / "gaussians.ply", args.device)
    with stage_run("ground_truth", settings.params, scene=args.scene) as run:
        with atomic_path(args.out, is_dir=True) as tmp, atomic_path(args.gt, is_dir=True) as gt_tmp:
            metrics = generate(tmp, gt_tmp, body, args.scene, scene, settings.video, settings.sim,
                               settings.material(scene.material), settings.lighting, depth_cfg, settings.seed,
                               args.device)
        write_json(args.metrics, metrics)
        run.log_metrics(metrics)
        run.log_artifact(args.out / "preview.gif")
    return metrics


if __name__ == "__main__":
    main(sys.argv[1:])
