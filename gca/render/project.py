"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (Zwicker et al. 2001, as in 3DGS).

For a Gaussian with world mean ``mu`` and covariance ``Sigma`` seen by a camera ``(K, W = w2c)``:

    t = R mu + r                                     camera-space mean, z = t_z (the depth)
    J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]  Jacobian of the perspective map at t
    Sigma_2d = J R Sigma R^T J^T + eps2d I           (eps2d = 0.3 px^2: the 3DGS low-pass dilation)
    mean_2d = (fx tx/z + cx, fy ty/z + cy)

As in 3DGS/gsplat, ``tx/z`` and ``ty/z`` inside ``J`` (not in ``mean_2d``) are clamped to 1.3x the
half field of view so that Gaussians far off-screen do not get huge footprints.

The blurred determinant is formed as ``det = max(det0, 0) + eps2d (a0 + c0) + eps2d^2`` from the
un-blurred ``Sigma_2d0 = [[a0, b0], [b0, c0]]``, ``det0 = a0 c0 - b0^2``: algebraically the same
``(a0 + eps2d)(c0 + eps2d) - b0^2``, but ``det0`` of a positive semi-definite ``Sigma_2d0`` is >= 0 and
only rounding makes it negative. For a large, thin footprint (``F Sigma0 F^T`` of a near-singular F seen
edge on) the float32 cancellation in ``a c - b^2`` exceeds the blur's share and the naive determinant
goes to ~0 or below: the conic (its inverse) and its gradient (~1/det^2) overflow. With the floor,
``det >= eps2d (a + c - eps2d)`` and the conic stays bounded. :func:`covariance_health` flags the
Gaussians where gsplat's float32 arithmetic (which has no such floor) is unreliable.
"""

from __future__ import annotations

import dataclasses

import torch


@dataclasses.dataclass(frozen=True)
class Projected:
    """Screen-space Gaussians, all [N, ...] in the input's order.

    Attributes:
        means2d: pixel-space centres [N, 2] (pixel centres at i + 0.5).
        conics: inverse 2D covariances as (A, B, C) [N, 3], power = A dx^2/2 + B dx dy + C dy^2/2.
        depths: camera-space z of the means [N] (world units).
        radii: screen-space extent [N] (pixels, ``sigma_cutoff`` x the largest std; detached).
        valid: in front of the near plane, before the far plane, non-degenerate [N] bool.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    valid: torch.Tensor


def _jacobian(t: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Perspective Jacobian [N, 2, 3] at camera-space points ``t`` [N, 3] (gsplat-style clamp)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = t[:, 2]
    lim_x_pos = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * height / fy)
    tx = z * torch.minimum(torch.maximum(t[:, 0] / z, -lim_x_neg), lim_x_pos)
    ty = z * torch.minimum(torch.maximum(t[:, 1] / z, -lim_y_neg), lim_y_pos)
    zeros = torch.zeros_like(z)
    row0 = torch.stack([fx / z, zeros, -fx * tx / z**2], dim=-1)
    row1 = torch.stack([zeros, fy / z, -fy * ty / z**2], dim=-1)
    return torch.stack([row0, row1], dim=-2)


def project_gaussians(means: torch.Tensor, covs: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor,
                      width: int, height: int, near: float = 0.01, far: float = 1e10,
                      eps2d: float = 0.3, sigma_cutoff: float = 3.0) -> Projected:
    """EWA-project Gaussians (differentiable w.r.t. ``means`` and ``covs``).

    Args:
        means: world means [N, 3].
        covs: world covariances [N, 3, 3] (symmetrised here: 0.5 (Sigma + Sigma^T)).
        K: intrinsics [3, 3] (pixels); w2c: world-to-camera [4, 4] (OpenCV).
        width, height: image size [pixels].
        near, far: clipping planes on camera z (world units).
        eps2d: low-pass dilation added to the 2D covariance [pixels^2].
        sigma_cutoff: extent of a Gaussian in standard deviations (radius and alpha cut-off).

    Returns:
        :class:`Projected`.
    """
    R, r = w2c[:3, :3], w2c[:3, 3]
    t = means @ R.T + r
    z = t[:, 2]
    valid = (z > near) & (z < far)
    z_safe = torch.where(valid, z, torch.ones_like(z))
    t_safe = torch.cat([t[:, :2], z_safe[:, None]], dim=-1)
    J = _jacobian(t_safe, K, width, height)
    cov_cam = R @ (0.5 * (covs + covs.transpose(-1, -2))) @ R.T
    cov2d = J @ cov_cam @ J.transpose(-1, -2)
    a0, c0 = cov2d[:, 0, 0], cov2d[:, 1, 1]
    b = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])
    a, c = a0 + eps2d, c0 + eps2d
    det = (a0 * c0 - b * b).clamp_min(0.0) + eps2d * (a0 + c0) + eps2d * eps2d
    valid = valid & (det > 0)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    means2d = t_safe[:, :2] / z_safe[:, None] * K.diagonal()[:2] + K[:2, 2]
    with torch.no_grad():
        lam_max = 0.5 * (a + c) + torch.sqrt((0.25 * (a - c) ** 2 + b * b).clamp_min(0.0))
        radii = torch.where(valid, sigma_cutoff * torch.sqrt(lam_max.clamp_min(0.0)), torch.zeros_like(a))
    return Projected(means2d=means2d, conics=conics, depths=z, radii=radii, valid=valid)


