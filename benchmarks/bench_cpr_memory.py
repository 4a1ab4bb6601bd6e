"""Peak memory of CPR's gradient on P particles x B frames: one call vs chunks of C frames.

    python benchmarks/bench_cpr_memory.py 127531 25 2    # the paper ball: 127.5k particles, 25 CPR frames
    python benchmarks/bench_cpr_memory.py 127531 25 0    # one call (chunk 0 = all frames)

Training takes CPR's gradient ``align.cpr.chunk_frames`` frames at a time (``Objective.prior_gradient``),
freeing each chunk's graph: the neural law evaluated on every particle of every CPR frame keeps its
activations for backward. Deformations are random (|F - I| ~ 0.05), the law is the jelly prior of
``--prior``. CPU: peak resident memory (ru_maxrss, one run per process); CUDA: max_memory_allocated.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gca.align.cpr import CPR  # noqa: E402
from gca.laws.checkpoint import load_prior  # noqa: E402
from gca.pipeline.schema import load_section  # noqa: E402


def peak_gib(device: str) -> float:
    if device == "cuda":
        return torch.cuda.max_memory_allocated() / 2 ** 30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20  # KiB on Linux


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("particles", type=int)
    ap.add_argument("frames", type=int)
    ap.add_argument("chunk", type=int, help="frames per call (0: all in one)")
    ap.add_argument("--prior", type=Path, default=ROOT / ".priors/jelly.pt")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = ap.parse_args(argv)
    prior = load_prior(args.prior, family="jelly")
    el, pl = prior.elasticity.to(args.device), prior.plasticity.to(args.device)
    params = [*el.parameters(), *pl.parameters()]
    g = torch.Generator().manual_seed(0)
    F = (torch.eye(3) + 0.03 * torch.randn(args.frames, args.particles, 3, 3, generator=g)).to(args.device)
    base, t = peak_gib(args.device), time.perf_counter()
    cpr, chunk = CPR(load_section("align.cpr", ROOT / "params.yaml"), args.particles, seed=0), args.chunk or args.frames
    for s in range(0, args.frames, chunk):
        R_e, R_p, _ = cpr.residuals_frames(el, pl, F[s:s + chunk], F[s:s + chunk])
        torch.autograd.grad(R_e + R_p, params, allow_unused=True)
    print(f"{args.device}: P {args.particles} x B {args.frames} frames, chunk {chunk}: peak {peak_gib(args.device):.2f} GiB "
          f"(inputs and model {base:.2f} GiB), {time.perf_counter() - t:.1f} s")


if __name__ == "__main__":
    main()
