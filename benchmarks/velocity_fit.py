"""Launch-velocity estimation against the ground truth, split along the training camera's viewing ray.

    python benchmarks/velocity_fit.py --work /tmp/pp --scene duck --seed 0 1 2 \
        --variant "" --variant "velocity.reg_view_axis=0 velocity.n_video_frames=12"

``--work`` is a pipeline (or ``gca/pipeline/grid.py``) work directory holding the scene's data, its
preprocessing and ``models/prior/<family>.pt``. Each variant (space-separated ``dotted.key=yaml``
overrides of its ``params.yaml``) fits (v0, w0) as the ``train`` stage does; the table gives the error
of v0 along the viewing ray (weakly observable from one view) and in the image plane [m/s], and of w0, on each
``--seed``'s observations (its nuisance draw: segmentation, depth, lighting; ``train.seeds`` of the work directory).
It reads the scene's true launch: use it on calibration scenes only (a table scene's truth is evaluation's).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gca.pipeline.grid import apply_overrides, scene_inputs  # noqa: E402  (the grid runner's --set)

from gca import config  # noqa: E402
from gca.pipeline.settings import Settings  # noqa: E402
from gca.scenes.ground_truth import scene_cameras  # noqa: E402
from gca.pipeline.train import default_device, estimate_scene_velocity, observed_inputs  # noqa: E402


def errors(params, scene_name: str, fit: dict) -> dict:
    """v0 error along the train0 viewing ray and in the image plane [m/s], w0 error [rad/s]."""
    scene = Settings(params).scene(scene_name)
    axis = np.array(scene_cameras(scene, 8)["train0"].w2c)[2, :3]
    err = np.array(fit["v0"]) - np.array(scene.v0)
    along = float(err @ axis)
    return {"v0_along_ray": along, "v0_in_plane": float(np.linalg.norm(err - along * axis)),
            "v0_gt_along_ray": float(np.array(scene.v0) @ axis),
            "w0_error": float(np.linalg.norm(np.array(fit["w0"]) - np.array(scene.w0)))}


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--variant", action="append", default=[], help="space-separated dotted.key=value overrides")
    ap.add_argument("--seed", type=int, nargs="+", default=[0], help="observations of these training seeds")
    ap.add_argument("--device", default=default_device())
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    base = config.load(f"velocity_fit@{args.scene}", args.work / "params.yaml")
    inputs = scene_inputs(args.work, args.scene, base)
    rows = []
    print(f"{'variant':50s} {'seed':6s} {'gt along':>8s} {'err along':>9s} {'in-plane':>8s} {'w0 err':>7s} {'loss':>8s}")
    for text in args.variant or [""]:
        params = apply_overrides(copy.deepcopy(base), text.split())
        settings = Settings(params)
        for seed in args.seed:  # each row as its fit ends (a run cut off keeps them: benchmarks/launch_choice.py)
            with tempfile.TemporaryDirectory() as tmp:
                fit = estimate_scene_velocity(settings, args.scene, observed_inputs(settings, args.scene, inputs, seed),
                                              Path(tmp) / "velocity.json", args.device)
            r = {"variant": text or "params.yaml", "scene": args.scene, "seed": seed, **fit,
                 **errors(params, args.scene, fit)}
            rows.append(r)
            print(f"{r['variant']:50s} seed {seed} {r['v0_gt_along_ray']:+8.2f} {r['v0_along_ray']:+9.2f} "
                  f"{r['v0_in_plane']:8.2f} {r['w0_error']:7.2f} {r['loss_last']:8.4f}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
