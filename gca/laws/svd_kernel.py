"""Forward 3x3 SVD of a batch in one warp kernel (float32 or float64), with the conventions of ``gca.laws.svd``.

``torch.linalg.svd`` on CUDA goes through cuSOLVER's batched Jacobi solver: several launches and a
host synchronisation (convergence info) per call, twice per MPM step for a neural law. That sync also
forbids capturing a frame's steps in a CUDA graph (``gca.sim.graph``). Here one thread per matrix runs
one-sided (Hestenes) cyclic Jacobi: plane rotations V orthogonalise the columns of B = F V until every
pair is orthogonal to the float type's rounding (at most ``MAX_SWEEPS`` sweeps; 3-6 for general
matrices, none for a diagonal F). Then

    sigma_i = |b_i| sorted descending (columns of B and V permuted alike, det V kept +1),
    u_1 = b_1 / sigma_1,  u_2 = b_2 / sigma_2,  u_3 = u_1 x u_2,  sigma_3 = b_3 . u_3 (signed),

so U and Vh are proper rotations and sigma_3 < 0 exactly where det F < 0: NCLaw's sign convention,
as in ``gca.laws.svd.torch_svd_rotations``. One-sided Jacobi is accurate to rounding relative to each
singular value, and exact at F = I (no rotation is taken), which keeps the laws' zero stress at rest
exact. warp's built-in ``svd3`` (fixed sweep count of approximate rotations) was measured off by up to
~1e-6 at F = I and ~1e-3 |F| on a few percent of general matrices, hence this kernel.

The float64 kernel (threshold 2.2e-16) serves CPR's float64 parameter fits on the GPU, where
cuSOLVER's float64 batched SVD cost ~1 ms and a host sync per call, ~1 s per GCA iteration.
"""

# no `from __future__ import annotations`: warp resolves the kernels' annotations (closure types) eagerly
import functools
import types

import torch
import warp as wp

from gca.warp_stream import on_torch_stream

_WHERE = "gca/laws/svd_kernel.py"
MAX_SWEEPS = 16  # cyclic sweeps of 3 rotations; convergence takes <= 6 (float32) / 7 (float64) on random F
_EPS = {torch.float32: 1.2e-7, torch.float64: 2.3e-16}  # columns count as orthogonal below this cosine
WARP_FLOATS = {torch.float32: wp.float32, torch.float64: wp.float64}  # torch dtype -> warp scalar


