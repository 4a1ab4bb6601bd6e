"""Several runs' simulations in one launch per step against the same runs one after another (a script, not a test).

For B in ``--runs``: B independent runs, each a lattice block of ``--particles`` particles with its own LoRA-adapted
neural law (different adapters), rolled out for ``--steps`` steps (frames of ``--steps-per-frame``) forward and
backward, as training does:

- ``sequential``: one rollout per run, one after another (what B trainings in one process would do today);
- ``batched``: one rollout over all runs' particles (``MPMSolver.with_runs``: one P2G / grid update / G2P launch per
  step with a grid per run), the laws evaluated run by run (``--laws composite``: a ``CompositeMaterial``) or as one
  batch (``--laws batched``: ``gca.laws.batched``, one ``bmm`` per layer, features and heads over all particles).

Reports seconds per run and the speed-up. On CUDA the frames replay from CUDA graphs (``gca.sim.graph``).

Usage::

    python benchmarks/bench_runs.py --device cuda --runs 1 2 4 8 --particles 30000 --n-grid 32 --json out.json
"""

from __future__ import annotations

import argparse
import json
import time

import torch
import warp as wp

from benchmarks.bench_sim import RHO, block
from gca.laws.base import CompositeMaterial, Material
from gca.laws.batched import runs_material
from gca.laws.lora import apply_lora
from gca.laws.neural import NeuralElasticity, NeuralPlasticity
from gca.sim import MPMSolver, SimConfig, rollout


def make_law(seed: int, device, dtype) -> Material:
    """NCLaw networks with LoRA r 16 and non-zero adapters (seeded), as a run of GCA trains them."""
    torch.manual_seed(seed)
    e, p = NeuralElasticity(), NeuralPlasticity()
    for net in (e, p):
        apply_lora(net, 16, 16.0)
        for name, param in net.named_parameters():
            if name.endswith("lora_B"):
                torch.nn.init.normal_(param, std=1e-3)
    return Material(e, p, RHO).to(device=device, dtype=dtype)


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


WAVE_SPEED = 12.0  # for the rollouts' CFL check [m/s]


def runs_setup(n_runs: int, n: int, n_grid: int, device, seed: int = 0):
    """B = ``n_runs`` runs on one lattice block of ~n particles: (solver, x, vol, mass, laws, v0s); run r's law is
    ``make_law(seed * 1000 + r)``, its launch velocity (0.3 r, -1, 0) m/s."""
    cfg = SimConfig(n_grid=n_grid, dt=2e-4, dtype="float32", max_refine=1)
    solver = MPMSolver(cfg, device)
    x, vol, mass = block(n, cfg, device, order="lattice")
    n = x.shape[0]
    laws = [make_law(seed * 1000 + r, device, torch.float32) for r in range(n_runs)]
    v0s = [torch.tensor([0.3 * r, -1.0, 0.0], device=device).expand(n, 3).contiguous() for r in range(n_runs)]
    return solver, x, vol, mass, laws, v0s


def one_rollout(solver, material, x, v0, vol, mass, steps: int, per_frame: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A rollout from launch velocity v0 forward and backward (a fixed loss of the positions), as training runs it:
    (final positions [N, 3], d sum(x^2) / d v0 [N, 3])."""
    v0 = v0.clone().requires_grad_(True)
    out = rollout(solver, material, x, v0, vol, mass, steps, per_frame, wave_speed=WAVE_SPEED)
    (out.x[1:] ** 2).sum().backward()
    return out.x[-1].detach(), v0.grad.detach()


def as_batch(solver, x, vol, mass, laws, v0s, laws_mode: str = "batched"):
    """The runs as one: (the solver over the runs' stacked grids, their material, x, v0, vol, mass concatenated), for
    :func:`one_rollout`; ``laws_mode`` composite (a ``CompositeMaterial``) or batched (``gca.laws.batched``)."""
    b, n = len(laws), x.shape[0]
    run = torch.arange(b, device=x.device, dtype=torch.int32).repeat_interleave(n)
    both = CompositeMaterial(laws, [n] * b) if laws_mode == "composite" else runs_material(laws, [n] * b)
    return solver.with_runs(run, b), both, x.repeat(b, 1), torch.cat(v0s), vol.repeat(b), mass.repeat(b)


def measure(n_runs: int, n: int, n_grid: int, steps: int, per_frame: int, device, repeats: int,
            laws_mode: str = "composite") -> dict:
    solver, x, vol, mass, laws, v0s = runs_setup(n_runs, n, n_grid, device)
    n = x.shape[0]

    def sequential():
        for law, v0 in zip(laws, v0s):
            one_rollout(solver, law, x, v0, vol, mass, steps, per_frame)

    batch = as_batch(solver, x, vol, mass, laws, v0s, laws_mode)

    def batched():
        one_rollout(*batch, steps, per_frame)

    row = {"runs": n_runs, "particles_per_run": n, "n_grid": n_grid, "steps": steps, "laws": laws_mode}
    for name, fn in (("sequential", sequential), ("batched", batched)):
        fn()  # warm-up: capture, kernel loads
        best = float("inf")
        for _ in range(repeats):
            _sync(device)
            t0 = time.perf_counter()
            fn()
            _sync(device)
            best = min(best, time.perf_counter() - t0)
        row[f"{name}_s"] = best
        row[f"{name}_s_per_run"] = best / n_runs
    row["speedup"] = row["sequential_s"] / row["batched_s"]
    return row


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--runs", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--particles", type=int, default=30000)
    ap.add_argument("--n-grid", type=int, default=32)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--steps-per-frame", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--laws", nargs="+", default=["composite"], choices=["composite", "batched"])
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    device = torch.device(a.device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    rows = []
    print("| laws | runs | particles per run | grid | sequential s | batched s | s per run, sequential -> batched | "
          "speed-up |\n| --- | --- | --- | --- | --- | --- | --- | --- |")
    for mode in a.laws:
        for b in a.runs:
            r = measure(b, a.particles, a.n_grid, a.steps, a.steps_per_frame, device, a.repeats, mode)
            rows.append(r)
            print(f"| {mode} | {b} | {r['particles_per_run']} | {a.n_grid}^3 | {r['sequential_s']:.3f} | "
                  f"{r['batched_s']:.3f} | {r['sequential_s_per_run']:.3f} -> {r['batched_s_per_run']:.3f} | "
                  f"{r['speedup']:.2f}x |", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu", "rows": rows},
                      f, indent=2)
    return rows


if __name__ == "__main__":
    main()
