"""Batched 3x3 SVD with proper-rotation factors and gradients that stay finite at repeated values.

Forward (both entry points): ``F = U diag(sigma) Vh`` from one warp kernel (``gca.laws.svd_kernel``,
float32 and float64; sigma descending), or ``torch.linalg.svd`` where warp cannot compile CPU kernels,
then NCLaw's sign fix (reference notes §3.6): where det U < 0 the 3rd column of U and sigma_3 are
negated, and likewise for V, so that U and V are proper rotations. Under inversion (det F < 0)
sigma_3 is negative; |sigma_3| is still the smallest.

Backward. For F = U S V^T with orthogonal U, V and diagonal S (signed entries allowed), the VJP is

    v_F = U [ diag(v_sigma) + M ] V^T,   M_ij = (A_ij s_j + s_i B_ij) / (s_j^2 - s_i^2)   (i != j),
    A = U^T v_U - (U^T v_U)^T,   B = V^T v_V - (V^T v_V)^T

(Townsend 2016; torch ``svd_backward``). ``1/(s_j^2 - s_i^2)`` is infinite at repeated singular values,
and F = I at rest repeats all three. We split it into partial fractions,

    M_ij = 1/2 (A + B)_ij / (s_j - s_i)  +  1/2 (A - B)_ij / (s_j + s_i),

and clamp each denominator to magnitude >= ``eps`` keeping its sign. For losses that do not depend on
the arbitrary basis inside a repeated subspace, A + B -> 0 there and the first term stays bounded,
while the second (the polar-rotation part) is kept exactly. This differs from warp's ``adj_svd3`` /
NCLaw (``1 / min(s_j^2 - s_i^2, -1e-6)``), which at F = I multiplies rounding noise by 1e6 and drops
the rotation part.

Spectral maps. A generic SVD backward cannot recover the limit of (y_i - y_j)/(s_i - s_j) for a
function y(sigma) at repeated values (the information is not in the VJP). :func:`svd_map` therefore
differentiates the whole map F -> U diag(y(sigma)) Vh (or U diag(y) U^T) in one Function and uses
the exact limit (d y_i/d s_i - d y_i/d s_j) from the Jacobian of ``y``, so elastic/plastic laws have
exact gradients at F = I and under uniaxial stretch (two equal singular values).
"""

from __future__ import annotations

import functools
from typing import Callable

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from gca.laws.svd_kernel import WARP_FLOATS, svd3
from gca.linalg import bmm3, det3  # noqa: F401  (the laws import them from here)


def check_F(F: torch.Tensor, where: str) -> None:
    """Raise a clear error unless ``F`` is a floating [N, 3, 3] tensor."""
    if not isinstance(F, torch.Tensor) or F.ndim != 3 or tuple(F.shape[1:]) != (3, 3):
        shape = tuple(F.shape) if isinstance(F, torch.Tensor) else type(F).__name__
        raise ValueError(f"gca/laws: {where}: F must be a [N, 3, 3] tensor, got {shape}")
    if not F.dtype.is_floating_point:
        raise TypeError(f"gca/laws: {where}: F must be floating point, got {F.dtype}")


def default_eps(dtype: torch.dtype) -> float:
    """Denominator clamp of the backward: sqrt(machine eps) (3.5e-4 in float32, 1.5e-8 in float64)."""
    return float(torch.finfo(dtype).eps) ** 0.5


