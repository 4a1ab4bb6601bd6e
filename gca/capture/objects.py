"""The capture object kind: ``objects.<name>`` with a ``scan`` key is a user's scan, not a procedural shape.

params.yaml::

    objects:
      donut:
        scan: captures/donut/point_cloud.ply   # any 3DGS .ply (reference trainer, gsplat, nerfstudio), SH 0-3
        mesh: ""                               # optional mesh in the scan's frame and units ("" = none)
        density: 1100.0                        # [kg/m^3]
        scan_options: {up: "+z", real_size: 0.12, outlier_factor: 10.0}   # gca.assets.scan.ScanConfig

:func:`import_capture` writes the object folder the ``particles`` stage reads, in the *object frame*
(metres, y up): ``gaussians.ply`` (cleaned, oriented, scaled; SH bands rotated), ``mesh.ply`` when a
mesh was given and is watertight or repairable, ``object_from_scan.json`` (the 4x4 similarity
x_obj = s Q x_scan, to bring cameras calibrated in the scan's frame along) and ``preview.png``.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from gca import io
from gca.assets.ply import read_ply, write_ply
from gca.assets.preview import write_preview
from gca.assets.scan import ScanConfig, ScanError, check_mesh, prepare_scan
from gca.config import build


@dataclasses.dataclass(frozen=True)
class CaptureObjectConfig:
    """One capture entry of the ``objects`` section (module docstring)."""

    scan: str  # the scan .ply, any name (relative paths from the repository root)
    mesh: str = ""  # optional mesh in the scan's frame and units; "" = none
    density: float = 1000.0  # material density [kg/m^3]
    scan_options: ScanConfig = ScanConfig()  # cleaning, up axis, rotation, real size


def is_capture(section: Mapping) -> bool:
    """Whether an ``objects.<name>`` entry is a capture (it names a ``scan`` file)."""
    return isinstance(section, Mapping) and "scan" in section


def capture_config(section: Mapping, name: str) -> CaptureObjectConfig:
    """Build :class:`CaptureObjectConfig` from ``objects.<name>``, refusing bad options in one line."""
    cfg = build(CaptureObjectConfig, section, f"objects.{name}", partial=True)  # a user record: defaults apply
    if not cfg.density > 0:
        raise ScanError(f"params objects.{name}.density: must be > 0 kg/m^3, got {cfg.density}")
    return cfg


def import_capture(cfg: CaptureObjectConfig, out: str | os.PathLike, name: str = "object",
                   root: str | os.PathLike = ".") -> dict:
    """Read, clean, orient and scale the user's scan and mesh into the object folder ``out`` (atomic).

    Args:
        cfg: the capture entry; ``root`` resolves its relative paths.
        out: the folder to write (replaced whole, or left untouched on an error).
        name: the object's name (preview title).

    Returns:
        The metrics: the cleaning report of :func:`gca.assets.scan.prepare_scan` plus ``mesh`` (its
        check report, or null) and ``n_gaussians``.

    Raises:
        ScanError / PlyFormatError: one line naming the file and the problem.
    """
    scan_path = Path(root) / cfg.scan
    if not scan_path.is_file():
        raise ScanError(f"{scan_path}: scan file not found (objects.{name}.scan)")
    raw = read_ply(scan_path)
    cloud, T, report = prepare_scan(raw, cfg.scan_options, name=str(scan_path))
    mesh, mesh_report = None, None
    if cfg.mesh:
        import trimesh

        mesh_path = Path(root) / cfg.mesh
        if not mesh_path.is_file():
            raise ScanError(f"{mesh_path}: mesh file not found (objects.{name}.mesh; \"\" for none)")
        try:
            loaded = trimesh.load(mesh_path, force="mesh")
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise ScanError(f"{mesh_path}: not a readable mesh ({type(exc).__name__}: {exc})") from exc
        if len(getattr(loaded, "faces", [])) == 0:
            raise ScanError(f"{mesh_path}: the mesh has no faces")
        mesh, mesh_report = check_mesh(loaded.apply_transform(T), mesh_path)
    metrics = {**report, "n_gaussians": cloud.n, "mesh": mesh_report, "scan": str(cfg.scan),
               "object_from_scan": T.tolist()}
    with io.atomic_path(out, is_dir=True) as tmp:
        write_ply(tmp / "gaussians.ply", cloud)
        if mesh is not None:
            mesh.export(tmp / "mesh.ply")
        io.write_json(tmp / "object_from_scan.json", {"object_from_scan": T.tolist(), "units": "x_obj [m] = "
                      "object_from_scan @ [x_scan, 1]; uniform scale s = metres per scan unit, y up"})
        write_preview(tmp / "preview.png", cloud, title=f"{name}: {cloud.n} Gaussians (cleaned, y up)")
    return metrics


def read_object_from_scan(folder: str | os.PathLike) -> np.ndarray:
    """The 4x4 ``object_from_scan`` of an imported capture object (identity for procedural objects)."""
    path = Path(folder) / "object_from_scan.json"
    return np.asarray(io.read_json(path)["object_from_scan"], dtype=np.float64) if path.is_file() else np.eye(4)
