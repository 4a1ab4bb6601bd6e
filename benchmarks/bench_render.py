"""Renderer throughput: frames/s forward and forward+backward (not a test).

Scene: N Gaussians filling a ball of radius 0.3 m at the centre of the sim cube (3DGS-like random
anisotropic covariances, spacing-sized), opacities in [0.5, 1], seen by a 40 deg camera 1.5 m away.

    python benchmarks/bench_render.py                                   # CPU, torch, full grid
    python benchmarks/bench_render.py --n 10000 --res 128 --repeats 5
    python benchmarks/bench_render.py --device cuda --backend torch gsplat   # side by side + max |diff|

Prints a Markdown table (median and best of ``--repeats`` timed runs after one warm-up).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gca.render import RasterConfig, covariance_from_scale_rot, look_at, render  # noqa: E402


def ball_scene(n: int, device: str, seed: int = 0, radius: float = 0.3):
    """Gaussians filling a ball: ``(means [n, 3], covs [n, 3, 3], colors [n, 3], opacities [n])``."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    means = 0.5 + radius * d / d.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=g) ** (1 / 3)
    spacing = (4 / 3 * math.pi * radius**3 / n) ** (1 / 3)
    log_scales = math.log(0.6 * spacing) + 0.3 * torch.randn(n, 3, generator=g)
    covs = covariance_from_scale_rot(log_scales, torch.randn(n, 4, generator=g))
    colors = torch.rand(n, 3, generator=g)
    opacities = 0.5 + 0.5 * torch.rand(n, generator=g)
    return tuple(t.to(device) for t in (means, covs, colors, opacities))


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_render(inputs, camera, bg, backend: str, device: str, backward: bool, repeats: int, cfg):
    """Wall-clock and process-CPU seconds of ``repeats`` renders (after one warm-up).

    On a shared CPU machine the process-CPU time with ``--threads 1`` is the contention-free figure.
    """
    times, cpu_times = [], []
    for i in range(repeats + 1):
        leaves = [t.detach().requires_grad_(backward) for t in inputs]
        _sync(device)
        t0, c0 = time.perf_counter(), time.process_time()
        out = render(*leaves, camera, bg, backend=backend, cfg=cfg)
        if backward:
            (out["rgb"].sum() + out["alpha"].sum() + out["depth"].sum()).backward()
        _sync(device)
        if i:
            times.append(time.perf_counter() - t0)
            cpu_times.append(time.process_time() - c0)
    return times, cpu_times


def max_diff(a: dict, b: dict) -> str:
    """``"rgb=max/mean .."``: max and mean |a - b| per output (moved to ``a``'s device)."""
    diffs = {k: (a[k] - b[k].to(a[k].device)).abs() for k in ("rgb", "alpha", "depth")}
    return " ".join(f"{k}={d.max().item():.1e}/{d.mean().item():.1e}" for k, d in diffs.items())


def grad_diff(inputs, camera, bg, cfg) -> str:
    """Relative max |VJP_torch - VJP_gsplat| / max |VJP_gsplat| per input, one random cotangent."""
    g = torch.Generator(device=inputs[0].device).manual_seed(0)
    grads = {}
    for backend in ("torch", "gsplat"):
        leaves = [t.detach().requires_grad_() for t in inputs]
        out = render(*leaves, camera, bg, backend=backend, cfg=cfg)
        g.manual_seed(0)
        loss = sum((out[k] * torch.randn(out[k].shape, generator=g, device=out[k].device)).sum()
                   for k in ("rgb", "alpha", "depth"))
        grads[backend] = torch.autograd.grad(loss, leaves)
    names = ("means", "covs", "colors", "opacities")
    return " ".join(f"v_{n}={((a - b).abs().max() / b.abs().max()).item():.1e}"
                    for n, a, b in zip(names, grads["torch"], grads["gsplat"]))


def compare(inputs, camera, bg, cfg, backends, check_cpu: bool) -> str:
    """Max differences torch-vs-gsplat (both requested) and device-vs-CPU torch (``check_cpu``)."""
    notes = []
    ours = render(*inputs, camera, bg, backend="torch", cfg=cfg)
    if "gsplat" in backends:
        notes.append("gsplat: " + max_diff(ours, render(*inputs, camera, bg, backend="gsplat", cfg=cfg)))
        notes.append("grads rel: " + grad_diff(inputs, camera, bg, cfg))
    if check_cpu:
        cpu = render(*[t.cpu() for t in inputs], camera, bg.cpu(), backend="torch", cfg=cfg)
        notes.append("cpu: " + max_diff(ours, cpu))
    return "; ".join(notes)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, nargs="+", default=[10_000, 100_000], help="Gaussian counts")
    parser.add_argument("--res", type=int, nargs="+", default=[128, 256, 512], help="square image sides")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--backend", nargs="+", default=["torch"], choices=["torch", "gsplat"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: leave as is)")
    parser.add_argument("--tile-size", type=int, default=RasterConfig.tile_size, help="torch backend tile side")
    parser.add_argument("--slab", type=int, default=RasterConfig.slab, help="torch backend depth slab")
    parser.add_argument("--no-backward", action="store_true")
    parser.add_argument("--check-cpu", action="store_true", help="also report max |device - CPU| (torch backend)")
    parser.add_argument("--gsplat-like", action="store_true",
                        help="torch backend with gsplat's rules (alpha clamp 0.999, extent = alpha >= 1/255) "
                             "to validate the gsplat input mapping; default: 3DGS rules (0.99, 3 sigma)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = RasterConfig(tile_size=args.tile_size, slab=args.slab)
    if args.gsplat_like:
        cfg = dataclasses.replace(cfg, alpha_max=0.999, sigma_cutoff=3.5)
    print(f"device={args.device} torch={torch.__version__} threads={torch.get_num_threads()} repeats={args.repeats} "
          f"cfg={cfg}")
    print("| N | res | backend | fwd s (med / best) | fwd FPS | fwd+bwd s (med / best) | fwd+bwd FPS "
          "| fwd / fwd+bwd process-CPU s (med) | abs diff max/mean |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    bg = torch.zeros(3, device=args.device)
    for n in args.n:
        inputs = ball_scene(n, args.device)
        for res in args.res:
            camera = look_at([0.5, 0.5, -1.0], [0.5, 0.5, 0.5], [0, 1, 0], 40.0, res, res)
            diff = compare(inputs, camera, bg, cfg, args.backend, args.check_cpu)
            for backend in args.backend:
                fwd, fwd_cpu = time_render(inputs, camera, bg, backend, args.device, False, args.repeats, cfg)
                both, both_cpu = ([math.nan], [math.nan]) if args.no_backward else \
                    time_render(inputs, camera, bg, backend, args.device, True, args.repeats, cfg)
                print(f"| {n} | {res} | {backend} | {statistics.median(fwd):.4f} / {min(fwd):.4f} | "
                      f"{1 / statistics.median(fwd):.1f} | {statistics.median(both):.4f} / {min(both):.4f} | "
                      f"{1 / statistics.median(both):.1f} | {statistics.median(fwd_cpu):.3f} / "
                      f"{statistics.median(both_cpu):.3f} | {diff} |", flush=True)


if __name__ == "__main__":
    main()
