"""How much of a table's Chamfer distance is the launch velocity's error? (evaluation-side: reads the true v0)

Each visual row of a (scene, seed) starts from the launch velocity v0 [m/s] estimated from that seed's observations
(``gca.train.velocity``, NeuMA's stage A: silhouettes of the first frames under the prior law, and since session 22 point tracks), so a wrong v0 moves
every row's trajectory alike. This prints, per (scene, seed) of a grid state, the estimate's error against the
scene's true v0 (params ``scenes.<name>.v0``, ground truth: only evaluation may read it), the Chamfer distance of
each method, and the Spearman rank correlation of |v0 error| with the prior's (``nclaw``) CD across the units.

    python benchmarks/velocity_vs_cd.py --state benchmarks/results/table1_seeds/state.tgz [--methods nclaw neuma gca]

Session 21 (Table 1 at the paper profile, three seeds): |error| 0.35-7.3 m/s, mostly along z (true |v0| ~2 m/s), and rank the prior's CD with rho 0.92 over the 18 units (benchmarks/NOTES.md).
"""

from __future__ import annotations

import argparse
import json
import tarfile
from pathlib import Path

import numpy as np
import yaml
from scipy.stats import spearmanr

ROOT = Path(__file__).resolve().parents[1]


def _run_name(method: str, seed: int) -> str:
    return method if seed == 0 else f"{method}@seed{seed}"


def units(members: dict[str, bytes], true_v0: dict[str, list], methods: list[str], seeds: list[int]) -> list[dict]:
    """One row per (scene, seed) with every method evaluated: ``error`` [3] = v0 estimate - truth [m/s] (the estimate
    the first method's run trained with: its ``train.json`` ``velocity``, else the seed's ``velocity*.json``) and
    ``cd`` {method: chamfer_mean [m]}."""
    rows = []
    for scene, truth in true_v0.items():
        for seed in seeds:
            evals = {m: members.get(f"metrics/eval/{scene}/{_run_name(m, seed)}.json") for m in methods}
            if not all(evals.values()) or any("chamfer_mean" not in json.loads(e) for e in evals.values()):
                continue  # not evaluated, or a rollout that diverged (no CD)
            train = json.loads(members.get(f"runs/{scene}/{_run_name(methods[0], seed)}/train.json", b"{}"))
            velocity = train.get("velocity") or json.loads(
                members[f"runs/{scene}/velocity{'' if seed == 0 else f'@seed{seed}'}.json"])
            error = np.asarray(velocity["v0"], float) - np.asarray(truth, float)
            rows.append({"scene": scene, "seed": seed, "error": error,
                         "cd": {m: float(json.loads(e)["chamfer_mean"]) for m, e in evals.items()}})
    return rows


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--state", type=Path, required=True, help="a grid state (grid --save-state)")
    ap.add_argument("--methods", nargs="+", default=["nclaw", "neuma", "gca"], help="the first one is correlated")
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    args = ap.parse_args(argv)
    with tarfile.open(args.state, "r:gz") as tar:
        members = {m.name: tar.extractfile(m).read() for m in tar.getmembers() if m.isfile()}
    params = yaml.safe_load(args.params.read_text())
    seeds = list(params["train"].get("seeds") or [0])
    scenes = sorted({name.split("/")[2] for name in members if name.startswith("metrics/eval/")})
    true_v0 = {s: params["scenes"][s]["v0"] for s in scenes if "v0" in params["scenes"].get(s, {})}
    rows = units(members, true_v0, args.methods, sorted(set(seeds) | {0, 1, 2}))
    print("scene  seed  err_x  err_y  err_z  |err| [m/s]  " + "  ".join(f"CD {m}" for m in args.methods))
    for r in rows:
        e = r["error"]
        print(f"{r['scene']:<7}{r['seed']:>4}  {e[0]:6.2f} {e[1]:6.2f} {e[2]:6.2f}  {np.linalg.norm(e):8.2f}     "
              + "  ".join(f"{r['cd'][m]:.4f}" for m in args.methods))
    if len(rows) >= 3:
        norm = [float(np.linalg.norm(r["error"])) for r in rows]
        rho = spearmanr(norm, [r["cd"][args.methods[0]] for r in rows]).statistic
        print(f"{len(rows)} units; |v0 error| median {np.median(norm):.2f} m/s (range {min(norm):.2f}-{max(norm):.2f}); "
              f"Spearman rho(|v0 error|, CD {args.methods[0]}) = {rho:.3f}")
    return rows


if __name__ == "__main__":
    main()
