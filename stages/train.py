"""DVC stage ``train``: estimate the launch velocity, then train every method of a scene.

    python stages/train.py --scene duck --scene-dir data/scenes/duck --prep data/prep/duck \
        --particles data/particles/duck.npz --gaussians data/assets/duck/gaussians.ply \
        --prior-dir models/prior --out runs/duck [--methods gca neuma] [--seeds 0 1] [--velocity runs/duck/velocity.json]

``--velocity`` reuses a launch velocity estimated by an earlier run of this stage on the same scene
(several processes training one scene's methods in parallel share one estimate: gca/pipeline/grid.py).
A run resuming from a checkpoint under ``--out`` reuses ``--out``/velocity.json the same way.

One training run per (method, seed) of ``train.seeds`` (``runs/duck/gca``, ``runs/duck/gca@seed1``, ...;
``--seeds`` picks a subset), seeds outermost. One MLflow run per (scene, method, seed), in the experiment of
the method's first paper table, with the method's effective configuration (``gca.pipeline.track.method_params``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from gca.pipeline.track import method_params, stage_run

from common import scene_context, scene_parser  # stages/common.py
from gca.pipeline.train import estimate_scene_velocity, read_velocity, seed_runs, train_method


def main(argv=None) -> dict:
    paths = ("scene-dir", "prep", "particles", "gaussians", "prior-dir", "out")
    ap = scene_parser(__doc__.splitlines()[0], paths)
    ap.add_argument("--velocity", type=Path, help="reuse this velocity.json instead of estimating it")
    args = ap.parse_args(argv)
    settings, scene, methods, inputs = scene_context("train", args)
    runs = seed_runs(settings, methods, args.seeds)
    args.out.mkdir(parents=True, exist_ok=True)
    # an interrupted run of this call (e.g. stopped by grid.py --deadline) goes on from its checkpoint
    resuming = any((args.out / name / "checkpoint.pt").is_file() for _, _, name in runs)
    if args.velocity is None and resuming and (args.out / "velocity.json").is_file():
        args.velocity = args.out / "velocity.json"  # with the launch velocity its first iterations used
    if args.velocity is None:
        with stage_run("train", settings.params, scene=args.scene, method="velocity") as run:
            velocity = estimate_scene_velocity(settings, args.scene, inputs, args.out / "velocity.json", args.device)
            run.log_metrics({k: v for k, v in velocity.items() if k not in ("v0", "w0")})
    velocity = read_velocity(args.velocity or args.out / "velocity.json")
    results = {}
    for method, seed, name in runs:
        with stage_run("train", settings.params, scene=args.scene, method=method.name, table=method.tables[0],
                       experiment=f"gca/{method.tables[0]}", run_name=f"{args.scene}/{name}",
                       tags={"tables": ",".join(method.tables), "material": scene.material, "seed": str(seed)}) as run:
            run.log_params(method_params(method, settings.rdga, settings.cpr, settings.lora))
            results[name] = train_method(settings, args.scene, method, inputs, velocity, args.out / name, run,
                                         args.device, seed)
            run.log_artifact(args.out / name / "loss.png")
        print(f"train {args.scene}/{name}: {results[name]['status']} in {results[name]['train_seconds']:.1f} s")
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
