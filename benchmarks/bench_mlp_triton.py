"""Issue 20, session 35: a probe before anything is built on it. Does the neural laws' MLP (``make_mlp``: 13 -> 64 ->
64 -> 9, GELU, bias-free) run faster as ONE fused Triton kernel, a block of particles per program with its
activations on chip, than as torch's three cuBLAS products and two GELU kernels?

Sessions 34-35 measured every warp form slower than torch (forward at 30k particles on an H100: torch 34.5 us, tile
kernel 55-76, simt 165.7): warp's scalar tile product reads both operands from shared memory for every multiply-add,
and simt's accumulators did not stay in registers. Triton's dot keeps a per-thread register tile (each operand loaded
once feeds several multiply-adds), and ``input_precision="ieee"`` keeps FP32 products (no TF32), so the law stays the
same to rounding. Session 35 measured the forward alone (47.7 us against torch's 34.7 at 30k: slower when timed
alone). Session 36 added the backward (:class:`FusedMLP`: one persistent launch recomputes the forward on chip and
gives dx and the three weight gradients, summed per program in registers and stored as partials that torch sums in a
fixed order), because a packed grid is bound by the GPU's throughput, where bytes count more than one call's latency
(``bench_mlp_packed.py`` times both ways). A benchmark probe, not a training path: triton is no CI dependency, and
its tests run in Triton's CPU interpreter where triton is installed (``tests/test_bench_mlp_triton.py``: float64 equal
to torch's autograd to 1e-12, a gradcheck, a transposed weight caught).

Per size and variant, per call [us] (CUDA: captured in one CUDA graph and replayed, as ``bench_mlp.py`` times;
CPU: Triton's interpreter, ``TRITON_INTERPRET=1``, a correctness smoke only): the forward (no gradient) and the
forward + backward, and the largest deviations of the output and the gradients from float64 relative to the largest
value. Variants: ``torch`` (nn.Sequential, FP32), ``ieee_<B>`` (fused, FP32 products, B particles per program),
``tf32_<B>`` (fused, TF32 products: a precision change, shown for scale only).

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
    """``net(x)`` for a float32 two-hidden-layer bias-free GELU ``make_mlp`` network, as one Triton launch, no
    gradient (:func:`fused_mlp` under no_grad). x: [N, 13] (made float32); returns [N, 9]."""
    with torch.no_grad():
        return fused_mlp(net, x.float(), block, precision)


@triton.jit
def _gelu_grad(x):
    """d/dx of x Phi(x): Phi(x) + x phi(x)."""
    return 0.5 * (1.0 + tl.math.erf(x * 0.7071067811865476)) + x * 0.3989422804014327 * tl.exp(-0.5 * x * x)


@triton.jit
def _fused_mlp_bwd(x_ptr, g_ptr, w1_ptr, w2_ptr, w3_ptr, dx_ptr, dw1_ptr, dw2_ptr, dw3_ptr, n, n_programs,
                   K_IN: tl.constexpr, K_PAD: tl.constexpr, H: tl.constexpr, N_OUT: tl.constexpr,
                   OUT_PAD: tl.constexpr, BLOCK: tl.constexpr, PRECISION: tl.constexpr,
                   PER_PROGRAM: tl.constexpr):
    """One persistent program: for its PER_PROGRAM tiles (pid, pid + n_programs, ...) of BLOCK particles, the forward
    recomputed on chip, then the backward of out = W3 gelu(W2 gelu(W1 x)) for the output cotangent g: dx stored per
    particle; the weight gradients summed over the program's tiles in registers and stored once as this program's
    partial (dw*_ptr[pid]; the caller sums the partials in a fixed order: no atomics, deterministic). PER_PROGRAM is a
    compile-time count (Triton's interpreter cannot loop to a runtime bound); the caller sizes the grid so that fewer
    than PER_PROGRAM iterations of all programs fall past the last tile."""
    pid = tl.program_id(0)
    k = tl.arange(0, K_PAD)
    h = tl.arange(0, H)
    o = tl.arange(0, OUT_PAD)
    w1 = tl.load(w1_ptr + h[:, None] * K_IN + k[None, :], mask=k[None, :] < K_IN, other=0.0)  # [H, K_PAD]
    w2 = tl.load(w2_ptr + h[:, None] * H + h[None, :])  # [H, H]
    w3 = tl.load(w3_ptr + o[:, None] * H + h[None, :], mask=o[:, None] < N_OUT, other=0.0)  # [OUT_PAD, H]
    dw1 = tl.zeros((H, K_PAD), dtype=w1.dtype)
    dw2 = tl.zeros((H, H), dtype=w1.dtype)
    dw3 = tl.zeros((OUT_PAD, H), dtype=w1.dtype)
    for i in range(0, PER_PROGRAM):  # tile pid + i programs (past the last tile: every row masked)
        rows = (pid + i * n_programs) * BLOCK + tl.arange(0, BLOCK)
        live = rows < n
        x = tl.load(x_ptr + rows[:, None] * K_IN + k[None, :], mask=live[:, None] & (k[None, :] < K_IN), other=0.0)
        g = tl.load(g_ptr + rows[:, None] * N_OUT + o[None, :], mask=live[:, None] & (o[None, :] < N_OUT), other=0.0)
        h1 = tl.dot(x, tl.trans(w1), input_precision=PRECISION)  # [BLOCK, H]
        a1 = _gelu(h1)
        h2 = tl.dot(a1, tl.trans(w2), input_precision=PRECISION)
        a2 = _gelu(h2)
        dw3 += tl.dot(tl.trans(g), a2, input_precision=PRECISION)  # [OUT_PAD, H]
        d2 = tl.dot(g, w3, input_precision=PRECISION) * _gelu_grad(h2)  # [BLOCK, H]
        dw2 += tl.dot(tl.trans(d2), a1, input_precision=PRECISION)
        d1 = tl.dot(d2, w2, input_precision=PRECISION) * _gelu_grad(h1)
        dw1 += tl.dot(tl.trans(d1), x, input_precision=PRECISION)  # [H, K_PAD]
        dx = tl.dot(d1, w1, input_precision=PRECISION)  # [BLOCK, K_PAD]
        tl.store(dx_ptr + rows[:, None] * K_IN + k[None, :], dx, mask=live[:, None] & (k[None, :] < K_IN))
    tl.store(dw1_ptr + pid * H * K_IN + h[:, None] * K_IN + k[None, :], dw1, mask=k[None, :] < K_IN)
    tl.store(dw2_ptr + pid * H * H + h[:, None] * H + h[None, :], dw2)
    tl.store(dw3_ptr + pid * N_OUT * H + o[:, None] * H + h[None, :], dw3, mask=o[:, None] < N_OUT)


def _weights(net: torch.nn.Sequential) -> list[torch.nn.Linear]:
    """The three bias-free layers of a two-hidden-layer exact-GELU ``make_mlp`` network (anything else refused)."""
    acts = [m for m in net if not isinstance(m, torch.nn.Linear)]
    if len(acts) != 2 or any(not isinstance(a, torch.nn.GELU) or a.approximate != "none" for a in acts):
        raise ValueError(f"fused MLP: two exact GELUs expected (the kernels compute x Phi(x)), got {acts}")
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    if any(m.bias is not None for m in linears):
        raise ValueError("fused MLP: bias-free layers (make_mlp's) expected")
    w1, w2, w3 = (m.weight for m in linears)
    if w2.shape[0] != w2.shape[1] or w1.shape[0] != w2.shape[0] or w3.shape[1] != w2.shape[0]:
        raise ValueError(f"fused MLP: two equal hidden layers expected, got {w1.shape}, {w2.shape}, {w3.shape}")
    if w2.shape[0] < 16 or w2.shape[0] & (w2.shape[0] - 1):
        raise ValueError(f"fused MLP: a hidden width that is a power of two >= 16 expected (tl.dot), got {w2.shape[0]}")
    return linears


def _pad(v: int) -> int:
    """A dimension padded for tl.dot: a power of two, at least 16."""
    return max(16, triton.next_power_of_2(v))


BWD_WARPS = 8  # the backward holds three weight-gradient accumulators ([64, 64] the largest) and six [BLOCK, 64]
# activations per program: 8 warps (256 threads) halve the registers each thread holds against Triton's default 4


class FusedMLP(torch.autograd.Function):
    """out = W3 gelu(W2 gelu(W1 x)) for x [N, K_IN] and weights [H, K_IN], [H, H], [N_OUT, H] (torch's layout): the
    forward one launch with nothing stored but the inputs; the backward one persistent launch that recomputes the
    forward on chip and gives dx and the three weight gradients (partials per program summed by torch). float32
    (``precision`` ieee or tf32) or float64 (ieee: the CPU interpreter's gradcheck)."""

    @staticmethod
    def forward(ctx, x, w1, w2, w3, block: int, precision: str, programs: int):
        ctx.save_for_backward(x, w1, w2, w3)
        ctx.cfg = (block, precision, programs)
        out = torch.empty(x.shape[0], w3.shape[0], device=x.device, dtype=x.dtype)
        _fused_mlp_fwd[(triton.cdiv(x.shape[0], block),)](x, w1, w2, w3, out, x.shape[0], K_IN=x.shape[1],
                                                         K_PAD=_pad(x.shape[1]), H=w2.shape[0], N_OUT=w3.shape[0],
                                                         OUT_PAD=_pad(w3.shape[0]), BLOCK=block, PRECISION=precision)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        x, w1, w2, w3 = ctx.saved_tensors
        block, precision, programs = ctx.cfg
        n, tiles = x.shape[0], triton.cdiv(x.shape[0], block)
        per = triton.cdiv(tiles, max(1, programs))  # tiles per program: the grid then wastes < per tile iterations
        p = max(1, triton.cdiv(tiles, per))
        dx = torch.empty_like(x)
        parts = [torch.empty(p, *w.shape, device=x.device, dtype=x.dtype) for w in (w1, w2, w3)]
        _fused_mlp_bwd[(p,)](x, g.contiguous(), w1, w2, w3, dx, *parts, n, p, K_IN=x.shape[1],
                             K_PAD=_pad(x.shape[1]), H=w2.shape[0], N_OUT=w3.shape[0], OUT_PAD=_pad(w3.shape[0]),
                             BLOCK=block, PRECISION=precision, PER_PROGRAM=per,
                             num_warps=BWD_WARPS)
        return (dx, *(part.sum(0) for part in parts), None, None, None)


def fused_mlp(net: torch.nn.Sequential, x: torch.Tensor, block: int = 32, precision: str = "ieee",
              programs: int = 4 * 132) -> torch.Tensor:
    """``net(x)`` with gradients to x and the three weights through :class:`FusedMLP` (block >= 16; ``programs``: the
    backward's persistent programs, default 4 per SM of an H100)."""
    if block < 16:
        raise ValueError("fused MLP: block >= 16 (tl.dot) expected")
    w1, w2, w3 = (m.weight for m in _weights(net))
    if x.dtype not in (torch.float32, torch.float64) or any(w.dtype != x.dtype for w in (w1, w2, w3)):
        raise ValueError(f"fused MLP: float32 or float64 input and weights alike expected, got {x.dtype}, {w1.dtype}")
    return FusedMLP.apply(x.contiguous(), w1.contiguous(), w2.contiguous(), w3.contiguous(), block, precision,
                          programs)


def rows(device: torch.device, sizes: list[int], variants: list[str], iters: int, repeats: int) -> list[dict]:
    """Per size and variant: the forward (no gradient) and the forward + backward (the gradients w.r.t. x and the
    three weights of <out, v>) per call [us], and their largest deviations from float64 relative to the largest
    value."""
    torch.manual_seed(0)
    net64 = make_mlp(NeuralLawConfig()).double().to(device)
    net = make_mlp(NeuralLawConfig()).to(device)
    net.load_state_dict({k: v.float() for k, v in net64.state_dict().items()})
    W64 = [m.weight for m in _weights(net64)]
    Ws = [m.weight for m in _weights(net)]
    out = []
    for n in sizes:
        x64 = torch.randn(n, 13, dtype=torch.float64, device=device).requires_grad_(True)
        x = x64.detach().float().contiguous().requires_grad_(True)
        v64 = torch.randn(n, 9, dtype=torch.float64, device=device)
        ref = net64(x64)
        gref = torch.autograd.grad(ref, [x64, *W64], v64)
        for name in variants:
            m = VARIANT.match(name)
            if m is None:
                raise SystemExit(f"bench_mlp_triton.py: unknown variant {name!r} (torch, ieee_<B>, tf32_<B>)")
            if name == "torch":
                fn = lambda: net(x)  # noqa: E731
            else:
                fn = lambda p=m.group(2), b=int(m.group(3)): fused_mlp(net, x, b, p)  # noqa: E731
            both = lambda: torch.autograd.grad(fn(), [x, *Ws], v64.float())  # noqa: E731
            rel = lambda a, b: float((a.double() - b).abs().max() / b.abs().max())  # noqa: E731
            with torch.no_grad():
                dev = rel(fn(), ref.detach())
                us = timed_us(fn, device, iters, repeats)
            gdev = max(rel(a, b) for a, b in zip(both(), gref))
            us_both = timed_us(both, device, iters, repeats)
            out.append({"particles": n, "variant": name, "fwd_us": us, "fwd_bwd_us": us_both, "rel_dev": dev,
                        "grad_rel_dev": gdev})
            print(f"| {n} | {name} | {us:.1f} | {us_both:.1f} | {dev:.1e} | {gdev:.1e} |", flush=True)
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
    print("| particles | variant | fwd us | fwd+bwd us | rel dev from float64 | grad rel dev |\n"
          "| --- | --- | --- | --- | --- | --- |", flush=True)
    res = rows(device, args.sizes, args.variants, args.iters, args.repeats)
    if args.json:
        name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
        args.json.write_text(json.dumps({"device": name, "rows": res}, indent=1))
    return res


if __name__ == "__main__":
    main()
