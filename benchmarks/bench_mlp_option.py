"""``train.mlp_kernel`` on one neural rollout (a script, not a test): each kind's 200-step rollout forward + backward
(CUDA graphs, as training runs it: ``bench_runs.one_rollout``) timed, and its final positions and launch-velocity
gradient against the first kind's (``torch``): what TF32 (``triton_tf32``) costs in the numbers it changes.

Usage::

    python benchmarks/bench_mlp_option.py --device cuda --kinds torch triton_tf32 torch --json out.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.bench_runs import _sync, one_rollout, runs_setup  # noqa: E402
from gca.laws.neural import neural_networks  # noqa: E402


def set_kind(law, kind: str) -> None:
    """Every neural network of ``law`` runs its MLP on ``kind``, as ``gca.train.loop.mlp_kernel`` sets it for a run
    (not imported here: the training modules need packages the GPU image lacks)."""
    for net in neural_networks(law):
        net.mlp_kernel = kind


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--kinds", nargs="+", default=["torch", "triton_tf32", "torch"])
    ap.add_argument("--particles", type=int, default=30000)
    ap.add_argument("--n-grid", type=int, default=32)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--per-frame", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=8)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    solver, x, vol, mass, laws, v0s = runs_setup(1, args.particles, args.n_grid, device)
    rows, ref = [], None
    print("| kind | ms per rollout (fwd + bwd) | final x: max dev / cell | v0 grad: rel dev |\n| --- | --- | --- | --- |",
          flush=True)
    for kind in args.kinds:
        set_kind(laws[0], kind)
        xf, g = one_rollout(solver, laws[0], x, v0s[0], vol, mass, args.steps, args.per_frame)  # warm-up (compiles)
        _sync(device)
        t0 = time.perf_counter()
        for _ in range(args.repeats):
            one_rollout(solver, laws[0], x, v0s[0], vol, mass, args.steps, args.per_frame)
        _sync(device)
        ms = (time.perf_counter() - t0) / args.repeats * 1e3
        ref = ref or (xf, g)
        dx = float((xf - ref[0]).abs().max() * args.n_grid)  # in grid cells (the domain is the unit cube)
        dg = float((g - ref[1]).abs().max() / ref[1].abs().max())
        rows.append({"kind": kind, "ms": ms, "x_dev_cells": dx, "grad_rel_dev": dg})
        print(f"| {kind} | {ms:.1f} | {dx:.2e} | {dg:.2e} |", flush=True)
    if args.json:
        name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
        args.json.write_text(json.dumps({"device": name, "args": vars(args) | {"json": str(args.json)}, "rows": rows},
                                        indent=1))
    return rows


if __name__ == "__main__":
    main()
