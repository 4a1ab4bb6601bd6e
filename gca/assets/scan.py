"""A user's 3DGS scan as it comes: crop, floater and outlier removal, up axis, real size, mesh check.

:func:`prepare_scan` turns a raw scan (any ``.ply`` the reference 3DGS trainer, gsplat or nerfstudio
writes, in the capture's own frame and units) into the *object frame* the rest of the project uses:
metres, y up, with its report. Steps, in order (each reported with how many Gaussians it removed
and why):

1. ``crop``: keep the Gaussians whose means lie in the box ``[[x0, y0, z0], [x1, y1, z1]]`` (scan
   frame and units, as read in a viewer);
2. ``far``: drop the Gaussians farther from the median centre than ``far_factor`` x the 95th
   percentile of that distance (a Gaussian at 1e30 m, a stray background blob);
3. ``statistical``: drop the Gaussians whose mean distance to their ``neighbors`` nearest
   neighbours exceeds ``outlier_factor`` x the median of that distance (isolated floaters);
4. ``component``: link Gaussians closer than ``link_factor`` x that median; drop the connected
   components holding less than ``min_component`` of the Gaussians (floater clusters);
5. orient and scale: the scan's ``up`` axis onto +y, then ``rotation_deg`` (x, y, z Euler angles
   about the fixed axes, degrees), then the uniform scale to metres (``real_size``: the largest
   side of the cleaned bounding box [m]; else ``metres_per_unit``). Gaussians rotate and scale with
   the frame, and so do their SH bands 1-3 (:func:`gca.sh.rotate_sh`).

The transform of step 5 is the similarity ``object_from_scan`` (x_obj = s Q x_scan), kept so that a
camera calibrated in the scan's frame can be brought into the object frame
(:func:`gca.capture.cameras.camera_to_object`).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from gca.assets.ply import GaussianCloud, normalized_quats, quats_to_rotmats, rotmats_to_quats
from gca.sh import rotate_sh

UP_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


class ScanError(ValueError):
    """A scan that cannot be used as given (the message names the file, the cause and the fix)."""


@dataclasses.dataclass(frozen=True)
class ScanConfig:
    """How to clean, orient and scale a user's scan (``objects.<name>.scan_options`` in params.yaml)."""

    crop: Sequence | None = None  # [[x0, y0, z0], [x1, y1, z1]] box kept (scan frame and units) or None
    far_factor: float = 10.0  # drop Gaussians farther than this x the 95th-percentile distance [1]; 0: off
    neighbors: int = 16  # neighbours of the statistical and component tests [count]
    outlier_factor: float = 10.0  # drop mean-neighbour distance > this x its median [1]; 0: off
    link_factor: float = 3.0  # component links: distance < this x the median neighbour distance [1]
    min_component: float = 0.01  # drop components with less than this share of the Gaussians [1]; 0: off
    up: str = "+y"  # the scan's up axis: +x -x +y -y +z -z (COLMAP captures are often -y or +z)
    rotation_deg: Sequence = (0.0, 0.0, 0.0)  # extra rotation after `up`: Euler x, y, z about fixed axes [deg]
    real_size: float = 0.0  # > 0: the largest side of the cleaned box in metres [m]; sets the scale
    metres_per_unit: float = 1.0  # scan units -> metres when real_size is 0 [m / unit]

    def __post_init__(self) -> None:
        bad = []
        if self.up not in UP_AXES:
            bad.append(f"up={self.up!r} (one of {sorted(UP_AXES)})")
        if len(self.rotation_deg) != 3:
            bad.append(f"rotation_deg={self.rotation_deg!r} (three angles)")
        if self.crop is not None:
            box = np.asarray(self.crop, dtype=np.float64)
            if box.shape != (2, 3) or not np.all(box[0] < box[1]):
                bad.append(f"crop={self.crop!r} ([[x0, y0, z0], [x1, y1, z1]] with x0 < x1 ...)")
        if not (self.real_size >= 0 and self.metres_per_unit > 0):
            bad.append(f"real_size={self.real_size}, metres_per_unit={self.metres_per_unit} (>= 0, > 0)")
        if self.neighbors < 2 or min(self.far_factor, self.outlier_factor, self.link_factor, self.min_component) < 0:
            bad.append("neighbors >= 2 and the factors >= 0")
        if bad:
            raise ScanError(f"scan options: invalid {'; '.join(bad)}")


