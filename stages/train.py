"""DVC stage ``train``: estimate the launch velocity, then train every method of a scene.

    python stages/train.py --scene duck --scene-dir data/scenes/duck --prep data/prep/duck \
        --particles data/particles/duck.npz --gaussians data/assets/duck/gaussians.ply \
        --prior-dir models/prior --out runs/duck [--methods gca neuma] [--seeds 0 1] [--velocity runs/duck/velocity.json]

Each seed of ``train.seeds`` observes its own nuisance draw (``--scene-dir``/seed<k>, ``--prep``/seed<k>; seed 0
the top level: :func:`gca.pipeline.train.observed_inputs`), so each seed has its own launch velocity, estimated
from its observations: ``--out``/velocity.json (seed 0), ``velocity@seed<k>.json`` (seed k).
``--velocity`` reuses a launch velocity estimated by an earlier run of this stage on the same scene and seed
(several processes training one scene's methods in parallel share one estimate per seed: gca/pipeline/grid.py).
A run resuming from a checkpoint under ``--out`` reuses its seed's velocity file the same way. Both carry a
stamp of the params and inputs they were made from (``gca.stamp``): a stale one is not reused (one line
says so), the velocity is estimated again and the run trains afresh. SIGTERM stops training at the end of
the iteration in progress, after a checkpoint (``gca.stop``).

One training run per (method, seed) of ``train.seeds`` (``runs/duck/gca``, ``runs/duck/gca@seed1``, ...;
``--seeds`` picks a subset), seeds outermost. One MLflow run per (scene, method, seed), in the experiment of
the method's first paper table, with the method's effective configuration (``gca.pipeline.track.method_params``).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from gca import stamp, stop
from gca.pipeline import cli
from gca.io import read_json, write_json
from gca.pipeline.track import method_params, stage_run, train_run_args

from common import scene_context, scene_parser  # stages/common.py
from gca.pipeline.train import (check_mlp_kernel, estimate_scene_velocity, observed_inputs, read_velocity, seed_runs,
                                 train_method, velocity_path)


# params the launch velocity and the training runs depend on (dvc.yaml's train params, in two parts)
VELOCITY_KEYS = ("profile", "seed", "sim", "video", "render.backend", "render.raster", "laws", "velocity", "prior.families")
TRAIN_KEYS = ("vision.matching", "align", "train")


def other_seeds(relative: Path) -> bool:
    """Whether a file of a scene or prep folder belongs to another seed's observations (``seed<k>/``, nested in
    seed 0's top level): not an input of seed 0's runs."""
    return bool(re.fullmatch(r"seed[0-9]+", relative.parts[0])) and len(relative.parts) > 1


def velocity_stamp(params, scene: str, inputs) -> str:
    """Stamp of the scene's inputs (one seed's observations) and the params of its launch velocity (gca.stamp)."""
    return stamp.fingerprint(params, (*VELOCITY_KEYS, f"scenes.{scene}"),
                             [inputs.scene_dir, inputs.prep_dir, inputs.particles, inputs.gaussians, inputs.prior],
                             skip=other_seeds)


def seed_velocity(args, settings, inputs, seed: int, given: Path | None, resuming: bool) -> tuple[tuple, str]:
    """(launch velocity, inputs stamp) of the runs of ``seed``: ``given`` or, when resuming, the seed's own
    ``velocity.json`` / ``velocity@seed<k>.json`` when its stamp matches; else estimated from the seed's observations."""
    observed = observed_inputs(settings, args.scene, inputs, seed)
    inputs_stamp = velocity_stamp(settings.params, args.scene, observed)
    path = velocity_path(args.out, seed)
    if given is None and resuming and path.is_file():
        given = path  # with the launch velocity its first iterations used
    if given is not None and not stamp.matches(read_json(given), inputs_stamp):
        why = "has no stamp" if stamp.KEY not in read_json(given) else "was made with other params or inputs"
        print(f"{given}: not reused: the launch velocity {why}; estimating it again")
        given = None
    if given is None:
        with stage_run("train", settings.params, scene=args.scene, method="velocity", tags={"seed": str(seed)}) as run:
            velocity = estimate_scene_velocity(settings, args.scene, observed, path, args.device)
            write_json(path, {**read_json(path), stamp.KEY: inputs_stamp})
            run.log_metrics({k: v for k, v in velocity.items() if k not in ("v0", "w0")})
    return read_velocity(given or path), inputs_stamp


def main(argv=None) -> dict:
    paths = ("scene-dir", "prep", "particles", "gaussians", "prior-dir", "out")
    ap = scene_parser(__doc__.splitlines()[0], paths)
    ap.add_argument("--velocity", type=Path, help="reuse this velocity.json (of the one seed run) instead of estimating it")
    args = ap.parse_args(argv)
    settings, scene, methods, inputs = scene_context("train", args)
    check_mlp_kernel(settings.train.mlp_kernel, args.device)  # before the launch-velocity fits
    runs = seed_runs(settings, methods, args.seeds)
    seeds = list(dict.fromkeys(s for _, s, _ in runs))
    if args.velocity is not None and len(seeds) > 1:
        raise SystemExit(f"train@{args.scene}: --velocity is one seed's estimate, but seeds {seeds} run (pick one with --seeds)")
    args.out.mkdir(parents=True, exist_ok=True)
    # an interrupted run of this call (e.g. stopped by grid.py --deadline) goes on from its checkpoint
    resuming = {s: any((args.out / name / "checkpoint.pt").is_file() for _, k, name in runs if k == s) for s in seeds}
    velocities = {s: seed_velocity(args, settings, inputs, s, args.velocity, resuming[s]) for s in seeds}
    results = {}
    for method, seed, name in runs:
        stop.check()  # a SIGTERM during the last run's final writes: that run is kept, this one is not started
        velocity, inputs_stamp = velocities[seed]
        # SIGTERM: checkpoint at the end of the iteration in progress, then stop; after the last iteration the run
        # finishes, its MLflow record included (its results and the job's .done marker are kept)
        with stop.deferred(stop_at_end=False), \
                stage_run("train", settings.params, **train_run_args(args.scene, method, seed, name, scene.material)) as run:
            run.log_params(method_params(method, settings.rdga, settings.cpr, settings.lora))
            checkpoint = args.out / name / "checkpoint.pt"
            stamp.guard_checkpoint(checkpoint, stamp.fingerprint(settings.params, TRAIN_KEYS,
                                                                 extra=[inputs_stamp, velocity, method.name, seed]))
            results[name] = train_method(settings, args.scene, method, inputs, velocity, args.out / name, run,
                                         args.device, seed)
            stamp.clear_checkpoint(checkpoint)
            run.log_artifact(args.out / name / "loss.png")
        print(f"train {args.scene}/{name}: {results[name]['status']} in {results[name]['train_seconds']:.1f} s")
    return results


if __name__ == "__main__":
    sys.exit(cli.run(main))
