"""The analytic laws' forward paths side by side in one process: a frame of ``--steps`` steps through
``MPMSolver.frame_fused`` (one particle pass a step), ``step_fused`` per step, and the generic step (law, then
transfers); ms per step, best of ``--repeats``. It decides ``MPMSolver.fuse_frames`` per device (NOTES, session 30).

    python benchmarks/bench_fused_frame.py --device cpu --law corotated neo_hookean --particles 30000 --n-grid 32
"""
import argparse
import sys
import time
from pathlib import Path

import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import _state, _sync, make_material  # noqa: E402

from gca.sim.solver import MPMSolver, SimConfig  # noqa: E402


def measure(law_name: str, n: int, n_grid: int, steps: int, repeats: int, device: torch.device) -> dict:
    """{path: ms per step} for one law on the lattice block (float32, dt 1e-4)."""
    cfg = SimConfig(n_grid=n_grid, dt=1e-4, dtype="float32")
    solver = MPMSolver(cfg, device)
    x, v, C, F, _, vol, mass = _state(n, cfg, device, "lattice")
    material = make_material(law_name, device, torch.float32)

    def frame():
        solver.frame_fused(x, v, C, F, law, vol, mass, steps)

    def fused_steps():
        state = (x, v, C, F)
        for _ in range(steps):
            state = solver.step_fused(*state, law, vol, mass)

    def generic():
        state = (x, v, C, F)
        for _ in range(steps):
            state = solver.step(*state, material.stress(state[3]), vol, mass)

    out = {}
    with torch.no_grad():
        law = material.elasticity.analytic_stress(F)
        for name, run in (("frame_fused", frame), ("step_fused", fused_steps), ("generic", generic)):
            run()  # warm-up: kernel loads
            best = float("inf")
            for _ in range(repeats):
                _sync(device)
                t0 = time.perf_counter()
                run()
                _sync(device)
                best = min(best, time.perf_counter() - t0)
            out[name] = 1e3 * best / steps
    return out


def main(argv=None) -> list:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--law", nargs="+", default=["corotated", "neo_hookean"], choices=["corotated", "neo_hookean"])
    p.add_argument("--particles", type=int, default=30000)
    p.add_argument("--n-grid", type=int, default=32)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    wp.config.quiet = True
    rows = []
    for law in args.law:
        row = {"law": law, **measure(law, args.particles, args.n_grid, args.steps, args.repeats, torch.device(args.device))}
        rows.append(row)
        print(" | ".join(f"{k} {v:.3f}" if isinstance(v, float) else str(v) for k, v in row.items()), "ms/step",
              flush=True)
    return rows


if __name__ == "__main__":
    main()