def rotation_from_euler_deg(angles: Sequence[float]) -> np.ndarray:
    """R = Rz Ry Rx for angles (x, y, z) [deg] about the fixed axes, [3, 3]."""
    ax, ay, az = np.radians(np.asarray(angles, dtype=np.float64))
    Rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    Ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    Rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def up_rotation(up: str) -> np.ndarray:
    """The proper rotation [3, 3] taking the axis ``up`` (e.g. ``"+z"``) onto +y by the shortest turn."""
    a = np.asarray(UP_AXES[up], dtype=np.float64)
    b = np.array([0.0, 1.0, 0.0])
    if np.allclose(a, b):
        return np.eye(3)
    if np.allclose(a, -b):
        return np.diag([1.0, -1.0, -1.0])  # half turn about x
    v, c = np.cross(a, b), float(a @ b)
    V = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + V + V @ V / (1 + c)


def neighbour_distances(means: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean distance to the k nearest other means [G], (distances [G, k], indices [G, k]))."""
    k = min(k, len(means) - 1)
    dist, index = cKDTree(means).query(means, k=k + 1)
    return dist[:, 1:].mean(axis=1), (dist[:, 1:], index[:, 1:])


def outlier_masks(means: np.ndarray, cfg: ScanConfig) -> dict[str, np.ndarray]:
    """Which Gaussians each test removes (cumulative order crop, far, statistical, component).

    Args:
        means: [G, 3] centres in the scan frame (any units).

    Returns:
        ``{reason: removed [G] bool}``, each mask disjoint from the previous ones.
    """
    x = np.asarray(means, dtype=np.float64)
    G = len(x)
    alive = np.ones(G, bool)
    out = {}

    def drop(reason: str, mask: np.ndarray) -> None:
        mask = mask & alive
        out[reason] = mask
        alive[mask] = False

    if cfg.crop is not None:
        lo, hi = np.asarray(cfg.crop, dtype=np.float64)
        drop("crop", ~np.all((x >= lo) & (x <= hi), axis=1))
    if cfg.far_factor > 0 and alive.sum() > 1:
        centre = np.median(x[alive], axis=0)
        r = np.linalg.norm(x - centre, axis=1)
        drop("far", r > cfg.far_factor * max(np.quantile(r[alive], 0.95), 1e-300))
    if alive.sum() > cfg.neighbors + 1 and (cfg.outlier_factor > 0 or cfg.min_component > 0):
        idx = np.nonzero(alive)[0]
        mean_d, (dist, nbr) = neighbour_distances(x[idx], cfg.neighbors)
        median = float(np.median(mean_d))
        if cfg.outlier_factor > 0:
            stat = np.zeros(G, bool)
            stat[idx] = mean_d > cfg.outlier_factor * median
            drop("statistical", stat)
        if cfg.min_component > 0:
            keep_local = alive[idx]
            link = (dist < cfg.link_factor * median) & keep_local[:, None] & keep_local[nbr]
            rows = np.repeat(np.arange(len(idx)), nbr.shape[1])[link.reshape(-1)]
            graph = sp.coo_matrix((np.ones(len(rows)), (rows, nbr.reshape(-1)[link.reshape(-1)])),
                                  shape=(len(idx), len(idx)))
            _, labels = connected_components(graph, directed=False)
            sizes = np.bincount(labels[keep_local], minlength=labels.max() + 1)
            small = sizes[labels] < cfg.min_component * keep_local.sum()
            comp = np.zeros(G, bool)
            comp[idx] = small
            drop("component", comp)
    return out


def transform_cloud(cloud: GaussianCloud, Q: np.ndarray, s: float) -> GaussianCloud:
    """The scan in the frame x' = s Q x: means, rotations, log-scales and SH bands 1-3 transformed.

    Args:
        Q: [3, 3] proper rotation; s: uniform scale > 0 [m per scan unit].
    """
    R = np.einsum("ij,gjk->gik", Q, quats_to_rotmats(normalized_quats(cloud)))
    return dataclasses.replace(
        cloud, means=(s * cloud.means.astype(np.float64) @ Q.T).astype(np.float32),
        normals=(cloud.normals.astype(np.float64) @ Q.T).astype(np.float32),
        sh_rest=rotate_sh(cloud.sh_rest, Q), log_scales=(cloud.log_scales + np.float32(np.log(s))),
        quats_wxyz=rotmats_to_quats(R).astype(np.float32))


def prepare_scan(cloud: GaussianCloud, cfg: ScanConfig, name: str = "scan") -> tuple[GaussianCloud, np.ndarray, dict]:
    """Clean, orient and scale a scan (module docstring).

    Args:
        cloud: the raw scan (scan frame, scan units).
        cfg: the options.
        name: the file, named in errors.

    Returns:
        (cleaned cloud in the object frame [m, y up], ``object_from_scan`` [4, 4] similarity,
        report: counts removed per reason, kept, extents before and after, scale, rotation).

    Raises:
        ScanError: nothing left after cleaning (names the step that removed the most and the knob).
    """
    removed = outlier_masks(cloud.means, cfg)
    keep = ~np.any(np.stack(list(removed.values())), axis=0) if removed else np.ones(cloud.n, bool)
    counts = {reason: int(mask.sum()) for reason, mask in removed.items()}
    if keep.sum() < 4:
        worst = max(counts, key=counts.get) if counts else "none"
        raise ScanError(f"{name}: {int(keep.sum())} of {cloud.n} Gaussians left after cleaning ({counts}); "
                        f"the {worst!r} step removed the most: loosen its option (scan_options."
                        f"{ {'crop': 'crop', 'far': 'far_factor', 'statistical': 'outlier_factor', 'component': 'min_component'}.get(worst, worst)})")
    clean = cloud.subset(keep)
    Q = rotation_from_euler_deg(cfg.rotation_deg) @ up_rotation(cfg.up)
    rotated = clean.means.astype(np.float64) @ Q.T
    extent = float((rotated.max(axis=0) - rotated.min(axis=0)).max())
    if not extent > 0:
        raise ScanError(f"{name}: the cleaned scan has no extent (all {clean.n} means coincide)")
    s = cfg.real_size / extent if cfg.real_size > 0 else cfg.metres_per_unit
    out = transform_cloud(clean, Q, s)
    T = np.eye(4)
    T[:3, :3] = s * Q
    raw_ext = (cloud.means.max(axis=0).astype(np.float64) - cloud.means.min(axis=0))
    report = {"n_gaussians_in": cloud.n, "n_gaussians_kept": int(keep.sum()), "removed": counts,
              "removed_total": int((~keep).sum()), "extent_raw_units": raw_ext.tolist(),
              "extent_m": (out.means.max(axis=0) - out.means.min(axis=0)).astype(np.float64).tolist(),
              "metres_per_unit": float(s), "up": cfg.up, "rotation_deg": list(map(float, cfg.rotation_deg)),
              "sh_degree": cloud.sh_degree}
    return out, T, report


# ----------------------------------------------------------------------------- mesh and binding checks


def check_mesh(mesh, name: str = "mesh.ply") -> tuple[object | None, dict]:
    """A mesh usable as the object's interior, or None (then the Gaussians define it), with a report.

    A watertight mesh is used as is. Otherwise trimesh's repairs are tried (merge vertices, fix
    winding and normals, fill holes); a mesh still not watertight is ignored (``used: false``): its
    ``contains`` test would leave much of the volume empty.
    """
    report = {"file": str(name), "watertight": bool(mesh.is_watertight), "repaired": False, "used": True}
    if mesh.is_watertight:
        return mesh, report
    import trimesh

    fixed = mesh.copy()
    fixed.merge_vertices()
    trimesh.repair.fix_winding(fixed)
    trimesh.repair.fix_normals(fixed)
    trimesh.repair.fill_holes(fixed)
    if fixed.is_watertight and fixed.volume > 0:
        report.update(repaired=True, reason="not watertight; repaired by trimesh (holes filled)")
        return fixed, report
    report.update(used=False, reason="not watertight and trimesh could not repair it: ignored, "
                                     "the interior comes from the Gaussians")
    return None, report


def binding_share(particles, cloud: GaussianCloud, chi2: float) -> dict:
    """How many kept Gaussians have a particle within their Mahalanobis bound d^T Sigma^-1 d <= chi2.

    The others were bound to their nearest particle as a fallback (``particles.unbound: nearest``).

    Args:
        particles: :class:`gca.assets.particles.Particles` made from ``cloud``.
        cloud: the scan the particles were made from (world frame).
        chi2: the bound used (``particles.mahalanobis_chi2``).

    Returns:
        ``{"share_bound_within_mahalanobis": float in [0, 1], "n_fallback_nearest": int}``.
    """
    from gca.assets.particles import apply_affine
    from gca.assets.ply import scales

    kept = cloud.subset(particles.gaussian_index)
    s = particles.sim_from_world[0, 0]
    means = apply_affine(particles.sim_from_world, kept.means)
    R = quats_to_rotmats(normalized_quats(kept))
    sig = np.maximum(scales(kept) * s, 1e-12)
    d = particles.x[particles.binding_cols].astype(np.float64) - means[particles.binding_rows]
    local = np.einsum("bji,bj->bi", R[particles.binding_rows], d)
    m = np.sum((local / sig[particles.binding_rows]) ** 2, axis=1)
    within = np.zeros(kept.n, bool)
    np.logical_or.at(within, particles.binding_rows, m <= chi2 * (1 + 1e-6))
    return {"share_bound_within_mahalanobis": float(within.mean()), "n_fallback_nearest": int((~within).sum())}