def _svd_rotations(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Forward SVD with the sign fix (no autograd). F [N,3,3] -> U [N,3,3], sigma [N,3], Vh [N,3,3].

    One warp kernel (``gca.laws.svd_kernel``, float32 or float64: no host sync, capturable in a CUDA
    graph, 7x faster than LAPACK on the CPU); :func:`torch_svd_rotations` on a CPU where warp has no
    compiler (GPU-only installs) and for other float types.
    """
    if warp_runs(F):
        return svd3(F)
    return torch_svd_rotations(F)


def warp_runs(F: torch.Tensor) -> bool:
    """Whether our warp kernels take ``F``: float32/float64 on CUDA, or on a CPU where warp compiles."""
    return F.dtype in WARP_FLOATS and (F.is_cuda or _warp_cpu())


@functools.cache
def _warp_cpu() -> bool:
    """Whether warp can compile CPU kernels here (a GPU-only install ships no CPU compiler)."""
    wp.init()
    return bool(wp.is_cpu_available())


def torch_svd_rotations(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference forward of :func:`_svd_rotations` through ``torch.linalg.svd`` (any float dtype)."""
    U, sigma, Vh = torch.linalg.svd(F.detach())
    flip_u = torch.where(det3(U) < 0, -1.0, 1.0).to(F.dtype)
    flip_v = torch.where(det3(Vh) < 0, -1.0, 1.0).to(F.dtype)
    U = torch.cat([U[:, :, :2], U[:, :, 2:] * flip_u[:, None, None]], dim=2)
    Vh = torch.cat([Vh[:, :2, :], Vh[:, 2:, :] * flip_v[:, None, None]], dim=1)
    sigma = torch.cat([sigma[:, :2], sigma[:, 2:] * (flip_u * flip_v)[:, None]], dim=1)
    return U, sigma, Vh


def _safe_reciprocal(d: torch.Tensor, eps: float) -> torch.Tensor:
    """1/d with |d| clamped to >= eps (sign kept, 0 counts as +); the diagonal [.., i, i] is zeroed."""
    sign = torch.where(d < 0, -1.0, 1.0).to(d.dtype)
    inv = 1.0 / (sign * d.abs().clamp(min=eps))
    return inv * (1.0 - torch.eye(3, dtype=d.dtype, device=d.device))


def _skew(X: torch.Tensor) -> torch.Tensor:
    return X - X.transpose(1, 2)


class _SVD(torch.autograd.Function):
    """U, sigma, Vh = svd(F) with the partial-fraction clamped backward (module docstring)."""

    @staticmethod
    def forward(ctx, F, eps):
        U, sigma, Vh = _svd_rotations(F)
        ctx.save_for_backward(U, sigma, Vh)
        ctx.eps = eps
        return U, sigma, Vh

    @staticmethod
    @once_differentiable
    def backward(ctx, v_U, v_sigma, v_Vh):
        U, sigma, Vh = ctx.saved_tensors
        V = Vh.transpose(1, 2)
        A = _skew(bmm3(U.transpose(1, 2), v_U))
        B = _skew(bmm3(V.transpose(1, 2), v_Vh.transpose(1, 2)))
        s_i, s_j = sigma[:, :, None], sigma[:, None, :]
        M = 0.5 * (A + B) * _safe_reciprocal(s_j - s_i, ctx.eps) \
            + 0.5 * (A - B) * _safe_reciprocal(s_j + s_i, ctx.eps)
        M = M + torch.diag_embed(v_sigma)
        return bmm3(bmm3(U, M), Vh), None


def svd(F: torch.Tensor, eps: float | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batched SVD with rotation-valued factors and a clamped, always-finite backward.

    Args:
        F: [N, 3, 3] matrices (float32/float64, CPU or CUDA).
        eps: backward denominator clamp; default sqrt(machine eps) of F's dtype.

    Returns:
        U [N, 3, 3] and Vh [N, 3, 3] with det = +1, sigma [N, 3] (descending; sigma_3 < 0 where
        det F < 0), such that F = U diag(sigma) Vh.
    """
    check_F(F, "svd")
    return _SVD.apply(F, default_eps(F.dtype) if eps is None else eps)


def _jacobian(fn: Callable, sigma: torch.Tensor, params: tuple) -> tuple[torch.Tensor, torch.Tensor, list]:
    """Evaluate y = fn(sigma, *params) with autograd on; returns (y [N,3], dy/dsigma [N,3,3], leaves)."""
    with torch.enable_grad():  # backward runs under no_grad
        s = sigma.detach().requires_grad_(True)
        leaves = [p.detach().requires_grad_(p.requires_grad) if isinstance(p, torch.Tensor) else p for p in params]
        y = torch.broadcast_to(fn(s, *leaves), sigma.shape)
        if not y.requires_grad:
            return y, torch.zeros(*sigma.shape, 3, dtype=sigma.dtype, device=sigma.device), leaves
        rows = []
        for a in range(3):
            (g,) = torch.autograd.grad(y[:, a].sum(), s, retain_graph=True, allow_unused=True)
            rows.append(torch.zeros_like(s) if g is None else g)
    return y, torch.stack(rows, dim=1), leaves


def _divided_difference(y: torch.Tensor, sigma: torch.Tensor, J: torch.Tensor, tol: float) -> torch.Tensor:
    """Gamma_ij = (y_i - y_j)/(s_i - s_j); where |s_i - s_j| <= tol the limit 1/2(J_ii + J_jj - J_ij - J_ji)."""
    d = sigma[:, :, None] - sigma[:, None, :]
    close = d.abs() <= tol
    quotient = (y[:, :, None] - y[:, None, :]) / torch.where(close, torch.ones_like(d), d)
    Jd = torch.diagonal(J, dim1=1, dim2=2)
    limit = 0.5 * (Jd[:, :, None] + Jd[:, None, :] - J - J.transpose(1, 2))
    return torch.where(close, limit, quotient)


def _sum_quotient(y: torch.Tensor, sigma: torch.Tensor, eps: float) -> torch.Tensor:
    """Gamma_ij = (y_i + y_j)/(s_i + s_j) with the denominator clamped (only 0 under inversion)."""
    s = sigma[:, :, None] + sigma[:, None, :]
    sign = torch.where(s < 0, -1.0, 1.0).to(s.dtype)
    return (y[:, :, None] + y[:, None, :]) / (sign * s.abs().clamp(min=eps))


def _spectral_core(X, y, sigma, J, eps):
    """M such that v_F = U M V^T for G = U diag(y) V^T with cotangent X = U^T v_G V. All [N,3,3]."""
    sym, skw = 0.5 * (X + X.transpose(1, 2)), 0.5 * (X - X.transpose(1, 2))
    off = 1.0 - torch.eye(3, dtype=X.dtype, device=X.device)
    M = (_divided_difference(y, sigma, J, eps) * sym + _sum_quotient(y, sigma, eps) * skw) * off
    v_y = torch.diagonal(X, dim1=1, dim2=2)
    return M + torch.diag_embed((v_y[:, :, None] * J).sum(dim=1)), v_y


class _SpectralMap(torch.autograd.Function):
    """G = U diag(fn(sigma)) Vh (left=False) or U diag(fn(sigma)) U^T (left=True); sigma is returned too."""

    @staticmethod
    def forward(ctx, F, fn, left, eps, *params):
        U, sigma, Vh = _svd_rotations(F)
        with torch.no_grad():
            y = torch.broadcast_to(fn(sigma, *params), sigma.shape)
        right = U.transpose(1, 2) if left else Vh
        ctx.save_for_backward(U, sigma, Vh, *[p if isinstance(p, torch.Tensor) else None for p in params])
        ctx.fn, ctx.left, ctx.eps, ctx.n_params = fn, left, eps, len(params)
        ctx.raw_params = [None if isinstance(p, torch.Tensor) else p for p in params]
        ctx.mark_non_differentiable(sigma)
        return bmm3(U * y[:, None, :], right), sigma

    @staticmethod
    @once_differentiable
    def backward(ctx, v_G, _v_sigma):
        U, sigma, Vh, *tensors = ctx.saved_tensors
        params = tuple(t if t is not None else r for t, r in zip(tensors, ctx.raw_params))
        y, J, leaves = _jacobian(ctx.fn, sigma, params)
        X = bmm3(bmm3(U.transpose(1, 2), v_G), U if ctx.left else Vh.transpose(1, 2))
        M, v_y = _spectral_core(X, y.detach(), sigma, J, ctx.eps)
        if ctx.left:  # G = (U diag(y) V^T)(U V^T)^T: add the rotation factor's share, cotangent X^T diag(y)
            R_cot = X.transpose(1, 2) * y.detach()[:, None, :]
            M = M + _sum_quotient(torch.ones_like(y), sigma, ctx.eps) * 0.5 * _skew(R_cot)
        grads = _param_grads(y, leaves, v_y, ctx.needs_input_grad[4:])
        return (bmm3(bmm3(U, M), Vh), None, None, None, *grads)


def _param_grads(y, leaves, v_y, needed) -> list:
    """VJPs of y = fn(sigma, *params) w.r.t. the tensor params that need them (cotangent v_y [N,3])."""
    wanted = [i for i, (p, need) in enumerate(zip(leaves, needed)) if need and isinstance(p, torch.Tensor)]
    grads = [None] * len(leaves)
    if wanted and y.requires_grad:
        with torch.enable_grad():
            found = torch.autograd.grad(y, [leaves[i] for i in wanted], v_y, allow_unused=True)
        for i, g in zip(wanted, found):
            grads[i] = torch.zeros_like(leaves[i]) if g is None else g
    return grads


def svd_map(F: torch.Tensor, fn: Callable[..., torch.Tensor], *params, left: bool = False,
            eps: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply a symmetric function to the singular values: G = U diag(fn(sigma, *params)) Vh.

    The backward is exact at repeated singular values (module docstring), provided ``fn`` is
    permutation-equivariant (isotropic laws are). Gradients flow to tensor ``params`` as well.

    Args:
        F: [N, 3, 3].
        fn: ``fn(sigma [N,3], *params) -> y [N,3]``, torch-differentiable; params broadcast against sigma.
        *params: tensors (e.g. mu of shape [] or [N, 1]) or plain numbers passed to ``fn``.
        left: return U diag(y) U^T (e.g. a Kirchhoff stress from principal values) instead.
        eps: tolerance for "repeated" singular values and denominator clamp; default sqrt(machine eps).

    Returns:
        G [N, 3, 3] and sigma [N, 3] (signed singular values, not differentiable).
    """
    check_F(F, "svd_map")
    return _SpectralMap.apply(F, fn, left, default_eps(F.dtype) if eps is None else eps, *params)


def _ones(sigma: torch.Tensor) -> torch.Tensor:
    return torch.ones_like(sigma)


def polar_rotation(F: torch.Tensor) -> torch.Tensor:
    """Rotation of the polar decomposition F = R S: R = U Vh (det R = +1, also for det F < 0).

    Args:
        F: [N, 3, 3].

    Returns:
        R [N, 3, 3]; the gradient is exact at F = I (dR = skew(dF)).
    """
    check_F(F, "polar_rotation")
    return svd_map(F, _ones)[0]
