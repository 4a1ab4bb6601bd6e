"""The neural laws' SVD and features: two kernels (the SVD kernel, then ``features``) against one
(``svd_features``, session 52), per launch, at a training step's particle count (a script).

Usage::

    python benchmarks/bench_features.py --device cuda --n 30000 --reps 200 [--json out.json]

Rows: ``two_kernels`` (``gca.laws.svd._svd_rotations`` then ``features``: the path before session 52),
``one_kernel_forward`` (``gca.laws.fused.features`` without gradients: the SVD not stored, a rollout's forward),
``one_kernel_kept`` (with gradients asked: the SVD stored for the backward, a replay's forward). F near the identity
(the duck's training states are within ~10 % of it). Timed by CUDA events on a GPU (the mean of ``--reps`` launches
after a warm-up; each call captured in a CUDA graph and replayed, as training replays its frames), by the wall clock
elsewhere; the three rows' R and z must be equal (checked, bitwise). Session 52's first run timed eager calls (the
host's launch rate, ~250-300 us a call) and found the three paths' outputs bitwise equal on the H200.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def _timed(fn, reps: int, device: torch.device) -> float:
    """Mean seconds of ``fn()`` over ``reps`` calls after one warm-up call; on a GPU ``fn`` captured in a CUDA graph
    and the graph replayed (eager calls time the host's launches: ~250-300 us a call on the H200 in session 52, for
    kernels of ~10 us)."""
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            fn()
        graph.replay()
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        for _ in range(reps):
            graph.replay()
        end.record()
        end.synchronize()
        return start.elapsed_time(end) / 1e3 / reps
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - t) / reps


def rows(n: int, reps: int, device: str, seed: int = 0) -> list[dict]:
    """The three rows (name, us per call, and the outputs' equality with the two-kernel path)."""
    from gca.laws import fused
    from gca.laws.svd import _svd_rotations

    g = torch.Generator().manual_seed(seed)
    F = (torch.eye(3) + 0.1 * torch.randn(n, 3, 3, generator=g)).to(device).contiguous()
    dev = F.device  # with its index (warp needs it: torch.device("cuda") has none)

    def two():
        return fused.features_of_svd(F, *_svd_rotations(F))

    def forward():
        with torch.no_grad():
            return fused.features(F)

    Fg = F.clone().requires_grad_(True)

    def kept():
        R, z = fused.features(Fg)
        return R.detach(), z.detach()

    ref = two()
    out = []
    for name, fn in (("two_kernels", two), ("one_kernel_forward", forward), ("one_kernel_kept", kept)):
        R, z = fn()
        out.append({"row": name, "us": 1e6 * _timed(fn, reps, dev),
                    "equal": bool(torch.equal(R, ref[0]) and torch.equal(z, ref[1]))})
    return out


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--n", type=int, default=30000)
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    result = rows(args.n, args.reps, args.device)
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu"
    print(f"{name}, {args.n} particles, {args.reps} calls a row")
    for r in result:
        print(f"| {r['row']:>18} | {r['us']:9.2f} us | equal: {r['equal']} |")
    if args.json:
        args.json.write_text(json.dumps({"device": name, "n": args.n, "reps": args.reps, "rows": result}, indent=1))
    return result


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main(sys.argv[1:])
