"""Stage ``particles@<object>``: Gaussians (+ mesh when present) -> MPM particles and binding.

    python stages/particles.py --object duck --assets data/assets/duck --out data/particles/duck.npz \
        --metrics metrics/particles/duck.json --params params.yaml

Reads ``<assets>/gaussians.ply`` and, if it exists, ``<assets>/mesh.ply`` (without it the interior
comes from the Gaussians alone, as for a user's own scan).
"""

from __future__ import annotations

import sys
import argparse
from pathlib import Path

import numpy as np
import trimesh

from gca import cli, config, io, track
from gca.assets import objects, particles, ply


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--object", required=True, help="a key of `objects:` in params.yaml (e.g. duck)")
    parser.add_argument("--assets", required=True, help="directory with gaussians.ply [and mesh.ply]")
    parser.add_argument("--out", required=True, help="particles .npz (written atomically)")
    parser.add_argument("--metrics", required=True, help="metrics .json")
    cli.add_common(parser)
    args = parser.parse_args(argv)

    params = config.load(f"particles@{args.object}", args.params)
    cfg = config.build(particles.ParticleConfig, config.section(params, "particles"), "particles")
    obj = config.build(objects.ObjectConfig, config.entry(params, "objects", args.object), f"objects.{args.object}")
    cloud = ply.read_ply(Path(args.assets) / "gaussians.ply")
    mesh_path = Path(args.assets) / "mesh.ply"
    mesh = None
    if mesh_path.exists():
        with io.reading(mesh_path, "mesh"):
            mesh = trimesh.load(mesh_path, force="mesh")
    with cli.phase("particles", f"{args.object}: {cloud.n} Gaussians to particles"):
        result = particles.convert(cloud, cfg, density=obj.density, mesh=mesh)
    bound = np.bincount(result.binding_rows, minlength=len(result.gaussian_index))
    metrics = {"n_particles": result.n, "n_gaussians": result.n_gaussians, "n_gaussians_kept": len(result.gaussian_index),
               "volume_sim_m3": float(result.vol.sum()), "mass_kg": float(result.mass.sum()),
               "scale_sim_per_m": float(result.sim_from_world[0, 0]), "spacing_sim_m": result.spacing,
               "mean_particles_per_gaussian": float(bound.mean()),
               "used_mesh": mesh is not None, "x_min": result.x.min(axis=0).tolist(), "x_max": result.x.max(axis=0).tolist()}
    with track.stage_run("particles", {"particles": params["particles"], "object": params["objects"][args.object]},
                         scene=args.object) as run:
        particles.save_particles(args.out, result)
        io.write_json(args.metrics, metrics)
        run.log_metrics(metrics)
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
