"""Gaussians -> MPM particles: opacity filter, world -> sim map, volume sampling, masses, binding.

Pipeline of :func:`convert` (facts from PhysGaussian and NeuMA, code our own):

1. keep Gaussians with sigmoid(opacity) > ``opacity_threshold`` (PhysGaussian/NeuMA use 0.02);
2. ``sim_from_world``: uniform scale + translation placing the object's bounding box (the mesh's
   when there is one, else the kept Gaussian means') in the unit cube, ``margin`` from the side
   walls, resting ``floor_gap`` above the floor (``placement="floor"``) or centred;
3. particles on a regular lattice of cell centres ``(i + 1/2) * spacing`` (sim units) inside the
   object (with ``target_count`` N, each object's own spacing (V / N)^(1/3) from its volume V, so
   every object gets ~N particles whatever its size): inside the mesh when one exists
   (:func:`gca.assets.inside.mesh_contains`, vertical-ray parity in bounded memory);
   otherwise the summed opacity field of the Gaussians (covariances inflated by half a cell so thin
   surface sheets register) is thresholded, closed and hole-filled (scipy.ndimage);
4. volumes: uniform, total = mesh volume in sim units (mesh path) or the lattice estimate that
   counts the boundary layer by half (Gaussians-only path); masses = density * volume;
5. binding (NeuMA's Particle-GS): Gaussian k binds to the particles p with Mahalanobis distance
   d^T Sigma_k^-1 d <= chi2_3(0.95) = 7.815, at most ``max_bound`` of them (the closest), with
   uniform weights; an unbound Gaussian takes its nearest particle (``unbound="nearest"``) or gets
   an extra particle at its centre (``unbound="extra"``, NeuMA). Rows sum to 1.

Particles file (:func:`save_particles`, ``.npz``):

    x                [P, 3] float32  positions, sim frame [m]
    vol              [P]    float32  volumes, sim units [m^3]
    mass             [P]    float32  masses [kg] (density * vol)
    binding_rows     [B]    int64    row = index into ``gaussian_index`` (kept Gaussians)
    binding_cols     [B]    int64    particle index
    binding_weights  [B]    float32  weights; each row sums to 1
    sim_from_world   [4, 4] float64  x_sim = s * x_world + t
    gaussian_index   [G']   int64    indices of the kept Gaussians in the source .ply
    n_gaussians      []     int64    Gaussians in the source .ply
    spacing          []     float64  lattice spacing used [sim m]
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
from scipy.spatial import cKDTree

from gca.assets.inside import mesh_contains
from gca.assets.ply import GaussianCloud, normalized_quats, opacities, quats_to_rotmats, scales
from gca.io import InputError, atomic_path, load_arrays

CHI2_3_95 = 7.815  # chi-square quantile, 3 dof, 95 %
_CHUNK = 1 << 16  # lattice points per vectorised block (bounds memory)


@dataclasses.dataclass(frozen=True)
class ParticleConfig:
    """Knobs of the Gaussian -> particle conversion (``particles`` section of params.yaml)."""

    opacity_threshold: float = 0.02  # keep Gaussians with sigmoid(opacity) > this [1]
    spacing: float = 0.008  # particle lattice spacing [sim m]; paper ~0.008, CI ~0.03
    target_count: int = 0  # > 0: each object's own spacing, (volume / target_count)^(1/3), so every
    # object gets ~this many particles whatever its size; 0: the lattice at ``spacing`` [count]
    margin: float = 0.25  # min gap between the object's bounding box and the side walls [sim m]
    placement: str = "floor"  # "floor": rest floor_gap above y = 0; "centre": centre in the cube
    floor_gap: float = 0.08  # lowest point's height above the floor when placement = floor [sim m]
    density_threshold: float = 0.1  # Gaussians-only path: the band around the surface is where the
    # opacity field exceeds this fraction of its median at the Gaussian centres [1]; low = well sealed
    mahalanobis_chi2: float = CHI2_3_95  # binding bound on d^T Sigma^-1 d [1]
    max_bound: int = 10  # particles bound per Gaussian at most (NeuMA: 10)
    unbound: str = "nearest"  # unbound Gaussians: "nearest" particle or "extra" particle (NeuMA)
    n_candidates: int = 32  # Euclidean nearest neighbours examined per query [count]

    def __post_init__(self) -> None:
        checks = {"placement": self.placement in ("floor", "centre"), "unbound": self.unbound in ("nearest", "extra"),
                  "spacing": self.spacing > 0, "target_count": self.target_count >= 0, "margin": 0 <= self.margin < 0.5,
                  "max_bound": 1 <= self.max_bound <= self.n_candidates, "mahalanobis_chi2": self.mahalanobis_chi2 > 0}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"gca/assets/particles.py: invalid ParticleConfig field(s) {bad}: {self}")


@dataclasses.dataclass(frozen=True)
class Particles:
    """Simulation particles and their binding to the kept Gaussians (see the module docstring)."""

    x: np.ndarray
    vol: np.ndarray
    mass: np.ndarray
    binding_rows: np.ndarray
    binding_cols: np.ndarray
    binding_weights: np.ndarray
    sim_from_world: np.ndarray
    gaussian_index: np.ndarray
    n_gaussians: int
    spacing: float

    @property
    def n(self) -> int:
        return int(self.x.shape[0])

    def binding_matrix(self) -> sp.csr_matrix:
        """W [G', P] with Gaussian mean displacement = W @ particle displacement."""
        shape = (len(self.gaussian_index), self.n)
        return sp.csr_matrix((self.binding_weights, (self.binding_rows, self.binding_cols)), shape=shape)


# ----------------------------------------------------------------------------- world <-> sim


def fit_sim_from_world(lo: np.ndarray, hi: np.ndarray, cfg: ParticleConfig) -> np.ndarray:
    """The affine x_sim = s * x_world + t fitting the box [lo, hi] (world, m) into the unit cube.

    The largest side becomes ``1 - 2 * margin``; x and z are centred at 0.5; y is centred too
    (``placement="centre"``) or the bottom sits at ``floor_gap`` (``placement="floor"``).

    Returns:
        [4, 4] float64 matrix ``sim_from_world``.
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    assert lo.shape == hi.shape == (3,), (lo.shape, hi.shape)
    extent = float((hi - lo).max())
    if not extent > 0:
        raise ValueError(f"gca/assets/particles.py: degenerate bounding box {lo} .. {hi}")
    s = (1.0 - 2.0 * cfg.margin) / extent
    t = 0.5 - s * (lo + hi) / 2
    if cfg.placement == "floor":
        t[1] = cfg.floor_gap - s * lo[1]
    T = np.eye(4)
    T[:3, :3] *= s
    T[:3, 3] = t
    return T


def apply_affine(T: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points x [N, 3] mapped by the 4x4 affine T (e.g. ``sim_from_world``), float64."""
    assert T.shape == (4, 4) and x.ndim == 2 and x.shape[1] == 3, (T.shape, x.shape)
    return np.asarray(x, np.float64) @ T[:3, :3].T + T[:3, 3]


def world_from_sim(sim_from_world: np.ndarray) -> np.ndarray:
    """Inverse of a uniform-scale affine ``sim_from_world`` [4, 4]."""
    s = sim_from_world[0, 0]
    T = np.eye(4)
    T[:3, :3] /= s
    T[:3, 3] = -sim_from_world[:3, 3] / s
    return T


# ----------------------------------------------------------------------------- lattice sampling


def lattice(lo: np.ndarray, hi: np.ndarray, spacing: float, pad: int = 0) -> tuple[np.ndarray, tuple]:
    """Cell centres (i + 1/2) * spacing covering [lo, hi] (plus ``pad`` cells each side).

    Returns:
        (points [M, 3] in C order over the grid, grid shape (nx, ny, nz)).
    """
    i0 = np.floor(np.asarray(lo) / spacing).astype(int) - pad
    i1 = np.ceil(np.asarray(hi) / spacing).astype(int) + pad
    axes = [(np.arange(a, b) + 0.5) * spacing for a, b in zip(i0, i1)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    return grid.reshape(-1, 3), grid.shape[:3]


class LatticeTooLarge(ValueError):
    """The lattice an object would need is refused before it is allocated (:data:`MAX_LATTICE_CELLS`)."""


def lattice_cells(lo: np.ndarray, hi: np.ndarray, spacing: float, pad: int = 0) -> int:
    """The number of cells :func:`lattice` would make for [lo, hi], without making them."""
    i0 = np.floor(np.asarray(lo) / spacing).astype(np.int64) - pad
    i1 = np.ceil(np.asarray(hi) / spacing).astype(np.int64) + pad
    return int(np.prod((i1 - i0).astype(np.float64)))


def check_lattice(lo: np.ndarray, hi: np.ndarray, spacing: float, pad: int = 0) -> None:
    """Refuse a lattice over [lo, hi] of more than :data:`MAX_LATTICE_CELLS` cells (one line naming the size)."""
    cells = lattice_cells(lo, hi, spacing, pad)
    if cells > MAX_LATTICE_CELLS:
        extent = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
        raise LatticeTooLarge(f"gca/assets/particles.py: a lattice of {cells:.3g} cells at spacing {spacing:.4g} sim m "
                              f"over a box of {np.array2string(extent, precision=3)} sim m (more than "
                              f"{MAX_LATTICE_CELLS:.0e}): raise particles.spacing or lower target_count")


def sample_mesh_interior(mesh, sim_from_world: np.ndarray, spacing: float) -> np.ndarray:
    """Lattice points inside a watertight world mesh, in the sim frame [P, 3].

    The inside test is :func:`gca.assets.inside.mesh_contains` (vertical rays, memory bounded by its pair
    budget), not ``mesh.contains``: without embree, trimesh lists every (oblique ray, triangle box) pair of
    the whole lattice at once, ~330 B a pair; for the paper dragon (405k lattice points, ~500 triangles a
    ray) that was ~130 GB.
    """
    mesh_sim = mesh.copy().apply_transform(sim_from_world)
    check_lattice(*mesh_sim.bounds, spacing)
    points, _ = lattice(*mesh_sim.bounds, spacing)
    return points[mesh_contains(mesh_sim, points)]


def precisions(R: np.ndarray, sigmas: np.ndarray, inflate: float = 0.0) -> np.ndarray:
    """Upper triangles (xx, xy, xz, yy, yz, zz) of (Sigma + inflate^2 I)^-1, [G, 6].

    Args:
        R: [G, 3, 3] rotations; sigmas: [G, 3] stds along R's columns; inflate: isotropic std.
    """
    inv_var = 1.0 / (np.maximum(sigmas, 1e-12) ** 2 + inflate**2)
    A = np.einsum("gij,gj,gkj->gik", R, inv_var, R)
    return A[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]


def _mahalanobis(d: np.ndarray, A6: np.ndarray) -> np.ndarray:
    """d^T A d for d [..., 3] and packed symmetric A6 [..., 6] -> [...]."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return (A6[..., 0] * x * x + A6[..., 3] * y * y + A6[..., 5] * z * z
            + 2 * (A6[..., 1] * x * y + A6[..., 2] * x * z + A6[..., 4] * y * z))


def opacity_field(points: np.ndarray, means: np.ndarray, A6: np.ndarray, alphas: np.ndarray,
                  r_cut: float, n_candidates: int) -> np.ndarray:
    """Summed opacity field f(p) = sum_k alpha_k exp(-1/2 d^T A_k d), d = p - mu_k.

    Only the ``n_candidates`` nearest means within ``r_cut`` contribute to a point.

    Args:
        points: [M, 3] query points; means: [G, 3]; A6: [G, 6] packed precisions (see
            :func:`precisions`); alphas: [G] opacities; r_cut: neighbour radius (same units).

    Returns:
        [M] field values.
    """
    assert points.ndim == 2 and means.ndim == 2 and A6.shape == (len(means), 6) and alphas.shape == (len(means),)
    k, G = min(n_candidates, len(means)), len(means)
    tree = cKDTree(means)
    f = np.zeros(len(points))
    for start in range(0, len(points), _CHUNK):
        block = points[start:start + _CHUNK]
        _, index = tree.query(block, k=k, distance_upper_bound=r_cut)
        index = index.reshape(len(block), k)
        valid = index < G
        index = np.where(valid, index, 0)
        m = _mahalanobis(block[:, None, :] - means[index], A6[index])
        f[start:start + _CHUNK] = np.sum(np.where(valid, alphas[index] * np.exp(-0.5 * m), 0.0), axis=1)
    return f


def _solid_from_field(occupied: np.ndarray) -> np.ndarray:
    """Seal small gaps (closing), then fill enclosed cavities: the solid occupancy grid."""
    return ndi.binary_fill_holes(ndi.binary_closing(occupied, iterations=1))


REFINE = (2, 3, 4)  # finer analysis lattices (h / k) tried where the particle lattice is too coarse for the object's
# thickness (its surface band leaves no core: the fish at the CI profile's 3-cm spacing, session 29)


def _band_solid(means: np.ndarray, R: np.ndarray, sigmas: np.ndarray, alphas: np.ndarray, cfg: ParticleConfig,
                g: float, pad: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The field's solid on a lattice of spacing ``g`` [sim m]: (points [M, 3], solid [nx, ny, nz] bool, depth
    [nx, ny, nz] [cells of g] to the nearest outside cell centre, b = the surface's median depth [cells of g])."""
    A6 = precisions(R, sigmas, inflate=g / 2)
    r_cut = 3.0 * float(np.sqrt(np.quantile((sigmas**2).max(axis=1), 0.99) + (g / 2) ** 2))
    field = lambda p: opacity_field(p, means, A6, alphas, r_cut, cfg.n_candidates)  # noqa: E731
    check_lattice(means.min(axis=0), means.max(axis=0), g, pad=pad)
    points, shape = lattice(means.min(axis=0), means.max(axis=0), g, pad=pad)
    level = cfg.density_threshold * float(np.median(field(means)))
    solid = _solid_from_field((field(points) > level).reshape(shape))
    depth = ndi.distance_transform_edt(solid)
    b = float(np.median(ndi.map_coordinates(depth, ((means - points[0]) / g).T, order=1)))
    return points, solid, depth, b


def _band_volume(solid: np.ndarray, depth: np.ndarray, b: float, g: float) -> float:
    """The enclosed volume [sim m^3]: the solid's cells counted fractionally around the surface depth ``b`` [cells]."""
    return float(np.clip(depth - b + 0.5, 0.0, 1.0)[solid].sum()) * g**3


def _encloses(depth: np.ndarray, b: float) -> bool:
    """Whether the solid has a core deeper than its surface band (else the flood fill leaked, or the lattice is too
    coarse for the object's thickness)."""
    return depth.max() >= 2 * b + 1


def sample_gaussian_interior(means: np.ndarray, R: np.ndarray, sigmas: np.ndarray, alphas: np.ndarray,
                             cfg: ParticleConfig) -> tuple[np.ndarray, float]:
    """Lattice points inside the volume the Gaussians enclose (no mesh), sim frame.

    The thresholded field marks a band around the surface, which hole filling turns into a solid S.
    The surface lies inside the band: its depth ``b`` below the outer boundary of S is the median,
    over the Gaussians (mostly surface ones in a scan), of the distance to the outside. Particles
    are the cells at least ``b`` deep; the volume counts the cells around depth ``b`` fractionally.

    Where the particle lattice (``cfg.spacing`` = h) is too coarse for the object's thickness (the band, a cell or
    two deep from each side, leaves no core), the band is analysed again on a finer lattice h / k (k in
    :data:`REFINE`, while h / k is no finer than the Gaussians' median nearest-neighbour distance: finer, the band
    has gaps, a leak no refinement seals): the particles are then the h-lattice points whose depth, interpolated
    from the fine lattice, is at least ``b``, and the volume is the fine lattice's. An object that encloses a core
    at h takes the h lattice alone (unchanged results).

    Returns:
        (points [P, 3], volume estimate [sim m^3]).
    """
    h = cfg.spacing
    points, solid, depth, b = _band_solid(means, R, sigmas, alphas, cfg, h, 3)
    if _encloses(depth, b):
        return points[(depth >= b).reshape(-1) & solid.reshape(-1)], _band_volume(solid, depth, b, h)
    coarse = (depth.max(), b)
    gap = float(np.median(cKDTree(means).query(means, k=2)[0][:, 1]))  # the Gaussians' typical spacing [sim m]
    for k in REFINE:
        g = h / k
        if g < gap:  # a lattice finer than the Gaussians' spacing sees the gaps between them: it leaks, not seals
            break
        try:
            fine, solid, depth, b = _band_solid(means, R, sigmas, alphas, cfg, g, 3 * k)
        except LatticeTooLarge:
            break
        if _encloses(depth, b):
            d = ndi.map_coordinates(depth, ((points - fine[0]) / g).T, order=1, cval=0.0)  # depth at the h points
            return points[d >= b], _band_volume(solid, depth, b, g)
    finer = f"; none on lattices down to h/{max(REFINE)} either" if REFINE else ""
    raise ValueError(f"gca/assets/particles.py: the Gaussians' surface band did not enclose a volume (max depth "
                     f"{coarse[0]:.1f} cells, surface depth {coarse[1]:.1f}{finer}): spacing {h:.4g} sim m is too fine "
                     f"for the Gaussian density (raise particles.spacing), or density_threshold "
                     f"{cfg.density_threshold} too high (lower it); a thin or open scan may need its mesh")


# ----------------------------------------------------------------------------- binding


def bind_gaussians(means: np.ndarray, R: np.ndarray, sigmas: np.ndarray, x: np.ndarray,
                   cfg: ParticleConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sparse binding of Gaussians to particles (NeuMA Particle-GS), vectorised.

    Gaussian k binds to the (at most ``max_bound``) particles with the smallest Mahalanobis
    distance d^T Sigma_k^-1 d <= ``mahalanobis_chi2``, chosen among its ``n_candidates``
    Euclidean-nearest particles, with uniform weights. A Gaussian with none binds to its nearest
    particle (weight 1) and is reported as unbound.

    Args:
        means: [G, 3] Gaussian centres; R: [G, 3, 3] rotations; sigmas: [G, 3] stds (sim units).
        x: [P, 3] particle positions (sim units).
        cfg: binding knobs.

    Returns:
        (rows [B], cols [B], weights [B], unbound [G] bool); each row's weights sum to 1.
    """
    assert means.ndim == 2 and means.shape[1] == 3 and R.shape == (len(means), 3, 3) and sigmas.shape == means.shape
    assert x.ndim == 2 and x.shape[1] == 3 and len(x) > 0, x.shape
    k = min(cfg.n_candidates, len(x))
    _, index = cKDTree(x).query(means, k=k)
    index = index.reshape(len(means), k)  # sorted by Euclidean distance: column 0 is the nearest
    d = x[index] - means[:, None, :]
    local = np.einsum("gji,gkj->gki", R, d)
    m = np.sum(local**2 / np.maximum(sigmas, 1e-12)[:, None, :] ** 2, axis=2)  # [G, K] Mahalanobis^2
    m = np.where(m <= cfg.mahalanobis_chi2, m, np.inf)
    order = np.argsort(m, axis=1, kind="stable")[:, :cfg.max_bound]
    chosen = np.take_along_axis(index, order, axis=1)
    valid = np.isfinite(np.take_along_axis(m, order, axis=1))
    unbound = ~valid[:, 0]
    valid[unbound, 0] = True  # fallback: the Euclidean-nearest particle ...
    chosen[unbound, 0] = index[unbound, 0]
    rows, slots = np.nonzero(valid)
    counts = valid.sum(axis=1)
    return rows, chosen[rows, slots], 1.0 / counts[rows], unbound


# ----------------------------------------------------------------------------- conversion


def _kept_gaussians(cloud: GaussianCloud, cfg: ParticleConfig) -> np.ndarray:
    keep = np.nonzero(opacities(cloud) > cfg.opacity_threshold)[0]
    if len(keep) == 0:
        raise ValueError(f"gca/assets/particles.py: no Gaussian has opacity > {cfg.opacity_threshold} "
                         f"(of {cloud.n}); lower particles.opacity_threshold")
    return keep


OUTLIER_QUANTILE = 0.001  # the bulk of a scan: its means between these per-axis quantiles [1]
OUTLIER_BOX_FACTOR = 2.0  # a bounding box this many times the bulk's is the outliers' [1]
MAX_LATTICE_CELLS = 50_000_000  # larger lattices are refused before they are allocated [count]


def check_bounding_box(means: np.ndarray, name: str = "the scan") -> None:
    """Refuse a bounding box set by a few outlying Gaussians (floaters, a Gaussian at 1e30 m).

    The conversion scales the means' bounding box into the unit cube; a few far Gaussians shrink the
    object to a few lattice cells, and no spacing or density threshold helps. The bulk is the box of
    the per-axis ``OUTLIER_QUANTILE`` .. ``1 - OUTLIER_QUANTILE`` quantiles; a full box more than
    ``OUTLIER_BOX_FACTOR`` times larger than the bulk's along any axis is refused.

    Args:
        means: [G, 3] Gaussian centres (world frame).
        name: what to call the scan in the message.

    Raises:
        ValueError: naming how many Gaussians lie outside the bulk, how far, and the fix.
    """
    x = np.asarray(means, dtype=np.float64)
    if len(x) < 100:
        return
    lo, hi = np.quantile(x, OUTLIER_QUANTILE, axis=0), np.quantile(x, 1 - OUTLIER_QUANTILE, axis=0)
    bulk = np.maximum(hi - lo, 1e-12 * max(1.0, float(np.abs(x).max())))
    full = x.max(axis=0) - x.min(axis=0)
    ratio = full / bulk
    if ratio.max() > OUTLIER_BOX_FACTOR:
        pad = (OUTLIER_BOX_FACTOR - 1) / 2 * bulk
        outside = np.any((x < lo - pad) | (x > hi + pad), axis=1)
        far = float(np.linalg.norm(x - (lo + hi) / 2, axis=1).max())
        raise ValueError(f"{name}: {int(outside.sum())} of {len(x)} Gaussians lie far outside the bulk of the scan "
                         f"(bounding box {ratio.max():.3g}x the bulk's, the farthest {far:.3g} m from its centre): "
                         f"floaters or outliers set the object's size, so no spacing or density_threshold can help; "
                         f"remove them (a capture object's scan_options: far_factor, outlier_factor, min_component, "
                         f"crop; gca.assets.scan.prepare_scan)")


def convert(cloud: GaussianCloud, cfg: ParticleConfig, density: float, mesh=None) -> Particles:
    """Turn a static 3DGS scan (and optionally its watertight mesh) into simulation particles.

    Args:
        cloud: the Gaussians (world frame, metres).
        cfg: conversion knobs.
        density: material density [kg/m^3]; mass = density * vol (vol in sim m^3).
        mesh: optional watertight ``trimesh.Trimesh`` in the same world frame; when given it
            defines the bounding box, the interior and the total volume.

    Returns:
        :class:`Particles`.
    """
    if not density > 0:
        raise ValueError(f"gca/assets/particles.py: density must be > 0 kg/m^3, got {density}")
    keep = _kept_gaussians(cloud, cfg)
    kept = cloud.subset(keep)
    if mesh is None:
        check_bounding_box(kept.means)
    lo, hi = (mesh.bounds if mesh is not None else (kept.means.min(axis=0), kept.means.max(axis=0)))
    T = fit_sim_from_world(lo, hi, cfg)
    s = T[0, 0]
    means, R, sigmas = apply_affine(T, kept.means), quats_to_rotmats(normalized_quats(kept)), scales(kept) * s
    if mesh is not None:
        volume = float(mesh.volume) * s**3
        h = lattice_spacing(cfg, volume)
        x = sample_mesh_interior(mesh, T, h)
    else:  # the volume comes from the field sampled at ``spacing``; resampled at the object's own spacing
        alphas = opacities(kept)
        x, volume = sample_gaussian_interior(means, R, sigmas, alphas, cfg)
        h = lattice_spacing(cfg, volume)
        if h != cfg.spacing:
            x, volume = sample_gaussian_interior(means, R, sigmas, alphas, dataclasses.replace(cfg, spacing=h))
    if len(x) == 0:
        raise ValueError(f"gca/assets/particles.py: no lattice point inside the object: spacing {h:.4g} "
                         f"is too coarse for its size {(hi - lo).max() * s:.3g} (sim m)")
    rows, cols, weights, unbound = bind_gaussians(means, R, sigmas, x, cfg)
    if cfg.unbound == "extra" and unbound.any():
        x = np.concatenate([x, means[unbound]])
        rows, cols, weights, unbound = bind_gaussians(means, R, sigmas, x, cfg)
    vol = np.full(len(x), volume / len(x))
    return Particles(x=x.astype(np.float32), vol=vol.astype(np.float32), mass=(density * vol).astype(np.float32),
                     binding_rows=rows.astype(np.int64), binding_cols=cols.astype(np.int64),
                     binding_weights=weights.astype(np.float32), sim_from_world=T, gaussian_index=keep.astype(np.int64),
                     n_gaussians=cloud.n, spacing=float(h))


def lattice_spacing(cfg: ParticleConfig, volume: float) -> float:
    """The lattice spacing [sim m] for an object of ``volume`` [sim m^3]: ``cfg.spacing``, or with a
    ``target_count`` N the spacing whose cubic cells tile the volume N times, (volume / N)^(1/3)."""
    if cfg.target_count <= 0:
        return cfg.spacing
    if not volume > 0:
        raise ValueError(f"gca/assets/particles.py: object volume {volume} sim m^3: cannot size a lattice for "
                         f"target_count {cfg.target_count}")
    return float((volume / cfg.target_count) ** (1.0 / 3.0))


# ----------------------------------------------------------------------------- files


def save_particles(path: str | os.PathLike, particles: Particles) -> Path:
    """Write the particles ``.npz`` (keys in the module docstring; atomic)."""
    path = Path(path)
    arrays = {f.name: np.asarray(getattr(particles, f.name)) for f in dataclasses.fields(particles)}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return path


def load_particles(path: str | os.PathLike) -> Particles:
    """Read a particles ``.npz``, naming the file and the key in any error."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: particles file not found")
    data = load_arrays(path, "particles file")
    missing = [f.name for f in dataclasses.fields(Particles) if f.name not in data]
    if missing:
        raise InputError(f"{path}: particles file lacks key(s) {missing}")
    values = {f.name: data[f.name] for f in dataclasses.fields(Particles)}
    values["n_gaussians"], values["spacing"] = int(values["n_gaussians"]), float(values["spacing"])
    return Particles(**values)
