"""DVC stage ``evaluate``: metrics of every trained method of a scene, one JSON per method.

    python stages/evaluate.py --scene duck --scene-dir data/scenes/duck --gt data/gt/duck --runs runs/duck \
        --particles data/particles/duck.npz --gaussians data/assets/duck/gaussians.ply \
        --prior-dir models/prior --out metrics/eval/duck [--methods gca] [--seeds 0 1]

A capture scene (no ground truth, ``--gt`` unread) is scored on its held-out frames instead
(:func:`gca.pipeline.evaluate.evaluate_capture_trained`; ``--prep`` gives their segmented masks).

One JSON per (method, seed) trained (``metrics/eval/duck/gca.json``, ``gca@seed1.json``, ...), added to the
training run's MLflow run (Chamfer also in mm), and mirrored into the experiment of each other table of the
method (``gca.pipeline.track.mirror_runs``). The ground truth (``--gt``, trajectory) is bound to the scene directory
for this process only (:func:`gca.scenes.truth.bind`): training's processes never have it.
"""

from __future__ import annotations

import sys
from pathlib import Path

from tqdm import tqdm

from gca.pipeline import cli
from gca.pipeline.evaluate import evaluate_capture_trained, evaluate_trained
from gca.io import read_json, write_json
from gca.pipeline.train import seed_runs
from gca.pipeline.track import method_params, mirror_runs, stage_run, train_run_args, with_millimetres
from gca.scenes import truth

from common import scene_context, scene_parser  # stages/common.py


def main(argv=None) -> dict:
    paths = ("scene-dir", "gt", "runs", "particles", "gaussians", "prior-dir", "out")
    parser = scene_parser(__doc__.splitlines()[0], paths)
    parser.add_argument("--prep", type=Path, help="data/prep/<scene> (a capture scene's held-out masks)")
    args = parser.parse_args(argv)
    settings, scene, methods, inputs = scene_context("evaluate", args)
    if scene.is_capture:
        return _capture(args, settings, methods, inputs)
    body = settings.load_body(args.particles, args.gaussians, args.device)
    out = {}
    args.out.mkdir(parents=True, exist_ok=True)  # a calibration scene (no methods) still gets its folder
    for method, seed, name in tqdm(seed_runs(settings, methods, args.seeds), desc=f"evaluate {args.scene}", unit="run",
                                   disable=cli.quiet()):
        run_id = read_json(args.runs / name / "train.json").get("mlflow_run_id")
        with stage_run("evaluate", settings.params, **train_run_args(args.scene, method, seed, name),
                       resume_run_id=run_id) as run:
            with truth.bind(args.scene_dir, args.gt):
                out[name] = evaluate_trained(settings, args.scene, method, inputs, body, args.runs, args.out,
                                             args.device, seed)
            out[name]["benchmark_version"] = settings.benchmark_version
            write_json(args.out / f"{name}.json", out[name])
            final = with_millimetres({k: v for k, v in out[name].items() if k != "chamfer_per_frame"})
            run.log_metrics(final)
            for media in ("strip.png", "rollout.gif", "cd_time.png"):
                run.log_artifact(args.out / name / media)
            primary = run.run_id
        # every other table of the method lists this row too (gca.pipeline.track module doc)
        mirror_runs(settings.params, final, method.tables[1:], primary, scene=args.scene, method=method.name,
                    run_name=f"{args.scene}/{name}", tags=train_run_args(args.scene, method, seed, name)["tags"],
                    extra_params=method_params(method, lora=settings.lora))
        print(f"evaluate {args.scene}/{name}: {out[name]['status']} CD={out[name].get('chamfer_mean', float('nan')):.4g}")
    return out


def _capture(args, settings, methods, inputs) -> dict:
    """The capture branch: held-out frames, silhouettes and CPR's nearest classical law per trained run."""
    from gca.scenes.store import SceneDataError

    body = settings.load_body(args.particles, args.gaussians, args.device)
    args.out.mkdir(parents=True, exist_ok=True)
    out = {}
    for method, seed, name in seed_runs(settings, methods, args.seeds):
        try:
            with stage_run("evaluate", settings.params, scene=args.scene, method=method.name,
                           run_name=f"{args.scene}/{name}", tags={"seed": str(seed), "kind": "capture"}) as run:
                out[name] = evaluate_capture_trained(settings, args.scene, method, inputs, body, args.runs, args.out,
                                                     args.device, seed)
                write_json(args.out / f"{name}.json", out[name])
                run.log_metrics({k: v for k, v in out[name].items() if isinstance(v, float)})
        except SceneDataError as exc:
            raise SystemExit(f"evaluate@{args.scene}: {exc}") from None
        law = out[name].get("nearest_law", {}).get("sentence", "")
        print(f"evaluate {args.scene}/{name} (capture): {out[name]['status']} held-out PSNR="
              f"{out[name].get('psnr_heldout', float('nan')):.3g} IoU={out[name].get('mask_iou_heldout', float('nan')):.3g}; {law}")
    return out


if __name__ == "__main__":
    sys.exit(cli.run(main))