@functools.cache
def make_svd_kernel(dtype: torch.dtype) -> types.SimpleNamespace:
    """Build the SVD kernel for ``torch.float32`` or ``torch.float64`` (one warp module each)."""
    T = WARP_FLOATS[dtype]
    vec3 = wp.types.vector(3, T)
    mat33 = wp.types.matrix((3, 3), T)
    eps = T(_EPS[dtype])
    module = f"gca_laws_svd3_{T.__name__}"

    @wp.func
    def jacobi_rotate(i: int, j: int, B: mat33, V: mat33):
        """Rotate columns i, j of B (and of V) to make them orthogonal; returns (B, V, rotated)."""
        alpha = T(0.0)
        beta = T(0.0)
        gamma = T(0.0)
        for r in range(3):
            alpha += B[r, i] * B[r, i]
            beta += B[r, j] * B[r, j]
            gamma += B[r, i] * B[r, j]
        rotated = False
        if wp.abs(gamma) > eps * wp.sqrt(alpha * beta):
            zeta = (beta - alpha) / (T(2.0) * gamma)
            t = T(1.0) / (wp.abs(zeta) + wp.sqrt(T(1.0) + zeta * zeta))
            if zeta < T(0.0):
                t = -t
            c = T(1.0) / wp.sqrt(T(1.0) + t * t)
            s = c * t
            for r in range(3):
                bi = B[r, i]
                bj = B[r, j]
                B[r, i] = c * bi - s * bj
                B[r, j] = s * bi + c * bj
                vi = V[r, i]
                vj = V[r, j]
                V[r, i] = c * vi - s * vj
                V[r, j] = s * vi + c * vj
            rotated = True
        return B, V, rotated

    @wp.func
    def sort_pair(i: int, j: int, B: mat33, V: mat33):
        """Swap columns i < j of B and V when |b_j| > |b_i|, negating one so that det V stays +1."""
        ni = T(0.0)
        nj = T(0.0)
        for r in range(3):
            ni += B[r, i] * B[r, i]
            nj += B[r, j] * B[r, j]
        if nj > ni:
            for r in range(3):
                b = B[r, i]
                B[r, i] = B[r, j]
                B[r, j] = -b
                v = V[r, i]
                V[r, i] = V[r, j]
                V[r, j] = -v
        return B, V

    @wp.func
    def unit_or(a: vec3, fallback: vec3):
        """a / |a|, or ``fallback`` where a vanishes (rank-deficient F)."""
        n = wp.length(a)
        if n > T(1.0e-30):
            return a / n
        return fallback

    @wp.func
    def svd3_func(f: mat33):
        """(U, sigma, Vh) of one matrix in the sign-fixed convention; inlined by :func:`svd3_kernel` and by kernels
        that need the rotation of F without a pass through memory (``gca.sim.fused_step``)."""
        B = f
        V = wp.identity(n=3, dtype=T)
        for _sweep in range(MAX_SWEEPS):
            B, V, r01 = jacobi_rotate(0, 1, B, V)
            B, V, r12 = jacobi_rotate(1, 2, B, V)
            B, V, r02 = jacobi_rotate(0, 2, B, V)
            if not (r01 or r12 or r02):
                break
        B, V = sort_pair(0, 1, B, V)
        B, V = sort_pair(1, 2, B, V)
        B, V = sort_pair(0, 1, B, V)
        b0 = vec3(B[0, 0], B[1, 0], B[2, 0])
        b1 = vec3(B[0, 1], B[1, 1], B[2, 1])
        b2 = vec3(B[0, 2], B[1, 2], B[2, 2])
        u0 = unit_or(b0, vec3(T(1.0), T(0.0), T(0.0)))
        e = vec3(T(0.0), T(1.0), T(0.0))  # some unit vector orthogonal to u0 in case b1 vanishes
        if wp.abs(u0[1]) > T(0.9):
            e = vec3(T(1.0), T(0.0), T(0.0))
        u1 = unit_or(b1, wp.normalize(e - wp.dot(e, u0) * u0))
        u2 = wp.cross(u0, u1)
        return wp.matrix_from_cols(u0, u1, u2), vec3(wp.length(b0), wp.length(b1), wp.dot(b2, u2)), wp.transpose(V)

    @wp.kernel(module=module)
    def svd3_kernel(F: wp.array(dtype=mat33), U_out: wp.array(dtype=mat33), s_out: wp.array(dtype=vec3),
                    Vh_out: wp.array(dtype=mat33)):
        p = wp.tid()
        U, s, Vh = svd3_func(F[p])
        U_out[p] = U
        s_out[p] = s
        Vh_out[p] = Vh

    return types.SimpleNamespace(kernel=svd3_kernel, svd3=svd3_func, vec3=vec3, mat33=mat33)


def svd3(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """U, sigma, Vh of a float32 or float64 batch, in the sign-fixed convention (no autograd).

    Args:
        F: [N, 3, 3] float32 or float64 on the CPU or a CUDA device.

    Returns:
        U [N, 3, 3], sigma [N, 3], Vh [N, 3, 3] with det U = det Vh = +1, |sigma| descending.

    Runs on torch's current CUDA stream (so it can be captured in a CUDA graph).
    """
    if F.dtype not in WARP_FLOATS or F.ndim != 3 or tuple(F.shape[1:]) != (3, 3):
        raise ValueError(f"{_WHERE}: svd3 needs a float32/float64 [N, 3, 3] tensor, got {F.dtype} {tuple(F.shape)}")
    F = F.detach().contiguous()
    n = F.shape[0]
    U = torch.empty_like(F)
    Vh = torch.empty_like(F)
    sigma = torch.empty(n, 3, dtype=F.dtype, device=F.device)
    if n == 0:
        return U, sigma, Vh
    wp.init()
    k = make_svd_kernel(F.dtype)
    device = wp.device_from_torch(F.device)
    args = [wp.from_torch(F, dtype=k.mat33), wp.from_torch(U, dtype=k.mat33), wp.from_torch(sigma, dtype=k.vec3),
            wp.from_torch(Vh, dtype=k.mat33)]
    with on_torch_stream(F.device):
        wp.launch(k.kernel, dim=n, inputs=args[:1], outputs=args[1:], device=device)
    return U, sigma, Vh
