"""DVC stage ``preprocess``: what a monocular method extracts from the training video.

    python stages/preprocess.py --scene duck --scene-dir data/scenes/duck --out data/prep/duck \
        --metrics metrics/preprocess/duck.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gca import cli, config
from gca.io import atomic_path, write_json
from gca.scenes import TRAIN_VIEW, load_view
from gca.scenes.prep import preprocess_view, synthetic_pair_precision, write_prep
from gca.track import stage_run
from gca.vision import VisionConfig


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="a key of `scenes:` in params.yaml (e.g. duck)")
    ap.add_argument("--scene-dir", type=Path, required=True, help="the ground_truth stage's data/scenes/<scene>")
    ap.add_argument("--out", type=Path, required=True, help="data/prep/<scene> (replaced atomically)")
    ap.add_argument("--metrics", type=Path, required=True, help="metrics .json")
    cli.add_common(ap)
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    params = config.load(f"preprocess@{args.scene}", args.params)
    if "scenes" in params:  # under DVC the stage sees no scenes section; dvc.yaml's foreach names them
        config.entry(params, "scenes", args.scene)
    cfg = config.build(VisionConfig, config.section(params, "vision"), "vision")
    view = load_view(args.scene_dir, TRAIN_VIEW)
    with stage_run("preprocess", params, scene=args.scene) as run:
        prep = preprocess_view(view, cfg, seed=int(params["seed"]))
        with atomic_path(args.out, is_dir=True) as tmp:
            write_prep(tmp, prep)
        n_kpts = np.diff(prep["keypoints"]["offsets"])
        metrics = {"n_frames": int(len(prep["depth"])), "keypoints_per_frame": float(n_kpts.mean()),
                   "mask_coverage": float(prep["masks"].mean()),
                   **synthetic_pair_precision(view.rgb[0], cfg, seed=int(params["seed"]))}
        write_json(args.metrics, metrics)
        run.log_metrics(metrics)
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
