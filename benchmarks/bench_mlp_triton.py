"""Issue 20, session 35: a probe before anything is built on it. Does the neural laws' MLP (``make_mlp``: 13 -> 64 ->
64 -> 9, GELU, bias-free) run faster as ONE fused Triton kernel, a block of particles per program with its
activations on chip, than as torch's three cuBLAS products and two GELU kernels?

Sessions 34-35 measured every warp form slower than torch (forward at 30k particles on an H100: torch 34.5 us, tile
kernel 55-76, simt 165.7): warp's scalar tile product reads both operands from shared memory for every multiply-add,
and simt's accumulators did not stay in registers. Triton's dot keeps a per-thread register tile (each operand loaded
once feeds several multiply-adds), and ``input_precision="ieee"`` keeps FP32 products (no TF32), so the law stays the
same to rounding. Forward only: the simulation's no-gradient forward and the frame recompute's forward are half of
the MLP's calls; a fused backward is worth building only if this forward wins clearly.

Per size and variant, per call [us] (CUDA: captured in one CUDA graph and replayed, as ``bench_mlp.py`` times;
CPU: Triton's interpreter, ``TRITON_INTERPRET=1``, a correctness smoke only), and the largest deviation of the output
from a float64 evaluation relative to the largest value. Variants: ``torch`` (nn.Sequential, FP32), ``ieee_<B>``
(fused, FP32 products, B particles per program), ``tf32_<B>`` (fused, TF32 products: a precision change, shown for
scale only).

Usage::

    python benchmarks/bench_mlp_triton.py --device cuda --json out.json
    python benchmarks/bench_mlp_triton.py --device cpu --sizes 200 --variants torch ieee_32 --iters 1 --repeats 1
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
if "--device" in sys.argv and sys.argv[sys.argv.index("--device") + 1] == "cpu":
    os.environ.setdefault("TRITON_INTERPRET", "1")  # read when the kernel is decorated: before triton's import
import triton  # noqa: E402
import triton.language as tl  # noqa: E402

from bench_mlp import timed_us  # noqa: E402
from gca.laws.neural import NeuralLawConfig, make_mlp  # noqa: E402

VARIANT = re.compile(r"^(torch|(ieee|tf32)_(\d+))$")


@triton.jit
def _gelu(x):
    """Exact GELU, x Phi(x) (torch's default ``nn.GELU()``)."""
    return 0.5 * x * (1.0 + tl.math.erf(x * 0.7071067811865476))


@triton.jit
def _fused_mlp_fwd(x_ptr, w1_ptr, w2_ptr, w3_ptr, out_ptr, n, K_IN: tl.constexpr, K_PAD: tl.constexpr,
                   H: tl.constexpr, N_OUT: tl.constexpr, OUT_PAD: tl.constexpr, BLOCK: tl.constexpr,
                   PRECISION: tl.constexpr):
    """One program: BLOCK particles' rows of out = W3 gelu(W2 gelu(W1 x)) (torch's weight layouts [out, in]); the
    inputs padded K_IN -> K_PAD and the outputs N_OUT -> OUT_PAD with zeros (tl.dot needs 16)."""
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = rows < n
    k = tl.arange(0, K_PAD)
    h = tl.arange(0, H)
    o = tl.arange(0, OUT_PAD)
    x = tl.load(x_ptr + rows[:, None] * K_IN + k[None, :], mask=live[:, None] & (k[None, :] < K_IN), other=0.0)
    w1t = tl.load(w1_ptr + h[None, :] * K_IN + k[:, None], mask=k[:, None] < K_IN, other=0.0)  # [K_PAD, H]
    a = _gelu(tl.dot(x, w1t, input_precision=PRECISION))
    w2t = tl.load(w2_ptr + h[None, :] * H + h[:, None])  # [H, H]
    a = _gelu(tl.dot(a, w2t, input_precision=PRECISION))
    w3t = tl.load(w3_ptr + o[None, :] * H + h[:, None], mask=o[None, :] < N_OUT, other=0.0)  # [H, OUT_PAD]
    y = tl.dot(a, w3t, input_precision=PRECISION)
    tl.store(out_ptr + rows[:, None] * N_OUT + o[None, :], y, mask=live[:, None] & (o[None, :] < N_OUT))


def fused_forward(net: torch.nn.Sequential, x: torch.Tensor, block: int, precision: str = "ieee") -> torch.Tensor:
    """``net(x)`` for a two-hidden-layer bias-free GELU ``make_mlp`` network, as one Triton launch. x: [N, 13] float32
    (contiguous); returns [N, 9]."""
    acts = [m for m in net if not isinstance(m, torch.nn.Linear)]
    if len(acts) != 2 or any(not isinstance(a, torch.nn.GELU) or a.approximate != "none" for a in acts):
        raise ValueError(f"fused_forward: two exact GELUs expected (the kernel computes x Phi(x)), got {acts}")
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    if any(m.bias is not None for m in linears) or block < 16:
        raise ValueError("fused_forward: bias-free layers (make_mlp's) and block >= 16 (tl.dot) expected")
    w1, w2, w3 = (m.weight.detach().float().contiguous() for m in linears)
    x = x.float().contiguous()
    if w2.shape[0] != w2.shape[1] or w1.shape[0] != w2.shape[0] or w3.shape[1] != w2.shape[0]:
        raise ValueError(f"fused_forward: two equal hidden layers expected, got {w1.shape}, {w2.shape}, {w3.shape}")
    n, k_in = x.shape
    out = torch.empty(n, w3.shape[0], device=x.device, dtype=x.dtype)
    pad = lambda v: max(16, triton.next_power_of_2(v))  # noqa: E731
    _fused_mlp_fwd[(triton.cdiv(n, block),)](x, w1, w2, w3, out, n, K_IN=k_in, K_PAD=pad(k_in), H=w2.shape[0],
                                             N_OUT=w3.shape[0], OUT_PAD=pad(w3.shape[0]), BLOCK=block,
                                             PRECISION=precision)
    return out


def rows(device: torch.device, sizes: list[int], variants: list[str], iters: int, repeats: int) -> list[dict]:
    torch.manual_seed(0)
    net64 = make_mlp(NeuralLawConfig()).double().to(device)
    net = make_mlp(NeuralLawConfig()).to(device)
    net.load_state_dict({k: v.float() for k, v in net64.state_dict().items()})
    out = []
    for n in sizes:
        x64 = torch.randn(n, 13, dtype=torch.float64, device=device)
        x = x64.float().contiguous()
        with torch.no_grad():
            ref = net64(x64)
        for v in variants:
            m = VARIANT.match(v)
            if m is None:
                raise SystemExit(f"bench_mlp_triton.py: unknown variant {v!r} (torch, ieee_<B>, tf32_<B>)")
            if v == "torch":
                fn = lambda: net(x)  # noqa: E731
            else:
                fn = lambda p=m.group(2), b=int(m.group(3)): fused_forward(net, x, b, p)  # noqa: E731
            with torch.no_grad():
                y = fn()
                dev = float((y.double() - ref).abs().max() / ref.abs().max())
                us = timed_us(fn, device, iters, repeats)
            out.append({"particles": n, "variant": v, "fwd_us": us, "rel_dev": dev})
            print(f"| {n} | {v} | {us:.1f} | {dev:.1e} |", flush=True)
    return out


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sizes", type=int, nargs="+", default=[30000, 100000])
    ap.add_argument("--variants", nargs="+", default=["torch", "ieee_32", "ieee_64", "ieee_128", "tf32_64"])
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    print("| particles | variant | fwd us | rel dev from float64 |\n| --- | --- | --- | --- |", flush=True)
    res = rows(device, args.sizes, args.variants, args.iters, args.repeats)
    if args.json:
        name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
        args.json.write_text(json.dumps({"device": name, "rows": res}, indent=1))
    return res


if __name__ == "__main__":
    main()
