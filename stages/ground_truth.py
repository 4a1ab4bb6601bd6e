"""DVC stage ``ground_truth``: simulate a scene with its ground-truth law and render its videos.

    python stages/ground_truth.py --scene duck --assets data/assets/duck \
        --particles data/particles/duck.npz --out data/scenes/duck --metrics metrics/ground_truth/duck.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from gca import cli, config
from gca.io import atomic_path, write_json
from gca.render.shading import LightingConfig
from gca.scenes import scene_config, video_config
from gca.scenes.groundtruth import generate
from gca.scenes.world import load_scene_body
from gca.sim.solver import SimConfig
from gca.track import stage_run


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="a key of `scenes:` in params.yaml (e.g. duck)")
    ap.add_argument("--assets", type=Path, required=True, help="data/assets/<object> (gaussians.ply)")
    ap.add_argument("--particles", type=Path, required=True, help="data/particles/<object>.npz")
    ap.add_argument("--out", type=Path, required=True, help="scene directory (replaced atomically)")
    ap.add_argument("--metrics", type=Path, required=True, help="metrics .json")
    cli.add_common(ap, device="cuda" if torch.cuda.is_available() else "cpu")
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    params = config.load(f"ground_truth@{args.scene}", args.params)
    scene, video = scene_config(params, args.scene), video_config(params)
    sim = config.build(SimConfig, config.section(params, "sim"), "sim")
    lighting = config.build(LightingConfig, config.section(params, "render.lighting"), "render.lighting")
    body = load_scene_body(params, args.particles, args.assets / "gaussians.ply", args.device)
    preset = config.section(params, f"materials.{scene.material}")
    with stage_run("ground_truth", params, scene=args.scene) as run:
        with atomic_path(args.out, is_dir=True) as tmp, \
                cli.phase("ground_truth", f"{args.scene}: simulating {video.n_frames} frames, then rendering"):
            metrics = generate(tmp, body, args.scene, scene, video, sim, preset, lighting, args.device)
        write_json(args.metrics, metrics)
        run.log_metrics(metrics)
        run.log_artifact(args.out / "preview.gif")
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
