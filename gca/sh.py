"""Real spherical harmonics of the 3DGS colour model (degrees 0..3): evaluation and rotation.

A Gaussian's colour seen along the unit direction ``d`` (from the camera centre to the Gaussian's
mean, in the frame the SH coefficients live in) is

    rgb(d) = SH_C0 * f_dc + sum_{l=1..deg} sum_m f_rest[l, m] * Y_lm(d) + 0.5,   clipped to [0, 1],

with the basis, signs and ordering of the reference 3DGS renderer (``Y_lm`` as polynomials of
``d = (x, y, z)``). ``f_rest`` is ``[G, K, 3]`` with ``K = (deg + 1)^2 - 1`` (see
:mod:`gca.assets.ply`). Rotating a scan by ``Q`` (x' = Q x) needs its SH coefficients rotated too, so
that rgb'(d') = rgb(Q^T d'): :func:`rotation_matrices` builds the per-band matrices numerically
(each band is closed under rotations, so a least-squares fit on 2(2l+1) directions is exact).
"""

from __future__ import annotations

import numpy as np
import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def basis(d, degree: int):
    """The SH basis of bands 1..``degree`` at unit directions ``d`` [N, 3] -> [N, K] (numpy or torch).

    Band 0 is left out (it is the constant SH_C0); K = (degree + 1)^2 - 1.
    """
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    cols = []
    if degree >= 1:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        cols += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                 SH_C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
                 SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                 SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    if isinstance(d, torch.Tensor):
        return torch.stack(cols, dim=1) if cols else d.new_zeros((len(d), 0))
    return np.stack(cols, axis=1) if cols else np.zeros((len(d), 0))


def degree_of(K: int) -> int:
    """SH degree of ``K`` rest coefficients per channel (0, 3, 8, 15 -> 0..3)."""
    degrees = {0: 0, 3: 1, 8: 2, 15: 3}
    if K not in degrees:
        raise ValueError(f"gca/sh.py: {K} SH rest coefficients per channel is no degree 0..3")
    return degrees[K]


def view_term(sh_rest: torch.Tensor, means: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """The view-dependent part of the colour, sum_l,m f_rest * Y_lm(d) [(T,) G, 3].

    Args:
        sh_rest: [G, K, 3] rest coefficients (frame of ``means``).
        means: [G, 3] Gaussian centres [m] (or [T, G, 3]: T frames); centre: [3] camera centre [m], same frame.
    """
    K = sh_rest.shape[1]
    if K == 0:
        return means.new_zeros((*means.shape[:-1], 3))
    d = means - centre.reshape(3)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    Y = basis(d.reshape(-1, 3), degree_of(K)).reshape(*d.shape[:-1], K)
    return torch.einsum("...gk,gkc->...gc", Y.to(sh_rest.dtype), sh_rest)


def rotation_matrices(Q: np.ndarray, degree: int) -> np.ndarray:
    """Block-diagonal matrix M [K, K] with rest' = M @ rest rotating SH coefficients by ``Q`` [3, 3].

    After the rotation, the colour along d' equals the old colour along Q^T d'.
    """
    Q = np.asarray(Q, np.float64)
    K = (degree + 1) ** 2 - 1
    M = np.zeros((K, K))
    rng = np.random.default_rng(0)
    start = 0
    for band in range(1, degree + 1):
        n = 2 * band + 1
        D = rng.standard_normal((4 * n, 3))
        D /= np.linalg.norm(D, axis=1, keepdims=True)
        sl = slice(start, start + n)
        B_new = basis(D, band)[:, sl]  # Y(d')
        B_old = basis(D @ Q, band)[:, sl]  # Y(Q^T d'): rows d'^T Q
        # sum_k c'_k Y_k(d') = sum_k c_k Y_k(Q^T d')  for all d'  =>  B_new M_l = B_old
        M[sl, sl] = np.linalg.lstsq(B_new, B_old, rcond=None)[0]
        start += n
    return M


def rotate_sh(sh_rest: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """SH rest coefficients [G, K, 3] rotated by ``Q`` [3, 3] (see :func:`rotation_matrices`)."""
    K = sh_rest.shape[1]
    if K == 0:
        return sh_rest.copy()
    M = rotation_matrices(Q, degree_of(K))
    return np.einsum("jk,gkc->gjc", M, sh_rest.astype(np.float64)).astype(sh_rest.dtype)