def covariance_health(means: torch.Tensor, covs: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor,
                      width: int, height: int, eps2d: float = 0.3, near: float = 0.01,
                      rel_tol: float = 1e-6) -> dict[str, torch.Tensor]:
    """Which Gaussians a float32 rasterizer (gsplat's projection kernel) cannot handle reliably.

    Evaluated in float64 (no gradients), per Gaussian [N] bool:

    - ``not_spd``: the symmetrised 3D covariance has an eigenvalue below ``-rel_tol * trace`` (not a
      covariance; F Sigma0 F^T is PSD in exact arithmetic) or a non-finite entry;
    - ``singular``: its smallest eigenvalue is <= ``rel_tol * trace`` (rank-deficient: a flattened or
      collapsed Gaussian, e.g. from a near-singular deformation gradient);
    - ``det_unreliable``: in front of the camera, and gsplat's float32 ``(a0 + eps2d)(c0 + eps2d) - b0^2``
      carries a rounding error (``~2 eps_f32 (|a c| + b^2)``) larger than half the exact blurred
      determinant: its conic and the conic's gradient (~1/det^2) are then garbage, possibly inf/NaN;
    - ``culled_by_det``: gsplat would compute det <= 0 in float32 and drop the Gaussian (our torch
      path keeps it: the two backends then disagree).

    Args: as :func:`project_gaussians`. Returns: the masks and ``"any"`` (their union).
    """
    with torch.no_grad():
        m64, c64 = means.detach().double(), covs.detach().double()
        sym = 0.5 * (c64 + c64.transpose(-1, -2))
        finite = torch.isfinite(sym).flatten(1).all(1)
        eig = torch.linalg.eigvalsh(torch.where(finite[:, None, None], sym, torch.eye(3, dtype=sym.dtype, device=sym.device)))
        scale = eig.abs().sum(-1).clamp_min(torch.finfo(torch.float64).tiny)
        not_spd = ~finite | (eig[:, 0] < -rel_tol * scale)
        singular = finite & (eig[:, 0] <= rel_tol * scale)
        K64, w64 = K.detach().double(), w2c.detach().double()
        R, r = w64[:3, :3], w64[:3, 3]
        t = m64 @ R.T + r
        front = t[:, 2] > near
        t_safe = torch.cat([t[:, :2], torch.where(front, t[:, 2], torch.ones_like(t[:, 2]))[:, None]], dim=-1)
        J = _jacobian(t_safe, K64, width, height)
        cov2d = J @ (R @ torch.where(finite[:, None, None], sym, torch.zeros_like(sym)) @ R.T) @ J.transpose(-1, -2)
        a, c = cov2d[:, 0, 0] + eps2d, cov2d[:, 1, 1] + eps2d
        b = cov2d[:, 0, 1]
        exact = (cov2d[:, 0, 0] * cov2d[:, 1, 1] - b * b).clamp_min(0.0) + eps2d * (a + c) - eps2d * eps2d
        a32, b32, c32 = a.float(), b.float(), c.float()
        det32 = (a32 * c32 - b32 * b32).double()
        err = 2.0 * torch.finfo(torch.float32).eps * ((a * c).abs() + b * b)
        det_unreliable = front & finite & (err > 0.5 * exact)
        culled = front & finite & (det32 <= 0)
    masks = {"not_spd": not_spd, "singular": singular, "det_unreliable": det_unreliable, "culled_by_det": culled}
    masks["any"] = not_spd | det_unreliable | culled
    return masks
