"""DVC stage ``evaluate``: metrics of every trained method of a scene, one JSON per method.

    python stages/evaluate.py --scene duck --scene-dir data/scenes/duck --runs runs/duck \
        --particles data/particles/duck.npz --gaussians data/assets/duck/gaussians.ply \
        --prior-dir models/prior --out metrics/eval/duck [--methods gca] [--seeds 0 1]

One JSON per (method, seed) trained (``metrics/eval/duck/gca.json``, ``gca@seed1.json``, ...), added to the
training run's MLflow run.
"""

from __future__ import annotations

import sys

from tqdm import tqdm

from gca.eval.evaluate import evaluate_trained
from gca.io import read_json, write_json
from gca.scenes.world import load_scene_body
from gca.train.run import seed_runs
from gca import cli
from gca.track import stage_run

from common import scene_context, scene_parser  # stages/common.py


def main(argv=None) -> dict:
    paths = ("scene-dir", "runs", "particles", "gaussians", "prior-dir", "out")
    args = scene_parser(__doc__.splitlines()[0], paths).parse_args(argv)
    params, scene, methods, inputs = scene_context("evaluate", args)
    body = load_scene_body(params, args.particles, args.gaussians, args.device)
    out = {}
    for method, seed, name in tqdm(seed_runs(params, methods, args.seeds), desc=f"evaluate {args.scene}", unit="run"):
        run_id = read_json(args.runs / name / "train.json").get("mlflow_run_id")
        with stage_run("evaluate", params, scene=args.scene, method=method.name, table=method.tables[0],
                       experiment=f"gca/{method.tables[0]}", run_name=f"{args.scene}/{name}",
                       tags={"tables": ",".join(method.tables), "seed": str(seed)}, resume_run_id=run_id) as run:
            out[name] = evaluate_trained(params, args.scene, method, inputs, body, args.runs, args.out, args.device,
                                         seed)
            write_json(args.out / f"{name}.json", out[name])
            run.log_metrics({k: v for k, v in out[name].items() if k != "chamfer_per_frame"})
            for media in ("strip.png", "rollout.gif", "cd_time.png"):
                run.log_artifact(args.out / name / media)
        print(f"evaluate {args.scene}/{name}: {out[name]['status']} CD={out[name].get('chamfer_mean', float('nan')):.4g}")
    return out


if __name__ == "__main__":
    sys.exit(cli.run(main))
