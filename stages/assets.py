"""Stage ``assets@<object>``: a procedural textured object and its static 3DGS scan.

    python stages/assets.py --object duck --out data/assets/duck --metrics metrics/assets/duck.json

Writes ``<out>/{gaussians.ply, mesh.ply, preview.png}`` (the directory atomically) and the metrics JSON.
"""

from __future__ import annotations

import sys
import argparse

from gca import cli, config, io, track
from gca.assets import objects, ply
from gca.assets.preview import write_preview


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--object", required=True, help="a key of `objects:` in params.yaml (e.g. duck)")
    parser.add_argument("--out", required=True, help="output directory (replaced atomically)")
    parser.add_argument("--metrics", required=True, help="metrics .json")
    cli.add_common(parser)
    args = parser.parse_args(argv)

    params = config.load(f"assets@{args.object}", args.params)
    cfg = config.build(objects.ObjectConfig, config.entry(params, "objects", args.object), f"objects.{args.object}")
    mesh, _, cloud = objects.scan_object(args.object, cfg)
    metrics = {"n_gaussians": cloud.n, "n_faces": len(mesh.faces), "mesh_volume_m3": float(mesh.volume),
               "mesh_area_m2": float(mesh.area), "extent_m": mesh.extents.tolist(), "watertight": bool(mesh.is_watertight),
               "sh_degree": cloud.sh_degree}
    with track.stage_run("assets", params, scene=args.object) as run:
        with io.atomic_path(args.out, is_dir=True) as out:
            ply.write_ply(out / "gaussians.ply", cloud)
            mesh.export(out / "mesh.ply")
            write_preview(out / "preview.png", cloud, title=f"{args.object}: {cloud.n} Gaussians")
        io.write_json(args.metrics, metrics)
        run.log_metrics(metrics)
        run.log_artifact(f"{args.out}/preview.png")
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
