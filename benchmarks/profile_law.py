"""Where a neural-law MPM step spends GPU time: torch.profiler over a few eager steps (a script).

Usage::

    python benchmarks/profile_law.py --particles 100000 --steps 5 [--backward]

Prints the kernels sorted by total CUDA time (top ``--top``) and the share of the MPM transfers.
"""

from __future__ import annotations

import argparse

import torch
import warp as wp
from torch.profiler import ProfilerActivity, profile

from benchmarks.bench_sim import _state, make_material
from gca.sim import MPMSolver, SimConfig


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--particles", type=int, default=100000)
    p.add_argument("--n-grid", type=int, default=64)
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--backward", action="store_true")
    p.add_argument("--top", type=int, default=30)
    args = p.parse_args(argv)
    wp.config.quiet = True
    device = torch.device("cuda")
    cfg = SimConfig(n_grid=args.n_grid, dt=1e-4)
    solver = MPMSolver(cfg, device)
    x, v, C, F, _, vol, mass = _state(args.particles, cfg, device)
    material = make_material("neural", device, torch.float32)

    def run():
        with torch.set_grad_enabled(args.backward):
            xs, vs, Cs, Fs = x, v.clone().requires_grad_(args.backward), C, F
            for _ in range(args.steps):
                xs, vs, Cs, Ftr = solver.step(xs, vs, Cs, Fs, material.stress(Fs), vol, mass)
                Fs = material.project(Ftr)
            if args.backward:
                (xs.sum() + Fs.sum()).backward()
        torch.cuda.synchronize()

    run()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        run()
    print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=args.top, max_name_column_width=60))


if __name__ == "__main__":
    main()
