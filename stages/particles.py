"""Stage ``particles@<object>``: Gaussians (+ mesh when present) -> MPM particles and binding.

    python stages/particles.py --object duck --assets data/assets/duck --out data/particles/duck.npz \
        --metrics metrics/particles/duck.json --params params.yaml

Reads ``<assets>/gaussians.ply`` and, if it exists, ``<assets>/mesh.ply`` (without it the interior
comes from the Gaussians alone, as for a user's own scan; a mesh that is not watertight is repaired or
ignored, reported under ``mesh``). Metrics in SI units: ``volume_m3`` and ``mass_kg`` of the real object
(``*_sim_*``: the simulation's, in the unit cube), ``share_bound_within_mahalanobis`` (the Gaussians with
a particle inside their bound; the others fell back to their nearest particle).
"""

from __future__ import annotations

import sys
import argparse
from pathlib import Path

import numpy as np
import trimesh

from gca import config, io
from gca.pipeline import cli
from gca.assets import objects, particles, ply, scan
from gca.capture import objects as capture
from gca.pipeline import schema, track


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--object", required=True, help="a key of `objects:` in params.yaml (e.g. duck)")
    parser.add_argument("--assets", required=True, help="directory with gaussians.ply [and mesh.ply]")
    parser.add_argument("--out", required=True, help="particles .npz (written atomically)")
    parser.add_argument("--metrics", required=True, help="metrics .json")
    cli.add_common(parser)
    args = parser.parse_args(argv)

    params = schema.load(f"particles@{args.object}", args.params)
    cfg = config.build(particles.ParticleConfig, config.section(params, "particles"), "particles")
    section = config.entry(params, "objects", args.object)
    obj = (capture.capture_config(section, args.object) if capture.is_capture(section)
           else config.build(objects.ObjectConfig, section, f"objects.{args.object}"))
    cloud = ply.read_ply(Path(args.assets) / "gaussians.ply")
    mesh_path = Path(args.assets) / "mesh.ply"
    mesh, mesh_report = None, None
    if mesh_path.exists():
        with io.reading(mesh_path, "mesh"):
            mesh, mesh_report = scan.check_mesh(trimesh.load(mesh_path, force="mesh"), mesh_path)
    with cli.phase("particles", f"{args.object}: {cloud.n} Gaussians to particles"):
        try:
            result = particles.convert(cloud, cfg, density=obj.density, mesh=mesh)
        except particles.LatticeTooLarge as exc:  # refused before it is allocated: one line naming the object
            raise config.ConfigError(f"particles@{args.object}: {exc}") from None
    bound = np.bincount(result.binding_rows, minlength=len(result.gaussian_index))
    s = float(result.sim_from_world[0, 0])
    volume_m3 = float(result.vol.sum()) / s**3  # the object frame is metres: SI volume and mass
    metrics = {"n_particles": result.n, "n_gaussians": result.n_gaussians, "n_gaussians_kept": len(result.gaussian_index),
               "volume_sim_m3": float(result.vol.sum()), "mass_sim_kg": float(result.mass.sum()),
               "volume_m3": volume_m3, "mass_kg": obj.density * volume_m3, "mesh": mesh_report,
               **scan.binding_share(result, cloud, cfg.mahalanobis_chi2),
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
