"""The neural law's matrix products in TF32 beside FP32: speed, and what TF32 does to a rollout and its gradient
(a script, not a test).

Issue 20, session 33: a swept paper-profile GCA iteration on the ball is 0.77 s of CUDA kernels, ~210 ms of them the
neural law's ~19k small FP32 matrix products ([N, 13 or 64] x [64 or 9], N = 30k; benchmarks/NOTES.md s33). TF32
tensor cores would run them at 10 mantissa bits instead of 23. Before any option is offered, this measures both sides
on one device:

- ``law``: one MPM step's calls of the law (plasticity on F_trial, then elasticity on F_e; NCLaw networks with LoRA
  r = 16 as training runs them, the paper prior's weights), forward, and forward + backward, per call [us], at FP32
  and at TF32 (``torch.backends.cuda.matmul.allow_tf32``);
- ``rollout``: a lattice ball of ~64 particles per cell (denser than the paper profile's ~12: session 34) dropped with a spin onto the
  floor, ``--steps`` steps, in float64 (the reference), float32, and float32 with TF32 products: each one's largest
  position deviation from float64 over all frames [m] and [cells], and of F;
- ``gradient``: the gradient of a fixed random projection of the last frame's positions with respect to the LoRA
  factors (checkpointed rollout, autograd), each precision's cosine with float64's and relative error.

TF32 is a CUDA mode (``train.matmul_precision: high``, set here the same way, ``gca.train.loop.matmul_precision``); on
a CPU torch may pick reduced-precision kernels of its own under it, or none (the CPU test checks the script runs and
the float32 deviations are small, not what TF32 does).

Usage::

    python benchmarks/bench_law_precision.py --device cuda --json out.json
    python benchmarks/bench_law_precision.py --device cpu --particles 600 --n-grid 16 --steps 20   # smoke
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_p2g import lattice_ball  # noqa: E402

from gca.efficiency import best_time_us  # noqa: E402
from gca.laws.base import Material  # noqa: E402
from gca.laws.checkpoint import load_prior  # noqa: E402
from gca.laws.lora import apply_lora, lora_layers, lora_parameters  # noqa: E402
from gca.sim import MPMSolver, SimConfig, rollout  # noqa: E402
from gca.train.loop import matmul_precision  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RHO = 1000.0  # density [kg/m^3]


def tf32(on: bool):
    """The block's float32 products as training runs them at ``train.matmul_precision`` high (TF32 on CUDA) or
    highest (FP32): :func:`gca.train.loop.matmul_precision`, restored after."""
    return matmul_precision("high" if on else "highest")


def material(prior: Path, device, dtype: torch.dtype, seed: int = 0) -> Material:
    """The prior's networks with LoRA r = 16 on every layer (B = 0: the prior's law; A seeded), as training runs them;
    B is then set to small seeded values so the gradient check differentiates an adapted law, not only the prior."""
    p = load_prior(prior)
    g = torch.Generator().manual_seed(seed)
    for net in (p.elasticity, p.plasticity):
        apply_lora(net, 16, 16.0, generator=g)
        with torch.no_grad():
            for name, q in net.named_parameters():
                if name.endswith("lora_B"):
                    q.copy_(1e-2 * torch.randn(q.shape, generator=g))
    return Material(p.elasticity, p.plasticity, RHO).to(device=device, dtype=dtype)


@contextlib.contextmanager
def frame_merge(mat: Material):
    """Every LoRA layer applies W + (alpha / r) B A formed once, as a simulated frame forms it
    (``gca.laws.lora.merged_weights``), here as leaves that take gradients: the timed backward computes the weight
    gradients' products as training's does, without repeating the once-per-frame merge."""
    layers = [layer for net in (mat.elasticity, mat.plasticity) for layer in lora_layers(net)]
    for layer in layers:
        layer._merged = (layer.weight + layer.delta_weight()).detach().requires_grad_(True)
    try:
        yield
    finally:
        for layer in layers:
            layer._merged = None


def ball(n: int, n_grid: int, device, dtype) -> tuple[torch.Tensor, ...]:
    """A lattice ball of ~n particles at spacing dx / 4 (~64 per cell) centred at (0.5, 0.3, 0.5), in meshgrid order;
    (x0 [N, 3] m, v0 [N, 3] m/s: falling at 2 m/s and spinning at 5 rad/s about z, vol [N] m^3, mass [N] kg)."""
    x, _ = lattice_ball(n, n_grid)
    s = 0.25 / n_grid  # its spacing
    v = torch.zeros_like(x)
    v[:, 1] = -2.0
    v[:, 0], v[:, 1] = v[:, 0] - 5.0 * x[:, 1], v[:, 1] + 5.0 * x[:, 0]  # omega x r, omega = (0, 0, 5)
    x = x + torch.tensor([0.5, 0.3, 0.5], dtype=torch.float64)
    vol = torch.full((len(x),), s ** 3, dtype=torch.float64)
    to = dict(device=device, dtype=dtype)
    return x.to(**to), v.to(**to), vol.to(**to), (vol * RHO).to(**to)


def law_times(mat: Material, n: int, device, iters: int, repeats: int, on: bool) -> dict:
    """One MPM step's law calls (project then stress) on n near-identity F [us per call], forward and fwd + bwd."""
    g = torch.Generator().manual_seed(1)
    F = (torch.eye(3, dtype=torch.float64) + 0.05 * torch.randn(n, 3, 3, generator=g)).to(device=device,
                                                                                          dtype=torch.float32)
    w = torch.randn(n, 3, 3, generator=g).to(F)

    def forward():  # the LoRA merge formed once per frame in a rollout (gca.sim.frame), so outside the timing here
        with torch.no_grad():
            mat.stress(mat.project(F))

    def backward():
        Fg = F.detach().requires_grad_(True)
        Fe = mat.project(Fg)
        ((mat.stress(Fe) * w).sum() + (Fe * w).sum()).backward()

    with tf32(on), frame_merge(mat):
        return {"forward_us": best_time_us(forward, device, iters, repeats),
                "forward_backward_us": best_time_us(backward, device, iters, repeats)}


