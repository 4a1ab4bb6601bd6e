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
(``bench_mlp_packed.py`` times both ways). Session 37: the FP32 kernels lose packed too (0.57x), the TF32 ones win
(1.44x forward + backward at 8 processes, H200); the kernels moved into the library (``gca.laws.mlp_triton``, the laws'
``mlp_kernel: triton_tf32``, the paper profile's ``train.mlp_kernel`` since session 44) and this script times them. Tests run in Triton's CPU interpreter
(``tests/test_bench_mlp_triton.py``: float64 equal to torch's autograd to 1e-12, a gradcheck, a transposed weight
caught; ``tests/test_laws_mlp_triton.py``: the laws with the option).

Per size and variant, per call [us] (CUDA: captured in one CUDA graph and replayed, as ``bench_mlp.py`` times;
CPU: Triton's interpreter, ``TRITON_INTERPRET=1``, a correctness smoke only): the forward (no gradient) and the
forward + backward, and the largest deviations of the output and the gradients from float64 relative to the largest
value. Variants: ``torch`` (nn.Sequential, FP32), ``ieee_<B>`` (fused, FP32 products, B particles per program),
``tf32_<B>`` (fused, TF32 products: the option ``train.mlp_kernel: triton_tf32``). A fused variant may name its
backward's launch: ``tf32_128_w8_p1`` = 8 warps per program, 1 program per SM (default the library's, ``_w4_p2`` since
session 39's sweep of the TF32 backward; ``_w8_p4`` before, 76 of its 87 us at 30k, H200, session 37).

Usage::

    python benchmarks/bench_mlp_triton.py --device cuda --json out.json
    python benchmarks/bench_mlp_triton.py --fastest out.json --particles 30000 --top 2   # the sweep's pick
    python benchmarks/bench_mlp_triton.py --device cpu --sizes 200 --variants torch ieee_32 --iters 1 --repeats 1
"""

from __future__ import annotations

import argparse
import contextlib
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

from bench_mlp import timed_us  # noqa: E402
from gca.laws import mlp_triton  # noqa: E402  (after TRITON_INTERPRET is set: read at its import)
from gca.laws.neural import NeuralLawConfig, make_mlp  # noqa: E402

VARIANT = re.compile(r"^(torch|(ieee|tf32)_(\d+)(?:_w(\d+))?(?:_p(\d+))?)$")
SMS = 132  # SMs of an H100 SXM / H200 (an H100 PCIe has 114): the CPU interpreter's count; CUDA reads the device's


def sm_count() -> int:
    """The SMs the backward's programs per SM multiply: the CUDA device's, else ``SMS``."""
    return torch.cuda.get_device_properties(0).multi_processor_count if torch.cuda.is_available() else SMS


def fused_launch(name: str) -> tuple[str, int, int, int] | None:
    """A fused variant's (precision, block, backward warps, backward programs) from its name, ``<ieee|tf32>_<B>``
    with an optional ``_w<W>`` (warps per program, default the library's ``BWD_WARPS``) and ``_p<P>`` (programs per
    SM, default the library's ``BWD_PROGRAMS_PER_SM``); None for a name that is no fused variant (``torch``, or anything else)."""
    m = VARIANT.match(name)
    if m is None or m.group(2) is None:
        return None
    warps = int(m.group(4)) if m.group(4) else mlp_triton.BWD_WARPS
    per_sm = int(m.group(5)) if m.group(5) else mlp_triton.BWD_PROGRAMS_PER_SM
    return m.group(2), int(m.group(3)), warps, per_sm * sm_count()


def fused_forward(net: torch.nn.Sequential, x: torch.Tensor, block: int, precision: str = "ieee") -> torch.Tensor:
    """``net(x)`` for a float32 two-hidden-layer bias-free GELU ``make_mlp`` network, as one Triton launch, no
    gradient (:func:`fused_mlp` under no_grad). x: [N, 13] (made float32); returns [N, 9]."""
    with torch.no_grad():
        return fused_mlp(net, x.float(), block, precision)


def fused_mlp(net: torch.nn.Sequential, x: torch.Tensor, block: int = 32, precision: str = "ieee",
              programs: int | None = None, warps: int = mlp_triton.BWD_WARPS) -> torch.Tensor:
    """``net(x)`` with gradients to x and the three weights through the library's :class:`FusedMLP`
    (``gca.laws.mlp_triton``; block >= 16; ``programs``: the backward's persistent programs, default the library's,
    ``BWD_PROGRAMS_PER_SM`` per SM; ``warps``: the backward's warps per program)."""
    return mlp_triton.mlp(x, [m.weight for m in mlp_triton.check(net)], precision, block, programs, warps)


def variant_call(name: str, net: torch.nn.Sequential):
    """``name``'s MLP as a function of x: ``net`` itself for ``torch``, else the fused MLP with the name's launch."""
    launch = fused_launch(name)
    if name == "torch":
        return net
    if launch is None:
        raise SystemExit(f"bench_mlp_triton.py: unknown variant {name!r} (torch, ieee_<B>, tf32_<B>, optionally "
                         "_w<warps>_p<programs per SM>)")
    precision, block, warps, programs = launch
    return lambda x: fused_mlp(net, x, block, precision, programs, warps)


@contextlib.contextmanager
def backward_launches():
    """Within the block, every launch of the fused backward (``mlp_triton._fused_mlp_bwd``, looked up by
    :class:`FusedMLP` at each call) is recorded as (grid, launch options such as ``num_warps``, the kernel the launch
    returns: CUDA's compiled kernel, or whatever the interpreter returns) in the list yielded; the kernel is put back
    as found after it."""
    launch, seen = mlp_triton._fused_mlp_bwd, []

    class Recording:
        def __getitem__(self, grid):
            def run(*args, **kwargs):
                seen.append((grid, kwargs, launch[grid](*args, **kwargs)))
                return seen[-1][2]
            return run
    mlp_triton._fused_mlp_bwd = Recording()
    try:
        yield seen
    finally:
        mlp_triton._fused_mlp_bwd = launch


def backward_kernel(both) -> dict:
    """What the fused backward compiled to, from one call of ``both`` (a forward + backward through
    :class:`FusedMLP`): registers per thread (``bwd_regs``), spilled registers (``bwd_spills``; Triton's count from
    the loaded binary) and shared memory per program [bytes] (``bwd_shared_bytes``), read off the kernel its launch
    returns. {} where no compiled kernel comes back (torch's MLP; the CPU interpreter)."""
    with backward_launches() as seen:
        both()
    kernel = seen[-1][2] if seen else None
    out = {key: getattr(kernel, attr, None) for key, attr in (("bwd_regs", "n_regs"), ("bwd_spills", "n_spills"))}
    out["bwd_shared_bytes"] = getattr(getattr(kernel, "metadata", None), "shared", None)
    return {k: v for k, v in out.items() if isinstance(v, int)}


def rows(device: torch.device, sizes: list[int], variants: list[str], iters: int, repeats: int,
         on_row=lambda out: None) -> list[dict]:
    """Per size and variant: the forward (no gradient) and the forward + backward (the gradients w.r.t. x and the
    three weights of <out, v>) per call [us], and their largest deviations from float64 relative to the largest
    value. ``on_row(rows so far)`` after each row (the JSON is written then: a sweep cut by its time limit keeps
    what it timed)."""
    torch.manual_seed(0)
    net64 = make_mlp(NeuralLawConfig()).double().to(device)
    net = make_mlp(NeuralLawConfig()).to(device)
    net.load_state_dict({k: v.float() for k, v in net64.state_dict().items()})
    W64 = [m.weight for m in mlp_triton.check(net64)]
    Ws = [m.weight for m in mlp_triton.check(net)]
    out = []
    for n in sizes:
        x64 = torch.randn(n, 13, dtype=torch.float64, device=device).requires_grad_(True)
        x = x64.detach().float().contiguous().requires_grad_(True)
        v64 = torch.randn(n, 9, dtype=torch.float64, device=device)
        ref = net64(x64)
        gref = torch.autograd.grad(ref, [x64, *W64], v64)
        for name in variants:
            fn = lambda call=variant_call(name, net): call(x)  # noqa: E731
            both = lambda: torch.autograd.grad(fn(), [x, *Ws], v64.float())  # noqa: E731
            rel = lambda a, b: float((a.double() - b).abs().max() / b.abs().max())  # noqa: E731
            with torch.no_grad():
                dev = rel(fn(), ref.detach())
                us = timed_us(fn, device, iters, repeats)
            gdev = max(rel(a, b) for a, b in zip(both(), gref))
            compiled = backward_kernel(both)
            us_both = timed_us(both, device, iters, repeats)
            out.append({"particles": n, "variant": name, "fwd_us": us, "fwd_bwd_us": us_both, "rel_dev": dev,
                        "grad_rel_dev": gdev, **compiled})
            on_row(out)
            regs = f"{compiled['bwd_regs']} / {compiled.get('bwd_spills', '?')}" if "bwd_regs" in compiled else "-"
            print(f"| {n} | {name} | {us:.1f} | {us_both:.1f} | {dev:.1e} | {gdev:.1e} | {regs} |", flush=True)
    return out


def fastest(rows_: list[dict], particles: int, top: int, exclude: str = "tf32_64") -> list[str]:
    """The ``top`` fused variants with the least forward + backward time at ``particles`` (torch and the launch of
    ``exclude``, under any of its names, left out: the library's launch is timed anyway), fastest first."""
    timed = [r for r in rows_ if r["particles"] == particles and fused_launch(r["variant"]) is not None
             and fused_launch(r["variant"]) != fused_launch(exclude)]
    return [r["variant"] for r in sorted(timed, key=lambda r: r["fwd_bwd_us"])[:top]]


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fastest", type=Path, help="print the fastest fused variants of this JSON (--particles, --top) "
                    "and exit: the sweep's pick for bench_mlp_packed.py")
    ap.add_argument("--particles", type=int, default=30000)
    ap.add_argument("--top", type=int, default=2)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sizes", type=int, nargs="+", default=[30000, 100000])
    ap.add_argument("--variants", nargs="+", default=["torch", "ieee_32", "ieee_64", "ieee_128", "tf32_64"])
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.fastest:
        try:
            timed = json.loads(args.fastest.read_text())["rows"]
        except (OSError, ValueError, KeyError) as exc:
            print(f"bench_mlp_triton.py: {args.fastest}: no sweep to pick from ({exc})", file=sys.stderr)
            return []
        print(" ".join(fastest(timed, args.particles, args.top)))
        return []
    device = torch.device(args.device)
    print("| particles | variant | fwd us | fwd+bwd us | rel dev from float64 | grad rel dev | bwd regs / spills |\n"
          "| --- | --- | --- | --- | --- | --- | --- |", flush=True)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"

    def write(res: list[dict]) -> None:
        if args.json:
            args.json.write_text(json.dumps({"device": name, "rows": res}, indent=1))
    res = rows(device, args.sizes, args.variants, args.iters, args.repeats, write)
    write(res)
    return res


if __name__ == "__main__":
    main()
