"""Conversion time, Gaussians -> particles, for a 100k-Gaussian scan (not a test).

    .venv/bin/python benchmarks/bench_particles.py [--n 100000] [--spacing 0.008] [--object duck]

Prints the wall time of ``gca.assets.particles.convert`` on the mesh path and the Gaussians-only path.
"""

from __future__ import annotations

import argparse
import time

from gca.assets import objects, particles


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--spacing", type=float, default=0.008)
    parser.add_argument("--object", default="duck")
    args = parser.parse_args()
    cfg = objects.ObjectConfig(n_gaussians=args.n, sh_degree=0)
    mesh, _, cloud = objects.scan_object(args.object, cfg)
    pcfg = particles.ParticleConfig(spacing=args.spacing)
    for label, m in (("mesh", mesh), ("gaussians-only", None)):
        start = time.perf_counter()
        p = particles.convert(cloud, pcfg, density=cfg.density, mesh=m)
        seconds = time.perf_counter() - start
        print(f"{args.object} G={cloud.n} spacing={args.spacing} {label}: {seconds:.2f} s, "
              f"P={p.n}, volume={p.vol.sum():.5f} sim m^3, binding nnz={len(p.binding_rows)}")


if __name__ == "__main__":
    main()
