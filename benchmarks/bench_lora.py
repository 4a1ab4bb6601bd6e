"""LoRA MLP of a neural law, forward + backward: merged-weight forward vs the rank-r path, side by side.

    python benchmarks/bench_lora.py [--device cuda] [--particles 33614 100000] [--repeats 20]

The network is the paper's (13 -> 64 -> 64 -> 9, GELU, LoRA r = 16 on every layer); the loss is a
fixed random projection of the output, back-propagated to the input and the adapters. The two paths
alternate within each repeat, so both see the same machine load; medians are printed.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gca.laws.lora import LoRALinear, apply_lora, lora_layers  # noqa: E402
from gca.laws.neural import NeuralElasticity  # noqa: E402


def timed(mlp, z, w, sync) -> float:
    t0 = time.perf_counter()
    y = mlp(z)
    (y * w).sum().backward()
    sync()
    return time.perf_counter() - t0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--particles", type=int, nargs="+", default=[33614, 100000])
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    law = apply_lora(NeuralElasticity(), rank=16, alpha=16.0, generator=torch.Generator().manual_seed(0)).to(device)
    for layer in lora_layers(law):
        with torch.no_grad():
            layer.lora_B.normal_(std=0.05)
    mlp = law.mlp
    print(f"{'N':>8}{'merged ms':>11}{'rank-r ms':>11}{'ratio':>7}   ({device}, median of {args.repeats})")
    for n in args.particles:
        z = (0.01 * torch.randn(n, 13, device=device)).requires_grad_(True)
        w = torch.randn(n, 9, device=device)
        merged, lowrank = [], []
        for _ in range(args.repeats + 2):
            merged.append(timed(mlp, z, w, sync))
            LoRALinear.forward, saved = LoRALinear.forward_lowrank, LoRALinear.forward
            try:
                lowrank.append(timed(mlp, z, w, sync))
            finally:
                LoRALinear.forward = saved
        m, r = statistics.median(merged[2:]) * 1e3, statistics.median(lowrank[2:]) * 1e3
        print(f"{n:>8}{m:>11.2f}{r:>11.2f}{r / m:>7.2f}")


if __name__ == "__main__":
    main(sys.argv[1:])
