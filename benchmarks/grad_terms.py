"""Which of a method's loss terms point the law where the ground truth is: per-term gradients at one law.

    python benchmarks/grad_terms.py --work /tmp/pp --scene fish --horizon 15 --json out.json

``--work`` is a pipeline (or ``gca/pipeline/grid.py``) work directory holding the scene's data, its
preprocessing and ``models/prior/<family>.pt`` (``--prior-dir`` elsewhere). At the prior (or a trained
``--law``), one rollout over the first ``--horizon`` video frames is differentiated once per term:

- the GCA terms (eq. 8) one at a time: ``mask`` (lambda_m L_mask), ``global`` (lambda_g lambda_1 ||P - Q||),
  ``anchor`` (lambda_g lambda_2 sum -gamma), ``cpr`` (R_e + R_p), and their sum ``gca``;
- ``color``: NeuMA's pixel colour L2 on the training view;
- ``oracle``: mean squared particle error against the ground-truth trajectory, which no method may
  see: the direction that would lower Table 1's Chamfer distance.

For each term: the gradient norm over the LoRA parameters and its cosine with the oracle's. A term
with a large norm and a cosine near 0 (or negative) steers the law away from the truth. The launch
velocity is the scene's true (v0, w0) unless ``--velocity`` names a ``velocity.json``, so the law is
the only unknown.

``--path K`` adds each image term's *value* along the straight line in state space from the law's
rollout (alpha = 0) to the ground-truth trajectory (alpha = 1), K + 1 points: particle positions
x(alpha) = (1 - alpha) x_law + alpha x_gt, deformation gradients the law's (the truth's are not stored).
A term whose value does not fall towards alpha = 1 does not have the truth at its minimum, whatever its
gradient; one that falls there but whose gradient opposes the oracle's is misled by the rollout's
nonlinearity, not by its definition.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gca.pipeline.grid import apply_overrides, scene_inputs  # noqa: E402  (the grid runner's --set and work layout)

from gca import config  # noqa: E402
from gca.pipeline.settings import Settings  # noqa: E402
from gca.scenes import truth  # noqa: E402
from gca.train.loop import simulate  # noqa: E402
from gca.train.methods import Method, get_method  # noqa: E402
from gca.pipeline.train import (SceneInputs, default_device, law_for, load_law, load_train_data,  # noqa: E402
                           objective_for, read_velocity, solver_for)

TERMS: dict[str, Method] = {
    "mask": Method("t_mask", terms=("silhouette",)),
    "global": Method("t_global", terms=("global",)),
    "anchor": Method("t_anchor", terms=("anchor",)),
    "cpr": Method("t_cpr", terms=("cpr",)),
    "gca": get_method("gca"),
    "color": get_method("neuma"),
}


def oracle_loss(traj, gt: torch.Tensor, video_frames: list[int], n_video: int) -> torch.Tensor:
    """Mean squared particle distance to the ground truth over video frames 1..n_video [m^2]."""
    pred = torch.stack([traj.x[f] for f in video_frames[:n_video]])  # [n, P, 3]
    return (pred - gt[1:n_video + 1]).square().sum(-1).mean()


def gt_dir_of(scene_dir: Path) -> Path:
    """``<work>/data/gt/<scene>`` beside ``<work>/data/scenes/<scene>`` (an oracle benchmark reads the truth)."""
    return Path(scene_dir).parent.parent / "gt" / Path(scene_dir).name


def _scene_and_law(params, scene_name: str, inputs: SceneInputs, velocity, law_path: Path | None, device: str):
    """The scene's config, its training data (GCA's view of it) and the law: the prior or ``law_path``."""
    scene = params.scene(scene_name)
    gca = get_method("gca")
    data = load_train_data(params, inputs, gca, velocity, params.video.background, device, dt=scene.dt)
    law = law_for(params, gca, scene, inputs, float(data.body.mass.sum() / data.body.vol.sum()), device)
    if law_path is not None:
        load_law(law_path, law, scene.prior)
    return scene, data, law


def term_gradients(params, scene_name: str, inputs: SceneInputs, loaded, n_video: int, terms: list[str],
                   device: str, ratios: list[float] = ()) -> list[dict]:
    """One row per term: loss, gradient norm, cosine with the oracle gradient. ``loaded``: the
    ``(scene, data, law)`` of :func:`_scene_and_law`."""
    scene, data, law = loaded
    solver = solver_for(params, scene, device)
    theta = law.trainable()
    gt = torch.as_tensor(truth.load_trajectory(gt_dir_of(inputs.scene_dir)), dtype=data.body.x0.dtype, device=device)

    def grad_of(loss_fn) -> tuple[float, torch.Tensor]:
        traj = simulate(solver, law, data, n_video)
        loss = loss_fn(traj)
        g = torch.autograd.grad(loss, theta, allow_unused=True)
        flat = torch.cat([(torch.zeros_like(p) if gi is None else gi).reshape(-1) for p, gi in zip(theta, g)])
        if not torch.isfinite(flat).all():
            raise FloatingPointError(f"non-finite gradient of a term at horizon {n_video}")
        return float(loss.detach()), flat.double()

    l_oracle, g_oracle = grad_of(lambda traj: oracle_loss(traj, gt, data.video_frames, n_video))
    rows = [{"term": "oracle", "loss": l_oracle, "grad_norm": float(g_oracle.norm()), "cos_oracle": 1.0}]
    cos_oracle = lambda g: float(g @ g_oracle / (g.norm() * g_oracle.norm()).clamp(min=1e-300))  # noqa: E731
    grads = {}
    for name in terms:
        method = TERMS[name]
        objective = objective_for(params, method, data, scene)
        stats: dict = {}

        def loss_fn(traj, objective=objective, stats=stats):
            loss, s = objective.loss(traj, n_video, law)
            stats.update(s)
            return loss

        loss, g = grad_of(loss_fn)
        grads[name] = g
        cos = cos_oracle(g)
        rows.append({"term": name, "loss": loss, "grad_norm": float(g.norm()), "cos_oracle": cos,
                     "stats": {k: v for k, v in stats.items() if k.startswith(("rdga/l_", "R_", "color"))}})
        print(f"  {name:7s} loss {loss:10.4g}  |grad| {float(g.norm()):10.3e}  cos(oracle) {cos:+.3f}", flush=True)
    if {"mask", "global", "anchor", "cpr"} <= grads.keys():  # GCA with CPR's gradient capped (objective.add_prior_gradient)
        g_data = grads["mask"] + grads["global"] + grads["anchor"]
        for r in ratios:
            scale = min(1.0, r * float(g_data.norm()) / max(float(grads["cpr"].norm()), 1e-300))
            g = g_data + scale * grads["cpr"]
            rows.append({"term": f"gca_cap{r:g}", "grad_norm": float(g.norm()), "cos_oracle": cos_oracle(g),
                         "prior_scale": scale})
            print(f"  gca, CPR capped at {r:g}x data: |grad| {float(g.norm()):10.3e}  cos(oracle) {cos_oracle(g):+.3f}")
    return rows


def path_values(params, scene_name: str, inputs: SceneInputs, loaded, n_video: int, terms: list[str],
                device: str, n_steps: int) -> list[dict]:
    """Each image term's value at ``n_steps + 1`` states between the law's rollout and the truth.
    ``loaded``: the ``(scene, data, law)`` of :func:`_scene_and_law`."""
    scene, data, law = loaded
    with torch.no_grad():
        traj = simulate(solver_for(params, scene, device), law, data, n_video)
    gt = torch.as_tensor(truth.load_trajectory(gt_dir_of(inputs.scene_dir)), dtype=traj.x.dtype, device=device)
    frames = data.video_frames[:n_video]
    objectives = {name: objective_for(params, TERMS[name], data, scene) for name in terms if name != "cpr"}
    rows = []
    for i in range(n_steps + 1):
        alpha = i / n_steps
        x = traj.x.clone()
        x[frames] = (1.0 - alpha) * traj.x[frames] + alpha * gt[1:n_video + 1]
        state = dataclasses.replace(traj, x=x)
        row = {"alpha": alpha, "rmse_m": float((x[frames] - gt[1:n_video + 1]).square().sum(-1).mean().sqrt())}
        with torch.no_grad():
            for name, objective in objectives.items():
                row[name] = float(objective.data_loss(state, n_video)[0])
        rows.append(row)
        print("  alpha {alpha:.2f} rmse {rmse_m:.4f} m  ".format(**row)
              + "  ".join(f"{k} {row[k]:.4g}" for k in objectives), flush=True)
    return rows


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--horizon", type=int, nargs="+", default=[15], help="supervised video frames (one run each)")
    ap.add_argument("--terms", nargs="+", default=list(TERMS), choices=list(TERMS))
    ap.add_argument("--prior-dir", type=Path, help="default: <work>/models/prior")
    ap.add_argument("--law", type=Path, help="a trained gca-family law.pt (default: the prior)")
    ap.add_argument("--velocity", type=Path, help="velocity.json (default: the scene's true v0, w0)")
    ap.add_argument("--set", action="append", default=[], help="dotted.key=yaml overrides of the params")
    ap.add_argument("--ratio", type=float, nargs="*", default=[0.1, 0.3, 1.0],
                    help="also GCA with CPR's gradient capped at these multiples of the data terms' (align.cpr.max_grad_ratio)")
    ap.add_argument("--profile", help="paper | ci (default: the params file's)")
    ap.add_argument("--device", default=default_device())
    ap.add_argument("--path", type=int, default=0, metavar="K",
                    help="also each image term's value at K + 1 states from the law's rollout to the truth")
    ap.add_argument("--no-gradients", action="store_true", help="with --path: only the values along the path")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    tree = apply_overrides(config.read_yaml(args.work / "params.yaml"), args.set)
    profile = args.profile or tree.get("profile", "paper")
    params = Settings({**config.resolve(tree, profile), "profile": profile})
    scene = params.scene(args.scene)
    inputs = scene_inputs(args.work, args.scene, params.params, args.prior_dir)
    velocity = read_velocity(args.velocity) if args.velocity else (list(scene.v0), list(scene.w0))
    loaded = _scene_and_law(params, args.scene, inputs, velocity, args.law, args.device)
    out = []
    for n in args.horizon:
        print(f"{args.scene}: horizon {n} video frames ({params.profile} profile)", flush=True)
        rows = [] if args.no_gradients else term_gradients(params, args.scene, inputs, loaded, n, args.terms,
                                                           args.device, args.ratio)
        out.append({"scene": args.scene, "horizon": n, "profile": params.profile, "set": args.set,
                    "law": str(args.law) if args.law else "prior", "rows": rows})
        if args.path:
            print(f"{args.scene}: term values from the law's rollout (alpha 0) to the truth (alpha 1)", flush=True)
            out[-1]["path"] = path_values(params, args.scene, inputs, loaded, n, args.terms, args.device, args.path)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
