"""The neural law's MLP variants under a saturated GPU: P processes at once, each replaying one variant's call
(a script, not a test; issue 20, session 36).

`bench_runs_packed.py` found the simulation and law saturating one H100 at ~0.1 s per run's 200-step rollout, however
eight or twelve runs share it (processes, batches or both), so a packed table is bound by the GPU work per step, not
by one kernel's latency. The MLP variants were timed alone (``bench_mlp.py``, ``bench_mlp_triton.py``: torch fastest,
34.5 us forward at 30k), where a kernel that keeps its [N, 64] activations on chip but fills the GPU poorly loses;
packed, it is the bytes and operations that count. Here each variant's call is captured in a CUDA graph (as training replays
it) and replayed ``--calls`` times by P workers at once after one start signal (``benchmarks/packed.py``); the
figure is the span per call over all workers (us), against torch's at the same P (law rows: against law_torch's).

Variants: ``torch``, ``torch_tf32``, ``simt``, ``t<k>s`` (``bench_mlp.py``'s MLPs; pass ``fwd`` under no_grad or
``fwdbwd``, the gradients w.r.t. the features and the three weights), ``ieee_<B>`` and ``tf32_<B>`` (the fused Triton
MLP of ``bench_mlp_triton.py``, both passes; needs triton), ``law_torch``, ``law_simt`` (one step's law calls,
plasticity then elasticity with LoRA merged, forward + backward: pass ``fwdbwd`` only).

Usage (the GPU machine)::

    python benchmarks/bench_mlp_packed.py --device cuda --mps --procs 1 8 --variants torch simt ieee_64 --json out.json
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script from anywhere
from benchmarks.packed import (add_arguments, exit_on_sigterm, ratios, repeat_after_go, run_workers,  # noqa: E402
                               write_result)

VARIANT = re.compile(r"^(torch|torch_tf32|simt|t\d+s|(ieee|tf32)_\d+(_w\d+)?(_p\d+)?|law_(torch|simt))$")


def passes_of(variant: str) -> tuple[str, ...]:
    """The passes a variant has: the law rows are forward + backward only."""
    return ("fwdbwd",) if variant.startswith("law_") else ("fwd", "fwdbwd")


def call_of(variant: str, pass_: str, n: int, device):
    """The callable a worker replays: ``variant``'s ``pass_`` on n particles (the MLP variants on one seeded network,
    features and cotangent: ``bench_mlp.mlp_calls``'s)."""
    from benchmarks.bench_mlp import _no_grad, law_step, mlp_calls

    if variant.startswith("law_"):
        return law_step(variant[4:], n, device)
    run = None
    if variant.startswith(("ieee_", "tf32_")):
        from benchmarks.bench_mlp_triton import variant_call

        run = lambda z, Ws, net: variant_call(variant, net)(z)  # noqa: E731
    fwd, both, *_ = mlp_calls(variant, n, device, run)
    return _no_grad(fwd) if pass_ == "fwd" else both


def worker(a) -> None:
    """One process: capture the call (CUDA) or take it as is (CPU), say ready, wait for the go, ``--calls`` calls."""
    import torch

    from benchmarks.bench_mlp import captured
    from gca.train.loop import matmul_precision

    device = torch.device(a.device)
    with matmul_precision("high" if a.variant == "torch_tf32" else "highest"):
        call = captured(call_of(a.variant, a.pass_, a.particles, device), device)
        t0 = repeat_after_go(call, a.calls, device, a)
    write_result(a.result, t0)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--procs", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--variants", nargs="+", default=["torch", "torch_tf32", "simt", "ieee_64", "tf32_64", "law_torch"])
    ap.add_argument("--particles", type=int, default=30000)
    ap.add_argument("--calls", type=int, default=20000,
                    help="calls per row, divided among its P processes (20000: ~1 s of torch's 30k forward alone)")
    add_arguments(ap)
    ap.add_argument("--variant", default="torch", help=argparse.SUPPRESS)
    ap.add_argument("--pass", dest="pass_", default="fwd", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        worker(a)
        return []
    bad = [v for v in a.variants if not VARIANT.match(v)]
    if bad or any(p < 1 for p in a.procs):
        ap.error(f"variants: torch, torch_tf32, simt, t<k>s, ieee_<B>, tf32_<B>, law_torch, law_simt (got {bad}); "
                 f"procs >= 1 (got {a.procs})")
    from gca.pipeline.grid import mps_daemon

    exit_on_sigterm()
    rows = []

    def base(r):  # like against like at the same P: an MLP against torch's, a law step against law_torch's
        name = "law_torch" if r["variant"].startswith("law_") else "torch"
        return next((x for x in rows if x["variant"] == name and x["pass"] == r["pass"]
                     and x["processes"] == r["processes"]), None)

    print("| variant | pass | processes | calls each | span s | us per call | x torch (law_torch) at this P |\n"
          "| --- | --- | --- | --- | --- | --- | --- |", flush=True)
    with tempfile.TemporaryDirectory() as tmp, mps_daemon(a.mps, lambda m: print(m, flush=True)) as mps_on:
        for variant in a.variants:
            for pass_ in passes_of(variant):
                for p in a.procs:
                    calls = max(2, a.calls // p)
                    cmd = ["-m", "benchmarks.bench_mlp_packed", "--worker", "--device", a.device, "--variant",
                           variant, "--pass", pass_, "--particles", str(a.particles), "--calls", str(calls)]
                    span, _ = run_workers([cmd] * p, Path(tmp), a.ready_timeout,
                                          f"bench_mlp_packed: {variant} {pass_} x{p}", a.run_timeout)
                    r = {"variant": variant, "pass": pass_, "processes": p, "calls_per_process": calls,
                         "particles": a.particles, "span_s": span, "us_per_call": 1e6 * span / (p * calls),
                         "mps": mps_on}
                    rows.append(r)
                    ratios(rows, "x_torch", base, "us_per_call")
                    print(f"| {variant} | {pass_} | {p} | {calls} | {span:.3f} | {r['us_per_call']:.1f} | "
                          + (f"{r['x_torch']:.2f}x |" if r["x_torch"] else "- |"), flush=True)
                    if a.json:  # after every row: a command stopped by its limit keeps what it measured
                        Path(a.json).write_text(json.dumps({"device": a.device, "rows": rows}, indent=2))
    return rows

if __name__ == "__main__":
    main()
