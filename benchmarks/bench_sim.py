"""Throughput and memory of the gca.sim MPM solver (a script, not a test).

Measures, for each (particles, grid) configuration:
  - forward particle-steps per second of ``MPMSolver.step`` (tau given, no law cost),
  - forward + backward particle-steps per second (a chain of steps, then one backward),
and, unless ``--skip-rollout``, the peak memory of back-propagating a checkpointed rollout
(corotated law from gca.laws; default 30k particles, 400 steps): ``torch.cuda.max_memory_allocated``
on CUDA, the process' peak RSS on the CPU (a coarse upper bound that includes the interpreter).

Usage::

    python benchmarks/bench_sim.py --device cuda                      # paper sizes (H100)
    python benchmarks/bench_sim.py --device cuda --law none neural --graph off on   # CUDA graphs vs launches
    python benchmarks/bench_sim.py --device cpu --sizes 10000:32 2000:32 --steps 5 \
        --rollout-particles 3000 --rollout-steps 40                   # CPU smoke sizes

Prints a table and writes JSON (``--json``, default benchmarks/results/sim_<device>.json).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import time
from pathlib import Path

import torch
import warp as wp

from gca.laws.base import Elasticity, Material
from gca.laws.elastic import CorotatedElasticity
from gca.laws.plastic import IdentityPlasticity
from gca.sim import MPMSolver, SimConfig, rollout
from gca.sim.graph import graphed_frame

RHO = 1000.0  # density [kg/m^3]
PPC = 8  # particles per occupied cell when placing the block [count]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def block(n: int, cfg: SimConfig, device: torch.device, seed: int = 0, order: str = "random"):
    """n particles in a centred cube holding about PPC per cell: uniformly at random (``order="random"``), or
    ``"lattice"``: round(n^(1/3))^3 particles on a regular lattice in meshgrid order, the way
    ``gca.assets.particles`` samples objects (the order decides how P2G's atomics collide: ``bench_p2g.py``)."""
    g = torch.Generator().manual_seed(seed)
    side = min((n / PPC) ** (1 / 3), cfg.n_grid - 2 * cfg.bound - 4) * cfg.dx
    lo = torch.tensor([0.5 - side / 2, (cfg.bound + 2) * cfg.dx, 0.5 - side / 2], dtype=torch.float64)
    if order == "lattice":
        k = round(n ** (1 / 3))
        n = k ** 3
        axis = (torch.arange(k, dtype=torch.float64) + 0.5) / k
        x = lo + side * torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    elif order == "random":
        x = lo + side * torch.rand(n, 3, generator=g, dtype=torch.float64)  # just above the floor wall
    else:
        raise ValueError(f"benchmarks/bench_sim.py: order must be random or lattice, got {order!r}")
    vol = torch.full((n,), side**3 / n, dtype=torch.float64)
    to = dict(dtype=cfg.torch_dtype, device=device)
    return x.to(**to), vol.to(**to), (vol * RHO).to(**to)


def _state(n, cfg, device, order: str = "random"):
    x, vol, mass = block(n, cfg, device, order=order)
    n = x.shape[0]
    to = dict(dtype=cfg.torch_dtype, device=device)
    v = torch.zeros(n, 3, **to)
    C = torch.zeros(n, 3, 3, **to)
    F = torch.eye(3, **to).expand(n, 3, 3).contiguous()
    tau = 1e3 * torch.randn(n, 3, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(**to)
    return x, v, C, F, tau, vol, mass


def make_material(law: str, device, dtype: torch.dtype) -> Material:
    """``corotated`` (analytic) or ``neural``: NCLaw networks with LoRA r=16 on every layer (a GCA step),
    features and heads in warp kernels (``gca.laws.fused``); ``neural_ref``: the same through the torch
    reference path; ``neo_hookean`` / ``neo_hookean_ref``: the elastomer law with learnable E and nu, fused / torch."""
    if law in ("neural", "neural_ref"):
        from gca.laws.lora import apply_lora
        from gca.laws.neural import NeuralElasticity, NeuralPlasticity
        e, p = NeuralElasticity(), NeuralPlasticity()
        apply_lora(e, 16, 16.0)
        apply_lora(p, 16, 16.0)
        e.fast_path = p.fast_path = law == "neural"
        return Material(e, p, RHO).to(device=device, dtype=dtype)
    if law in ("neo_hookean", "neo_hookean_ref"):  # the PAC-NeRF-style elastic rows' law (learnable E, nu)
        from gca.laws.ood import NeoHookeanElasticity
        e = NeoHookeanElasticity(1e5, 0.3, learnable=True)
        e.fast_path = law == "neo_hookean"
        return Material(e, IdentityPlasticity(), RHO).to(device=device, dtype=dtype)
    return Material(CorotatedElasticity(1e5, 0.3), IdentityPlasticity(), RHO).to(device=device, dtype=dtype)


class FixedStress(Elasticity):
    """tau(F) = a fixed stress field [N,3,3] (Pa): the bare MPM step inside a Material (graph mode)."""

    def __init__(self, tau: torch.Tensor):
        super().__init__()
        self.register_buffer("tau", tau)

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        return self.tau


def throughput(n: int, n_grid: int, steps: int, device: torch.device, dtype: str, repeats: int = 3,
               law: str = "none", graph: bool = False, steps_per_frame: int = 10, order: str = "random",
               fuse: bool = True, block: bool | None = None) -> dict:
    """Forward and forward+backward particle-steps per second (best of ``repeats``).

    ``law="none"``: the bare step with a fixed stress; otherwise the law is evaluated every step
    (tau = elasticity(F) before, F = plasticity(F_trial) after), as in training. ``graph``: frames
    of ``steps_per_frame`` steps replayed through ``gca.sim.graph`` (CUDA graphs; forward and the
    recompute-backward), as a rollout does on a GPU; otherwise the steps are launched one by one. ``fuse``: graphed
    forward frames of an analytic law take the fused step (``MPMSolver.step_fused``, the default); False: the
    generic step (the law's kernels, then the transfers). ``block``: forward P2G summed per thread block first
    (``MPMSolver.block_p2g``; None: the solver's default, off).
    """
    cfg = SimConfig(n_grid=n_grid, dt=1e-4, dtype=dtype)
    solver = MPMSolver(cfg, device)
    solver.fuse_analytic = fuse
    if block is not None:  # None: the solver's own default (None there would mean "on CUDA")
        solver.block_p2g = block
    x, v, C, F, tau, vol, mass = _state(n, cfg, device, order)
    n = x.shape[0]
    if law == "none":
        material = Material(FixedStress(tau), IdentityPlasticity(), RHO) if graph else None
    else:
        material = make_material(law, device, cfg.torch_dtype)
    runner = solver.frame_graphs(material, steps_per_frame, n) if graph else None
    if runner is not None:
        runner.bind(vol, mass)
        steps = steps_per_frame * max(1, steps // steps_per_frame)

    def chain(grad: bool):
        ins = [t.clone().requires_grad_(grad) for t in (x, v, C, F, tau)]
        xs, vs, Cs, Fs = ins[:4]
        if runner is not None:
            for _ in range(steps // steps_per_frame):
                xs, vs, Cs, Fs, _ = graphed_frame(runner, xs, vs, Cs, Fs)
        for _ in range(0 if runner is not None else steps):
            if material is None:
                xs, vs, Cs, Fs = solver.step(xs, vs, Cs, Fs, ins[4], vol, mass)
            else:
                xs, vs, Cs, Ftr = solver.step(xs, vs, Cs, Fs, material.stress(Fs), vol, mass)
                Fs = material.project(Ftr)
        if grad:
            (xs.sum() + vs.sum() + Fs.sum()).backward()
        _sync(device)

    result = {"particles": n, "n_grid": n_grid, "steps": steps, "law": law, "graph": graph, "order": order, "fuse": fuse,
              "block": solver.blocks_p2g, "captured": bool(runner is not None and runner.capture)}
    for name, grad in (("fwd", False), ("fwd_bwd", True)):
        with torch.set_grad_enabled(grad):
            chain(grad)  # warm-up: kernel compile/load, allocator
            seconds = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                chain(grad)
                seconds = min(seconds, time.perf_counter() - t0)
        result[f"{name}_ms_per_step"] = 1e3 * seconds / steps
        result[f"{name}_particle_steps_per_s"] = n * steps / seconds
    return result


def rollout_memory(n: int, n_steps: int, steps_per_frame: int, n_grid: int, device, dtype, checkpoint,
                   law: str = "corotated", graph: bool = False) -> dict:
    """Peak memory and time of forward + backward through a rollout (corotated or LoRA-neural law)."""
    cfg = SimConfig(n_grid=n_grid, dt=2e-4, dtype=dtype)
    solver = MPMSolver(cfg, device)
    x, vol, mass = block(n, cfg, device)
    material = make_material("corotated" if law == "none" else law, device, cfg.torch_dtype)
    params = [p for p in material.parameters() if p.requires_grad]
    v0 = torch.zeros_like(x).requires_grad_()
    c = 12.0  # wave speed for the CFL check [m/s] (the neural law's numerical estimate is not needed here)
    warm = rollout(solver, material, x[:8], v0[:8], vol[:8], mass[:8], steps_per_frame, steps_per_frame,
                   checkpoint=checkpoint, wave_speed=c, graph=False)  # one-off costs: kernel load, imports
    warm.x.sum().backward()
    material.zero_grad()
    v0.grad = None
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    out = rollout(solver, material, x, v0, vol, mass, n_steps, steps_per_frame, checkpoint=checkpoint, wave_speed=c,
                  graph=graph)
    (out.x[1:] ** 2).sum().backward()
    _sync(device)
    seconds = time.perf_counter() - t0  # with graph: includes the one-off capture
    peak = (torch.cuda.max_memory_allocated(device) if device.type == "cuda"
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    return {"particles": n, "n_grid": n_grid, "steps": n_steps, "steps_per_frame": steps_per_frame,
            "checkpoint": checkpoint, "graph": graph, "seconds": seconds, "peak_bytes": int(peak),
            "peak_kind": "cuda_max_memory_allocated" if device.type == "cuda" else "process_max_rss",
            "law": law, "grad_finite": bool(torch.isfinite(v0.grad).all()),
            "grad_norm_law": float(sum(p.grad.norm() ** 2 for p in params if p.grad is not None) ** 0.5)}


def _parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--sizes", nargs="+", default=["10000:32", "100000:32", "10000:64", "100000:64"],
                   help="particles:n_grid pairs")
    p.add_argument("--steps", type=int, default=50, help="timed steps per configuration")
    p.add_argument("--repeats", type=int, default=3, help="timed chains per configuration (best is kept)")
    p.add_argument("--rollout-particles", type=int, default=30000)
    p.add_argument("--rollout-steps", type=int, default=400)
    p.add_argument("--steps-per-frame", type=int, default=10)
    p.add_argument("--rollout-grid", type=int, default=32)
    p.add_argument("--no-checkpoint", action="store_true", help="also measure the rollout without checkpoints")
    p.add_argument("--skip-rollout", action="store_true")
    p.add_argument("--law", nargs="+", default=["none"], choices=["none", "corotated", "neural", "neural_ref",
                                                                     "neo_hookean", "neo_hookean_ref"],
                   help="law evaluated each step in the throughput chains (none: fixed stress)")
    p.add_argument("--rollout-law", default="corotated", choices=["corotated", "neural"])
    p.add_argument("--graph", nargs="+", default=["off"], choices=["off", "on"],
                   help="step launches one by one (off) and/or frames replayed from CUDA graphs (on)")
    p.add_argument("--json", default=None, help="output path (default benchmarks/results/sim_<device>.json)")
    p.add_argument("--fuse", nargs="+", default=["on"], choices=["on", "off"],
                   help="graphed forward frames of an analytic law: fused step (on) and/or generic step (off)")
    p.add_argument("--block", nargs="+", default=["auto"], choices=["auto", "on", "off"],
                   help="forward P2G summed per thread block first (on), per particle (off), the solver's default (auto)")
    p.add_argument("--order", nargs="+", default=["random"], choices=["random", "lattice"],
                   help="particle orders of the block (throughput rows; each one side by side)")
    return p.parse_args(argv)


def _table(results: dict) -> str:
    lines = ["| law | graph | fuse | block P2G | order | particles | grid | fwd ms/step | fwd Mparticle-steps/s | "
             "fwd+bwd ms/step | fwd+bwd Mparticle-steps/s |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results["throughput"]:
        lines.append(f"| {r['law']} | {'on' if r.get('captured') else 'twin' if r.get('graph') else 'off'} | "
                     f"{'on' if r.get('fuse', True) else 'off'} | {'on' if r.get('block') else 'off'} | "
                     f"{r.get('order', 'random')} | "
                     f"{r['particles']} | {r['n_grid']}^3 | {r['fwd_ms_per_step']:.2f} | "
                     f"{r['fwd_particle_steps_per_s'] / 1e6:.3f} | {r['fwd_bwd_ms_per_step']:.2f} | "
                     f"{r['fwd_bwd_particle_steps_per_s'] / 1e6:.3f} |")
    for r in results["rollout"]:
        lines.append(f"rollout ({r['law']}) {r['particles']} p x {r['steps']} steps ({r['n_grid']}^3, checkpoint="
                     f"{r['checkpoint']}, graph={r.get('graph', False)}): {r['seconds']:.1f} s fwd+bwd, peak {r['peak_bytes'] / 2**30:.2f} GiB "
                     f"({r['peak_kind']})")
    return "\n".join(lines)


def main(argv=None) -> dict:
    args = _parse(argv)
    wp.config.quiet = True
    device = torch.device(args.device)
    results = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor()
               or "cpu", "warp": wp.__version__, "torch": torch.__version__, "dtype": args.dtype,
               "throughput": [], "rollout": []}
    graphs = [g == "on" for g in args.graph]
    for law in args.law:
        for spec in args.sizes:
            for graph in graphs:  # side by side in one run
                n, n_grid = (int(s) for s in spec.split(":"))
                for order in args.order:
                    for fuse in [f == "on" for f in args.fuse]:
                        for block in [{"auto": None, "on": True, "off": False}[b] for b in args.block]:
                            results["throughput"].append(throughput(n, n_grid, args.steps, device, args.dtype,
                                                                    args.repeats, law, graph, args.steps_per_frame,
                                                                    order, fuse, block))
                            print(results["throughput"][-1], flush=True)
    if not args.skip_rollout:
        for checkpoint in (True, False) if args.no_checkpoint else (True,):
            for graph in graphs:
                results["rollout"].append(rollout_memory(args.rollout_particles, args.rollout_steps,
                                                         args.steps_per_frame, args.rollout_grid, device, args.dtype,
                                                         checkpoint, args.rollout_law, graph))
                print(results["rollout"][-1], flush=True)
    print(_table(results))
    out = Path(args.json or f"benchmarks/results/sim_{device.type}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(f"wrote {out}")
    return results


if __name__ == "__main__":
    main()
