"""DVC stage ``nuisance``: measured nuisance statistics of a scene's observations against its ground truth.

    python stages/nuisance.py --scene duck --scene-dir data/scenes/duck --gt data/gt/duck --prep data/prep/duck \
        --out metrics/nuisance/duck.json

Per-frame mask IoU, per-frame depth Spearman inside the object, and the share of in-object colour variance
the lighting adds beyond a per-frame affine colour map (gca/eval/nuisance.py), for training seed 0's observations
and, under ``seeds``, for each other seed of ``train.seeds`` (each draws its own lighting, masks and depth noise). Evaluation-side: it reads
the ground-truth directory; no training stage depends on its output.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gca.config import section
from gca.pipeline import cli
from gca.eval.nuisance import scene_nuisance
from gca.io import write_json
from gca.pipeline.settings import Settings
from gca.pipeline.track import stage_run
from gca.scenes.capture import is_capture
from gca.scenes.store import seed_dir


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name in ("scene-dir", "gt", "prep", "out"):
        ap.add_argument(f"--{name}", type=Path, required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--params", type=Path, default=Path("params.yaml"))
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    settings = Settings.load(f"nuisance@{args.scene}", args.params)
    if is_capture(args.scene_dir):  # a real video has no ground truth to measure the observations against
        metrics = {"scene": args.scene, "skipped": "capture scene: no ground truth"}
        write_json(args.out, metrics)
        print(f"nuisance {args.scene}: skipped ({metrics['skipped']})")
        return metrics
    with stage_run("nuisance", settings.params, scene=args.scene) as run:
        threshold = settings.video.mask_threshold
        metrics = {"scene": args.scene, "benchmark_version": settings.benchmark_version,
                   **scene_nuisance(args.scene_dir, args.gt, args.prep, threshold)}
        # the other training seeds' own draws (train.seeds; seed 0's are the headline numbers above)
        extra = [int(k) for k in section(settings.params, "train.seeds") if int(k) != 0]
        if extra:
            metrics["seeds"] = {str(k): {key: v for key, v in scene_nuisance(
                seed_dir(args.scene_dir, k), args.gt, seed_dir(args.prep, k), threshold).items()
                if key != "image_mean_per_frame"} for k in extra}
        write_json(args.out, metrics)
        run.log_metrics({k: v for k, v in metrics.items() if isinstance(v, float)})
    print(f"nuisance {args.scene}: mask IoU {metrics['mask_iou_mean']:.3f}, depth Spearman "
          f"{metrics['depth_spearman_mean']:.3f}, lighting unexplained {metrics['lighting_unexplained_share']:.3f}")
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
