"""The neural law's MLP in torch's products, in the warp tile kernel and as simt's forward (``gca.laws.mlp_kernel``),
side by side.

Issue 20, session 34: in a swept paper-profile GCA iteration on the ball (0.77 s of CUDA kernels, session 33) the
neural law's MLP (13 -> 64 -> 64 -> 9, GELU, N ~ 30k particles, twice per MPM step: plasticity and elasticity) is ~210
ms of FP32 products plus ~100 ms of activations and copies. TF32 did not speed it (session 34: the products are small
and memory-bound). The tile kernel keeps a block's activations on chip; simt keeps a particle's in registers. Per
size and variant, per call [us]:

- ``mlp fwd`` / ``mlp fwd+bwd``: the MLP alone; the forward under ``torch.no_grad()`` as the simulation's forward runs
  it (simt then stores no pre-activations), the backward: the input gradient and the three weight gradients;
- ``law fwd+bwd``: one MPM step's law calls (plasticity, then elasticity on its output), NCLaw-shaped networks with
  LoRA r = 16 merged once as a frame merges them, features + MLP + head, gradient to F and the merged weights, with
  the MLP in torch, ``simt`` and the tile kernel (``warp``);

each captured in one CUDA graph and replayed (what training does: ``gca.sim.graph``), so launch overheads count as
they do there; on the CPU, eager calls. Variants: ``torch`` (nn.Sequential, FP32 products), ``torch_tf32`` (the same
with TF32 products, ``train.matmul_precision`` high: session 33's TF32 bench timed eager calls, bound by the host's
launches, so it could not see what TF32 does to the kernels), ``simt`` (the forward one
thread per particle, torch's backward from the stored pre-activations: ``gca.laws.mlp_kernel.simt_mlp``), ``t<k>`` (the tile kernel,
k particles per block, cuBLASDx products: minutes to compile), ``t<k>s`` (warp's scalar tile product, the
kernel's default). Each row also gives the largest
deviation of X and of the gradients from a float64 evaluation, relative to the largest value, and the tile
kernel's own float64 build against torch's float64 (a correctness check of the device's build).

Usage::

    python benchmarks/bench_mlp.py --device cuda --json out.json
    python benchmarks/bench_mlp.py --device cpu --sizes 300 --variants torch t16 --iters 2 --repeats 1   # smoke
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gca.efficiency import best_time_us  # noqa: E402
from gca.laws import mlp_kernel as mk  # noqa: E402
from gca.laws.lora import apply_lora, lora_layers  # noqa: E402
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity, make_mlp  # noqa: E402
from gca.train.loop import matmul_precision  # noqa: E402

VARIANT = re.compile(r"^(torch|torch_tf32|simt|t(\d+)(s?))$")


def timed_us(fn, device: torch.device, iters: int, repeats: int) -> float:
    """Per call [us]: on CUDA ``fn`` captured once in a CUDA graph (after warm-up on a side stream) and the graph
    replayed; on the CPU ``fn`` itself (:func:`gca.efficiency.best_time_us`, warm-up excluded)."""
    return best_time_us(captured(fn, device), device, iters, repeats)


def captured(fn, device: torch.device):
    """On CUDA: ``fn`` warmed up on a side stream, captured once in a CUDA graph; returns the graph's replay. On the
    CPU: ``fn`` itself."""
    if device.type != "cuda":
        return fn
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):
        for _ in range(3):
            fn()
    torch.cuda.current_stream(device).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        fn()
    return graph.replay


def features(n: int, device, dtype, seed: int = 0) -> torch.Tensor:
    """z [n, 13] at the scale of strains of a few percent (what the law sees in a deforming object)."""
    g = torch.Generator().manual_seed(seed)
    return (0.05 * torch.randn(n, 13, generator=g, dtype=torch.float64)).to(device=device, dtype=dtype)


def run_mlp(variant: str, z: torch.Tensor, Ws: list[torch.Tensor], net: torch.nn.Sequential) -> torch.Tensor:
    m = VARIANT.match(variant)
    if m.group(1).startswith("torch"):  # torch_tf32: the same call, inside mlp_row's TF32 block
        return net(z)
    if m.group(1) == "simt":
        return mk.simt_mlp(z, Ws, mk.shape_of(net), net[1])
    return mk.mlp(z, Ws, mk.shape_of(net), tile=int(m.group(2)), mathdx=not m.group(3))


def mlp_row(variant: str, n: int, device, iters: int, repeats: int) -> dict:
    """The MLP alone: time forward and forward + backward; deviations from float64 (``torch_tf32``: torch's products
    at ``train.matmul_precision`` high, TF32 on CUDA, captured and replayed as training would)."""
    with matmul_precision("high" if variant == "torch_tf32" else "highest"):
        return _mlp_row(variant, n, device, iters, repeats)


def _no_grad(fn):
    """``fn`` called under ``torch.no_grad()`` (the simulation's forward pass)."""
    def call():
        with torch.no_grad():
            return fn()
    return call


def mlp_calls(variant: str, n: int, device, run=None):
    """The MLP of ``variant`` on n particles' features: (fwd, both, net64, net, z, v): ``fwd()`` its output, ``both()``
    the gradients of <output, v> w.r.t. z and the three weights (seeded; net64 the float64 twin of net). ``run(z, Ws,
    net)``: another forward of the same network in place of ``variant``'s (the fused Triton MLP's)."""
    torch.manual_seed(0)
    net64 = make_mlp(NeuralLawConfig()).double().to(device)
    net = make_mlp(NeuralLawConfig()).to(device)
    net.load_state_dict({k: v.float() for k, v in net64.state_dict().items()})
    z = features(n, device, torch.float32).requires_grad_(True)
    Ws = [net[i].weight for i in (0, 2, 4)]
    v = torch.randn(n, 9, device=device, generator=torch.Generator(device).manual_seed(1))
    run = run or (lambda z, Ws, net: run_mlp(variant, z, Ws, net))
    fwd = lambda: run(z, Ws, net)  # noqa: E731
    both = lambda: torch.autograd.grad(fwd(), [z, *Ws], v)  # noqa: E731
    return fwd, both, net64, net, z, v


def _mlp_row(variant: str, n: int, device, iters: int, repeats: int) -> dict:
    fwd, both, net64, net, z, v = mlp_calls(variant, n, device)
    Ws = [net[i].weight for i in (0, 2, 4)]
    leaves = [z, *Ws]
    row = {"variant": variant, "particles": n, "mlp_fwd_us": timed_us(_no_grad(fwd), device, iters, repeats),
           "mlp_fwd_bwd_us": timed_us(both, device, iters, repeats)}
    z64 = z.detach().double().requires_grad_(True)
    W64 = [net64[i].weight for i in (0, 2, 4)]
    X64 = net64(z64)
    g64 = torch.autograd.grad(X64, [z64, *W64], v.double())
    X = fwd()
    g = torch.autograd.grad(X, leaves, v)
    rel = lambda a, b: float((a.double() - b).abs().max() / b.abs().max())  # noqa: E731
    row["X_rel_dev"] = rel(X.detach(), X64.detach())
    row["grad_rel_dev"] = max(rel(a, b) for a, b in zip(g, g64))
    if not variant.startswith("torch") and (variant.endswith("s") or variant == "simt" or device.type == "cpu"):  # f64
        # (scalar products only on CUDA: cuBLASDx compiled one float32 module for 281 s on the H100, session 34)
        W64l = [W.detach().requires_grad_(True) for W in W64]
        X = run_mlp(variant, z64, W64l, net64)
        g = torch.autograd.grad(X, [z64, *W64l], v.double())
        row["f64_rel_dev"] = max(rel(X.detach(), X64.detach()), *(rel(a, b) for a, b in zip(g, g64)))
    return row


def law_row(kind: str, n: int, device, iters: int, repeats: int) -> dict:
    """One step's law calls (plasticity, then elasticity) with LoRA merged as a frame merges it, forward + backward,
    the MLP on ``kind``: torch, simt or the tile kernel (``warp``)."""
    return {"variant": kind, "particles": n, "law_fwd_bwd_us": timed_us(law_step(kind, n, device), device, iters,
                                                                        repeats)}


def law_step(kind: str, n: int, device):
    """:func:`law_row`'s call: ``step()`` gives the gradients of one step's law calls on n particles (seeded)."""
    torch.manual_seed(0)
    nets = [NeuralPlasticity(NeuralLawConfig()), NeuralElasticity(NeuralLawConfig())]
    leaves = []
    for net in nets:
        apply_lora(net, 16, 16.0)
        net.to(device).mlp_kernel = kind
        for layer in lora_layers(net):
            layer._merged = (layer.weight + 1e-2 * torch.randn_like(layer.weight)).detach().requires_grad_(True)
            leaves.append(layer._merged)
    g = torch.Generator().manual_seed(2)
    F = (torch.eye(3, dtype=torch.float64) + 0.03 * torch.randn(n, 3, 3, generator=g, dtype=torch.float64))
    F = F.float().to(device).requires_grad_(True)
    v = torch.randn(n, 3, 3, device=device, generator=torch.Generator(device).manual_seed(3))
    return lambda: torch.autograd.grad(nets[1](nets[0](F)), [F, *leaves], v)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[30000, 100000], help="particle counts")
    ap.add_argument("--variants", nargs="+", default=["torch", "torch_tf32", "simt", "t16s"])  # t<k>: cuBLASDx compiles for minutes
    ap.add_argument("--iters", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    bad = [v for v in args.variants if not VARIANT.match(v)]
    if bad:
        ap.error(f"variants must be torch, torch_tf32, simt, t<k> or t<k>s, got {bad}")
    device = torch.device(args.device)
    out = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu", "mlp": [], "law": []}
    print("| particles | variant | mlp fwd us | mlp fwd+bwd us | X rel dev | grad rel dev | float64 rel dev |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for n in args.sizes:
        for variant in args.variants:
            try:
                row = mlp_row(variant, n, device, args.iters, args.repeats)
            except Exception as exc:  # a variant that cannot build here (shared memory) is reported, not fatal
                row = {"variant": variant, "particles": n, "error": f"{type(exc).__name__}: {exc}"[:300]}
                print(f"| {n} | {variant} | failed: {row['error']} | | | | |", flush=True)
            else:
                print(f"| {n} | {variant} | {row['mlp_fwd_us']:.1f} | {row['mlp_fwd_bwd_us']:.1f} | "
                      f"{row['X_rel_dev']:.1e} | {row['grad_rel_dev']:.1e} | {row.get('f64_rel_dev', float('nan')):.1e} |",
                      flush=True)
            out["mlp"].append(row)
    print("| particles | law step (plasticity + elasticity) | fwd+bwd us |\n| --- | --- | --- |")
    for n in args.sizes:
        for kind in ("torch", "simt", "warp"):
            row = law_row(kind, n, device, args.iters, args.repeats)
            out["law"].append(row)
            print(f"| {n} | MLP in {kind} | {row['law_fwd_bwd_us']:.1f} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
