"""Stage ``assets@<object>``: a procedural textured object and its static 3DGS scan.

    python stages/assets.py --object duck --out data/assets/duck --metrics metrics/assets/duck.json

Writes ``<out>/{gaussians.ply, mesh.ply, preview.png}`` (the directory atomically) and the metrics JSON.
An ``objects.<name>`` entry with a ``scan`` key is a user's capture (:mod:`gca.capture.objects`): its
scan is cleaned, oriented and scaled into ``<out>`` instead (plus ``object_from_scan.json``; ``mesh.ply``
only when a usable mesh was given); a bad scan or option stops the stage with one line naming it.
"""

from __future__ import annotations

import sys
import argparse

from gca import config, io
from gca.pipeline import cli
from gca.pipeline import schema, track
from gca.assets import objects, ply
from gca.assets.preview import write_preview
from gca.assets.ply import PlyFormatError
from gca.assets.scan import ScanError
from gca.capture import objects as capture


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--object", required=True, help="a key of `objects:` in params.yaml (e.g. duck)")
    parser.add_argument("--out", required=True, help="output directory (replaced atomically)")
    parser.add_argument("--metrics", required=True, help="metrics .json")
    cli.add_common(parser)
    args = parser.parse_args(argv)

    params = schema.load(f"assets@{args.object}", args.params)
    if capture.is_capture(config.section(params, f"objects.{args.object}")):
        return _capture(args, params)
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


def _capture(args, params) -> dict:
    """The capture branch: import the user's scan (user errors end the stage with one line, no traceback)."""
    try:
        cfg = capture.capture_config(config.section(params, f"objects.{args.object}"), args.object)
        with track.stage_run("assets", params, scene=args.object) as run:
            metrics = capture.import_capture(cfg, args.out, name=args.object)
            io.write_json(args.metrics, metrics)
            run.log_metrics(metrics)  # numbers only, nested ones as removed.far etc.
    except (ScanError, PlyFormatError, config.ConfigError) as exc:
        raise SystemExit(f"assets@{args.object}: {exc}") from None
    return metrics


if __name__ == "__main__":
    sys.exit(cli.run(main))
