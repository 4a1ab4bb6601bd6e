"""DVC stage ``train``: estimate the launch velocity, then train every method of a scene.

    python stages/train.py --scene duck --scene-dir data/scenes/duck --prep data/prep/duck \
        --particles data/particles/duck.npz --gaussians data/assets/duck/gaussians.ply \
        --prior-dir models/prior --out runs/duck [--methods gca neuma] [--seeds 0 1] [--velocity runs/duck/velocity.json]

``--velocity`` reuses a launch velocity estimated by an earlier run of this stage on the same scene
(several processes training one scene's methods in parallel share one estimate: gca/pipeline/grid.py).
A run resuming from a checkpoint under ``--out`` reuses ``--out``/velocity.json the same way. Both carry a
stamp of the params and inputs they were made from (``gca.stamp``): a stale one is not reused (one line
says so), the velocity is estimated again and the run trains afresh. SIGTERM stops training at the end of
the iteration in progress, after a checkpoint (``gca.stop``).

One training run per (method, seed) of ``train.seeds`` (``runs/duck/gca``, ``runs/duck/gca@seed1``, ...;
``--seeds`` picks a subset), seeds outermost. One MLflow run per (scene, method, seed), in the experiment of
the method's first paper table, with the method's effective configuration (``gca.pipeline.track.method_params``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from gca import stamp, stop
from gca.pipeline import cli
from gca.io import read_json, write_json
from gca.pipeline.track import method_params, stage_run

from common import scene_context, scene_parser  # stages/common.py
from gca.pipeline.train import estimate_scene_velocity, read_velocity, seed_runs, train_method


# params the launch velocity and the training runs depend on (dvc.yaml's train params, in two parts)
VELOCITY_KEYS = ("profile", "seed", "sim", "video", "render.backend", "render.raster", "laws", "velocity", "prior.families")
TRAIN_KEYS = ("vision.matching", "align", "train")


def velocity_stamp(params, scene: str, inputs) -> str:
    """Stamp of the scene's inputs and the params of its launch velocity (gca.stamp)."""
    return stamp.fingerprint(params, (*VELOCITY_KEYS, f"scenes.{scene}"),
                             [inputs.scene_dir, inputs.prep_dir, inputs.particles, inputs.gaussians, inputs.prior])


def main(argv=None) -> dict:
    paths = ("scene-dir", "prep", "particles", "gaussians", "prior-dir", "out")
    ap = scene_parser(__doc__.splitlines()[0], paths)
    ap.add_argument("--velocity", type=Path, help="reuse this velocity.json instead of estimating it")
    args = ap.parse_args(argv)
    settings, scene, methods, inputs = scene_context("train", args)
    runs = seed_runs(settings, methods, args.seeds)
    args.out.mkdir(parents=True, exist_ok=True)
    inputs_stamp = velocity_stamp(settings.params, args.scene, inputs)
    # an interrupted run of this call (e.g. stopped by grid.py --deadline) goes on from its checkpoint
    resuming = any((args.out / name / "checkpoint.pt").is_file() for _, _, name in runs)
    if args.velocity is None and resuming and (args.out / "velocity.json").is_file():
        args.velocity = args.out / "velocity.json"  # with the launch velocity its first iterations used
    if args.velocity is not None and not stamp.matches(read_json(args.velocity), inputs_stamp):
        why = "has no stamp" if stamp.KEY not in read_json(args.velocity) else "was made with other params or inputs"
        print(f"{args.velocity}: not reused: the launch velocity {why}; estimating it again")
        args.velocity = None
    if args.velocity is None:
        with stage_run("train", settings.params, scene=args.scene, method="velocity") as run:
            velocity = estimate_scene_velocity(settings, args.scene, inputs, args.out / "velocity.json", args.device)
            write_json(args.out / "velocity.json", {**read_json(args.out / "velocity.json"), stamp.KEY: inputs_stamp})
            run.log_metrics({k: v for k, v in velocity.items() if k not in ("v0", "w0")})
    velocity = read_velocity(args.velocity or args.out / "velocity.json")
    results = {}
    for method, seed, name in runs:
        with stage_run("train", settings.params, scene=args.scene, method=method.name, table=method.tables[0],
                       experiment=f"gca/{method.tables[0]}", run_name=f"{args.scene}/{name}",
                       tags={"tables": ",".join(method.tables), "material": scene.material, "seed": str(seed)}) as run:
            run.log_params(method_params(method, settings.rdga, settings.cpr, settings.lora))
            checkpoint = args.out / name / "checkpoint.pt"
            stamp.guard_checkpoint(checkpoint, stamp.fingerprint(settings.params, TRAIN_KEYS,
                                                                 extra=[inputs_stamp, velocity, method.name, seed]))
            with stop.deferred():  # SIGTERM: checkpoint at the end of the iteration, then stop
                results[name] = train_method(settings, args.scene, method, inputs, velocity, args.out / name, run,
                                             args.device, seed)
            stamp.clear_checkpoint(checkpoint)
            run.log_artifact(args.out / name / "loss.png")
        print(f"train {args.scene}/{name}: {results[name]['status']} in {results[name]['train_seconds']:.1f} s")
    return results


if __name__ == "__main__":
    sys.exit(cli.run(main))