def simulate(prior: Path, n: int, n_grid: int, steps: int, steps_per_frame: int, device, dtype: torch.dtype,
             on: bool, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A rollout of the adapted prior law at ``dtype`` (TF32 products if ``on``) and the gradient of a fixed random
    projection of its last positions with respect to the LoRA factors; (x [frames, N, 3], F [frames, N, 3, 3],
    gradient [P]) in float64 on the CPU."""
    mat = material(prior, device, dtype, seed)
    solver = MPMSolver(SimConfig(n_grid=n_grid, dtype="float64" if dtype == torch.float64 else "float32",
                                 cuda_graphs=False), device=device)
    x0, v0, vol, mass = ball(n, n_grid, device, dtype)
    w = torch.randn(x0.shape, generator=torch.Generator().manual_seed(seed + 7), dtype=torch.float64).to(x0)
    params = list(lora_parameters(mat))
    with tf32(on):
        traj = rollout(solver, mat, x0, v0, vol, mass, n_steps=steps, steps_per_frame=steps_per_frame,
                       checkpoint=True, graph=False)
        grads = torch.autograd.grad((traj.x[-1] * w).sum(), params)
    flat = torch.cat([q.reshape(-1) for q in grads]).detach().double().cpu()
    return traj.x.detach().double().cpu(), traj.F.detach().double().cpu(), flat


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--prior", type=Path, default=ROOT / "benchmarks" / "results" / "priors_paper" / "jelly.pt")
    p.add_argument("--particles", type=int, default=30000)
    p.add_argument("--n-grid", type=int, default=32)
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--steps-per-frame", type=int, default=20)
    p.add_argument("--iters", type=int, default=100)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    device = torch.device(a.device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    out = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
           "particles": a.particles, "n_grid": a.n_grid, "steps": a.steps, "law": {}, "rollout": {}}
    mat = material(a.prior, device, torch.float32)
    print("| products | law forward us | law forward + backward us |\n| --- | --- | --- |")
    for name, on in (("fp32", False), ("tf32", True)):
        out["law"][name] = r = law_times(mat, a.particles, device, a.iters, a.repeats, on)
        print(f"| {name} | {r['forward_us']:.1f} | {r['forward_backward_us']:.1f} |", flush=True)
    ref_x, ref_F, ref_g = simulate(a.prior, a.particles, a.n_grid, a.steps, a.steps_per_frame, device,
                                   torch.float64, False)
    dx = 1.0 / a.n_grid
    print("| rollout | max position deviation from float64 [m] (cells) | max F deviation | gradient cosine | "
          "gradient relative error |\n| --- | --- | --- | --- | --- |")
    for name, on in (("fp32", False), ("tf32", True)):
        x, F, g = simulate(a.prior, a.particles, a.n_grid, a.steps, a.steps_per_frame, device, torch.float32, on)
        dev_x = float((x - ref_x).norm(dim=-1).max())
        r = {"max_dx_m": dev_x, "max_dx_cells": dev_x / dx, "max_dF": float((F - ref_F).abs().max()),
             "grad_cos": float(g @ ref_g / (g.norm() * ref_g.norm())),
             "grad_rel_err": float((g - ref_g).norm() / ref_g.norm()), "particles": int(x.shape[1])}
        out["rollout"][name] = r
        print(f"| {name} | {r['max_dx_m']:.3g} ({r['max_dx_cells']:.3g}) | {r['max_dF']:.3g} | {r['grad_cos']:.6f} | "
              f"{r['grad_rel_err']:.3g} |", flush=True)
    if a.json:
        a.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
