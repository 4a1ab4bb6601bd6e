"""DVC stage ``preprocess``: what a monocular method extracts from the training video.

It reads the scene directory only (frames, cameras, the simulated estimator's depth); the ground-truth
directory ``data/gt/<scene>`` is not among its dependencies and is never opened. Each seed k > 0 of
``train.seeds`` has its own observations (``data/scenes/<scene>/seed<k>``, its own nuisance draw) and gets its own
``data/prep/<scene>/seed<k>``; seed 0's are the top level.

    python stages/preprocess.py --scene duck --scene-dir data/scenes/duck --out data/prep/duck \
        --metrics metrics/preprocess/duck.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gca.pipeline import cli
from gca import config
from gca.io import atomic_path, write_json
from gca.pipeline.settings import Settings
from gca.pipeline.track import stage_run
from gca.scenes import TRAIN_VIEW, load_simulated_depth, load_view
from gca.scenes.store import load_plate, nuisance_seed, seed_dir
from gca.capture.cameras import CaptureError
from gca.config import ConfigError
from gca.scenes.capture import is_capture, load_heldout
from gca.scenes.preprocess import preprocess_capture, preprocess_view, synthetic_pair_precision, write_prep
from gca.scenes.store import SceneDataError


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
    settings = Settings.load(f"preprocess@{args.scene}", args.params)
    if "scenes" in settings.params:  # under DVC the stage sees no scenes section; dvc.yaml's foreach names them
        config.entry(settings.params, "scenes", args.scene)
    cfg = settings.vision
    if is_capture(args.scene_dir):
        return _capture(args, settings)
    with stage_run("preprocess", settings.params, scene=args.scene) as run:
        metrics = {}
        with atomic_path(args.out, is_dir=True) as tmp:
            for k in [0] + sorted(set(settings.seeds) - {0}):  # seed 0's draw at the top, seed k's in seed<k>/
                scene_dir, out = seed_dir(args.scene_dir, k), seed_dir(tmp, k)
                view = load_view(scene_dir, TRAIN_VIEW)
                sim_depth = load_simulated_depth(scene_dir, len(view.rgb)) if cfg.depth.backend == "simulated" else None
                prep = preprocess_view(view, cfg, seed=nuisance_seed(settings.seed, k), simulated_depth=sim_depth,
                                       plate=load_plate(scene_dir, TRAIN_VIEW))
                out.mkdir(parents=True, exist_ok=True)
                write_prep(out, prep)
                n_kpts = np.diff(prep["keypoints"]["offsets"])
                one = {"n_frames": int(len(prep["depth"])), "keypoints_per_frame": float(n_kpts.mean()),
                       "mask_coverage": float(prep["masks"].mean())}
                if k == 0:
                    metrics.update({**one, **synthetic_pair_precision(view.rgb[0], cfg, seed=settings.seed)})
                else:
                    metrics.update({f"seed{k}/{key}": v for key, v in one.items()})
        write_json(args.metrics, metrics)
        run.log_metrics(metrics)
    return metrics


def _capture(args, settings: Settings) -> dict:
    """A capture: masks, depth and keypoints from the frames only (user errors: one line, nothing written)."""
    try:
        scene = settings.scene(args.scene)
        view = load_view(args.scene_dir, TRAIN_VIEW)
        heldout, _ = load_heldout(args.scene_dir)
        with stage_run("preprocess", settings.params, scene=args.scene) as run:
            prep = preprocess_capture(view, heldout.rgb, settings.vision, scene.capture.depth, seed=settings.seed,
                                      plate=load_plate(args.scene_dir, TRAIN_VIEW))
            with atomic_path(args.out, is_dir=True) as tmp:
                write_prep(tmp, prep)
            n_kpts = np.diff(prep["keypoints"]["offsets"])
            metrics = {"n_frames": int(len(prep["depth"])), "n_heldout_frames": int(len(prep["heldout_masks"])),
                       "keypoints_per_frame": float(n_kpts.mean()), "mask_coverage": float(prep["masks"].mean()),
                       "depth": scene.capture.depth}
            write_json(args.metrics, metrics)
            run.log_metrics({k: v for k, v in metrics.items() if not isinstance(v, str)})
    except (SceneDataError, CaptureError, ConfigError) as exc:
        raise SystemExit(f"preprocess@{args.scene}: {exc}") from None
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
