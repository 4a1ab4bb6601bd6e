"""Synthetic "as captured" 3DGS scans for tests and the worked example: a torus of Gaussians with
the defects a real capture has (floaters, a far-away outlier), in a world frame of the caller's choice.

The torus (major radius ``R``, minor radius ``r``, metres) lies flat in the world's x-z plane when
``up="y"`` (its axis along +y) or the x-y plane when ``up="z"`` (axis along +z, the COLMAP/OpenCV
habit of a z-up capture). Surface Gaussians are flat discs tangent to the surface (std ``r / 8`` in
the tangent plane, ``r / 80`` along the normal); a tenth of them sit inside the tube.
"""

from __future__ import annotations

import numpy as np

from gca.assets.ply import SH_REST_COUNTS, GaussianCloud, rgb_to_sh0, rotmats_to_quats


def torus_volume(R: float, r: float) -> float:
    """Volume of a torus, 2 pi^2 R r^2 [m^3] for radii in metres."""
    return 2.0 * np.pi**2 * R * r**2


def torus_scan(n: int = 6000, R: float = 0.05, r: float = 0.02, up: str = "y", n_floaters: int = 0,
               far_outlier: float | None = None, sh_degree: int = 0, seed: int = 0,
               floater_box: float = 4.0) -> GaussianCloud:
    """A torus of ``n`` Gaussians plus defects.

    Args:
        n: Gaussians on and inside the torus [count].
        R, r: major and minor radius [m].
        up: ``"y"`` or ``"z"``: the torus axis (it lies flat on the plane normal to it).
        n_floaters: extra small, opaque Gaussians scattered uniformly in a cube of side
            ``floater_box * (R + r)`` around the torus (never closer than ``r`` to the tube) [count].
        far_outlier: when given, one more Gaussian at ``(far_outlier, 0, 0)`` [m] (e.g. 1e30).
        sh_degree: SH degree 0..3 stored; the higher bands carry a view-dependent tint.
        seed: RNG seed.

    Returns:
        The :class:`GaussianCloud`; the torus Gaussians come first, then the floaters, then the outlier.
    """
    if up not in ("y", "z"):
        raise ValueError(f"torus_scan: up must be 'y' or 'z', got {up!r}")
    rng = np.random.default_rng(seed)
    n_in = n // 10
    u, v = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n)
    rho = np.where(np.arange(n) < n - n_in, r, r * np.sqrt(rng.uniform(0, 0.8, n)))
    ring = np.stack([np.cos(u), np.zeros(n), np.sin(u)], 1)  # direction to the tube centre (y-up frame)
    normal = np.cos(v)[:, None] * ring + np.sin(v)[:, None] * np.array([0.0, 1.0, 0.0])
    means = R * ring + rho[:, None] * normal
    tangent_u = np.stack([-np.sin(u), np.zeros(n), np.cos(u)], 1)
    tangent_v = np.cross(normal, tangent_u)
    rot = np.stack([tangent_u, tangent_v, normal], axis=2)  # columns: local axes
    sig = np.tile([r / 8, r / 8, r / 80], (n, 1))
    sig[n - n_in:] = r / 6
    colour = 0.5 + 0.4 * np.stack([np.cos(u), np.sin(v), np.cos(u + v)], 1)
    if n_floaters:
        half = floater_box * (R + r) / 2
        f = rng.uniform(-half, half, (4 * n_floaters, 3))
        dist_to_tube = np.hypot(np.hypot(f[:, 0], f[:, 2]) - R, f[:, 1])
        f = f[dist_to_tube > 2 * r][:n_floaters]
        assert len(f) == n_floaters
        means = np.concatenate([means, f])
        rot = np.concatenate([rot, np.tile(np.eye(3), (n_floaters, 1, 1))])
        sig = np.concatenate([sig, np.full((n_floaters, 3), r / 10)])
        colour = np.concatenate([colour, np.full((n_floaters, 3), 0.9)])
    if far_outlier is not None:
        means = np.concatenate([means, [[far_outlier, 0.0, 0.0]]])
        rot = np.concatenate([rot, np.eye(3)[None]])
        sig = np.concatenate([sig, [[r / 10] * 3]])
        colour = np.concatenate([colour, [[0.5, 0.5, 0.5]]])
    if up == "z":  # y-up -> z-up: (x, y, z) -> (x, -z, y), a proper rotation
        to_z = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
        means, rot = means @ to_z.T, to_z @ rot
    G, K = len(means), SH_REST_COUNTS[sh_degree]
    rest = np.zeros((G, K, 3), np.float32)
    if K:
        rest[:, 0] = 0.3 * rng.standard_normal(3)  # a tint along the first band-1 basis function
    return GaussianCloud(means=means.astype(np.float32), normals=np.zeros((G, 3), np.float32),
                         sh_dc=rgb_to_sh0(colour).astype(np.float32), sh_rest=rest,
                         opacity_logit=np.full(G, 3.0, np.float32), log_scales=np.log(sig).astype(np.float32),
                         quats_wxyz=rotmats_to_quats(rot).astype(np.float32))
