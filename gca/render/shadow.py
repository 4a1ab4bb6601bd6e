"""Shadows from the Gaussians' own occupancy, seen from a directional light (issue 21, item 2).

A light-space occupancy grid (a shadow map with depth bins): with ``l`` the unit direction toward the
light and (u, v) an orthonormal basis of the plane normal to it, each Gaussian i (centre mu_i, covariance
Sigma_i, opacity o_i) adds the optical depth

    c_i = o_i * 2 pi r_i^2 / h^2,    r_i^2 = tr(Sigma_i) / 3

to its (u, v) cell of side h (its alpha integrated over the plane, an isotropic stand-in for its footprint,
per cell area), binned by its light-space depth w = mu_i . l.
A point p is lit through the transmittance of everything strictly nearer the light in its column:

    V(p) = exp(- sum_{Gaussians j in p's column, w_j > w(p) + h} c_j)

(the column's coverage blurred by a 3x3 box in (u, v) against aliasing). The own bin is left out, so a
Gaussian does not shadow itself; a floor point below the object gets the whole column: the cast shadow.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

_WHERE = "gca/render/shadow.py"


def light_basis(direction: torch.Tensor) -> torch.Tensor:
    """Rows (u, v, l) [3, 3]: an orthonormal basis whose last row is the unit light direction."""
    l = F.normalize(direction, dim=0)
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=l.dtype, device=l.device)
    if abs(float(l[0])) > 0.9:
        helper = torch.tensor([0.0, 0.0, 1.0], dtype=l.dtype, device=l.device)
    u = F.normalize(torch.linalg.cross(helper, l), dim=0)
    v = torch.linalg.cross(l, u)
    return torch.stack([u, v, l])


def light_visibility(means: torch.Tensor, covs: torch.Tensor, opacities: torch.Tensor, direction,
                     resolution: int = 48, points: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Visibility from the light of each Gaussian and of extra points (module docstring).

    Args:
        means: Gaussian centres [N, 3] (sim frame).
        covs: covariances [N, 3, 3].
        opacities: [N] in [0, 1].
        direction: unit direction toward the light [3] (sequence or tensor).
        resolution: (u, v) cells across the Gaussians' extent (fewer where a cell would be narrower than a
            median Gaussian's 2-sigma width), and depth bins along l [count].
        points: extra points [M, 3] (e.g. floor points seen by background pixels), or None.

    Returns:
        (V [N] in (0, 1], V_points [M] or None).
    """
    if means.ndim != 2 or means.shape[1] != 3 or covs.shape != (means.shape[0], 3, 3):
        raise ValueError(f"{_WHERE}: means [N, 3] and covs [N, 3, 3] expected, got {tuple(means.shape)}, {tuple(covs.shape)}")
    dtype, device = means.dtype, means.device
    basis = light_basis(torch.as_tensor(direction, dtype=dtype, device=device))
    q = means @ basis.T                                         # [N, 3] light-space (u, v, w)
    lo, hi = q.min(0).values, q.max(0).values
    r2 = torch.diagonal(covs, dim1=-2, dim2=-1).sum(-1) / 3.0
    # cells no smaller than a typical Gaussian's 2-sigma width, so a surface of Gaussians has no gaps
    h = max(float((hi[:2] - lo[:2]).max()) / resolution, 2.0 * float(r2.median().sqrt())) + 1e-9
    cells = int(math.ceil(float((hi[:2] - lo[:2]).max()) / h)) + 3          # margin cells each side
    origin = lo[:2] - h
    ij = ((q[:, :2] - origin) / h).floor().long().clamp(0, cells - 1)
    dw = float(hi[2] - lo[2]) / resolution + 1e-9
    k = ((q[:, 2] - lo[2]) / dw).floor().long().clamp(0, resolution - 1)
    cover = opacities.to(dtype) * 2.0 * math.pi * r2 / h ** 2
    grid = torch.zeros(cells * cells * resolution, dtype=dtype, device=device)
    grid.index_add_(0, (ij[:, 0] * cells + ij[:, 1]) * resolution + k, cover)
    grid = grid.view(cells, cells, resolution).permute(2, 0, 1)[:, None]      # [K, 1, cells, cells]
    grid = F.avg_pool2d(grid, 3, stride=1, padding=1, count_include_pad=True)[:, 0] * 1.0
    # in front of bin k (nearer the light): bins k+2.. (the own and adjacent bins are left out)
    rev = torch.flip(torch.cumsum(torch.flip(grid, [0]), 0), [0])            # rev[k] = sum_{k' >= k}
    front = torch.cat([rev[2:], torch.zeros_like(rev[:2])], 0)                # front[k] = sum_{k' >= k+2}
    vis = torch.exp(-front[k, ij[:, 0], ij[:, 1]])
    vis_points = None
    if points is not None:
        qp = points.to(dtype) @ basis.T
        ijp = ((qp[:, :2] - origin) / h).floor().long()
        inside = ((ijp >= 0) & (ijp < cells)).all(-1)
        kp = ((qp[:, 2] - lo[2]) / dw).floor().long()
        tau = torch.zeros(points.shape[0], dtype=dtype, device=device)
        ijc = ijp.clamp(0, cells - 1)
        kc = (kp + 2).clamp(0, resolution)                                  # below the grid: the whole column
        full = torch.cat([rev, torch.zeros_like(rev[:1])], 0)
        tau = torch.where(inside, full[kc, ijc[:, 0], ijc[:, 1]], tau)
        vis_points = torch.exp(-tau)
    return vis, vis_points
