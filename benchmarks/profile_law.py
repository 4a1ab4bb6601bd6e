"""Where an MPM step with a law spends GPU time: torch.profiler over a few eager steps (a script).

Usage::

    python benchmarks/profile_law.py --particles 100000 --steps 5 [--backward] [--law neural corotated]
        [--json out.json]

For each law prints the kernels sorted by total CUDA time (top ``--top``), then a summary per group
(MPM transfers, law kernels in warp, GEMMs, torch elementwise, memsets/copies) with the number of
kernels per step and their summed GPU time per step. Comparing that sum with the CUDA-graph replay
time of the same step (``bench_sim.py --graph on``) says how much of a replayed step is kernel work
and how much is the gaps between ~100 small kernels.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import torch
import warp as wp
from torch.profiler import ProfilerActivity, profile

from benchmarks.bench_sim import _state, make_material
from gca.laws.lora import merged_weights
from gca.sim import MPMSolver, SimConfig

GROUPS = (  # (group, regex on the kernel name), first match wins
    ("mpm p2g/grid/g2p", r"p2g|grid_update|g2p"),
    ("svd (warp)", r"svd"),
    ("law kernels (warp)", r"features|head|gca_laws|stress_kernel|corot"),
    ("gemm", r"gemm|sgemm|cutlass|ampere|sm90|cublas|xmma|nvjet"),
    ("memset/copy", r"memset|memcpy|Memcpy|Memset|copy"),
    ("reduce", r"reduce|Reduce"),
    ("torch elementwise", r"elementwise|vectorized|unrolled|at::native"),
)


def group_of(name: str) -> str:
    for group, pattern in GROUPS:
        if re.search(pattern, name):
            return group
    return "other"


def summarise(events, steps: int, cuda: bool = True) -> dict:
    """Kernels per step and GPU microseconds per step, by group (from profiler key averages)."""
    out: dict[str, dict] = {}
    for e in events:
        t = (getattr(e, "device_time_total", None) or getattr(e, "cuda_time_total", 0)) if cuda else e.self_cpu_time_total
        if not t:
            continue
        g = out.setdefault(group_of(e.key), {"kernels_per_step": 0.0, "us_per_step": 0.0})
        g["kernels_per_step"] += e.count / steps
        g["us_per_step"] += t / steps
    total = {"kernels_per_step": sum(g["kernels_per_step"] for g in out.values()),
             "us_per_step": sum(g["us_per_step"] for g in out.values())}
    return {"groups": out, "total": total}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--particles", type=int, default=100000)
    p.add_argument("--n-grid", type=int, default=64)
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--backward", action="store_true")
    p.add_argument("--law", nargs="+", default=["neural"], choices=["neural", "corotated"])
    p.add_argument("--top", type=int, default=30)
    p.add_argument("--json", default=None)
    p.add_argument("--device", default="cuda", help="cpu: a smoke run of this script (CPU ops, not kernels)")
    args = p.parse_args(argv)
    wp.config.quiet = True
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    cfg = SimConfig(n_grid=args.n_grid, dt=1e-4)
    solver = MPMSolver(cfg, device)
    x, v, C, F, _, vol, mass = _state(args.particles, cfg, device)
    results = {"device": torch.cuda.get_device_name(device) if cuda else "cpu", "particles": args.particles, "n_grid": args.n_grid,
               "steps": args.steps, "backward": args.backward, "laws": {}}
    for law in args.law:
        material = make_material(law, device, torch.float32)

        def run():
            # one frame of steps: a LoRA law's merged weights formed once, as gca.sim.frame does in training
            with torch.set_grad_enabled(args.backward), merged_weights(material):
                xs, vs, Cs, Fs = x, v.clone().requires_grad_(args.backward), C, F
                for _ in range(args.steps):
                    xs, vs, Cs, Ftr = solver.step(xs, vs, Cs, Fs, material.stress(Fs), vol, mass)
                    Fs = material.project(Ftr)
                if args.backward:
                    (xs.sum() + Fs.sum()).backward()
            if cuda:
                torch.cuda.synchronize()

        run()
        with profile(activities=[ProfilerActivity.CUDA if cuda else ProfilerActivity.CPU]) as prof:
            run()
        events = prof.key_averages()
        print(f"== law {law}: {args.particles} particles, {args.n_grid}^3, {args.steps} steps, "
              f"{'forward + backward' if args.backward else 'forward'}")
        print(events.table(sort_by="cuda_time_total" if cuda else "cpu_time_total", row_limit=args.top, max_name_column_width=70))
        s = summarise(events, args.steps, cuda)
        results["laws"][law] = s
        for g, d in sorted(s["groups"].items(), key=lambda kv: -kv[1]["us_per_step"]):
            print(f"  {g:<22} {d['kernels_per_step']:6.1f} kernels/step {d['us_per_step']:9.1f} us/step")
        print(f"  {'total':<22} {s['total']['kernels_per_step']:6.1f} kernels/step "
              f"{s['total']['us_per_step']:9.1f} us/step", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
