"""The neural laws' per-particle algebra in warp kernels with hand-written adjoints (fast path).

:class:`gca.laws.neural.NeuralElasticity` (and the plasticity) compute, per particle,

    U, sigma, Vh = svd(F),  R = U Vh,  z = [sigma - 1, vec(F^T F - I), det F - 1]      (features)
    X = MLP(z) [9]                                                                     (torch GEMMs)
    S = sym(X),  tau = stress_scale R S F^T   |   F_e = F + alpha R S                   (heads)

In torch the features and heads are ~60 elementwise kernels forward and more backward per network
and step (their launches dominated a neural-law MPM step on the GPU, ``benchmarks/NOTES.md``). Here
they are two warp kernels each way: ``features`` (after the SVD kernel) and a head, with adjoints
written out by hand (warp's automatic adjoint cannot go through the SVD's data-dependent loop):

    features:  v_F = U (diag(v_sigma) + K) Vh + F (v_C + v_C^T) + v_J cof(F),
               K_ij = (X_ij - X_ji) / (sigma_i + sigma_j) (i != j), K_ii = 0, X = U^T v_R Vh^T,
    elastic:   P = s R S, tau = P F^T:  v_F = v_tau^T P, v_R = s v_tau F S, v_X = sym(s R^T v_tau F),
    plastic:   F_e = F + a R S:         v_F = v_Fe,      v_R = a v_Fe S,   v_X = sym(a R^T v_Fe).

The rotation term is the polar-rotation VJP of ``gca.laws.svd``'s backward (its U-V term cancels
exactly for R = U Vh), with the same sign-keeping clamp |sigma_i + sigma_j| >= eps (only reached
under inversion). The MLP stays in torch (one GEMM per layer, merged LoRA weights), so gradients
reach the weights through autograd as before. Same values as the torch path to rounding, tested
with float64 gradient checks and against the torch implementation.
"""

# no `from __future__ import annotations`: warp resolves the kernels' annotations (closure types) eagerly
import dataclasses
import functools
import types

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from gca.laws.svd import _svd_rotations, default_eps, warp_runs
from gca.laws.svd_kernel import WARP_FLOATS, make_svd_kernel
from gca.warp_stream import on_torch_stream

_WHERE = "gca/laws/fused.py"
N_FEATURES = 13
COROTATED, NEO_HOOKEAN = 0, 1  # analytic laws a transfer kernel can evaluate inline (``analytic_stress``)
ANALYTIC_KINDS = {"corotated": COROTATED, "neo_hookean": NEO_HOOKEAN}


@functools.cache
def make_law_kernels(dtype: torch.dtype) -> types.SimpleNamespace:
    """Build the feature and head kernels and their adjoints for float32 or float64 (warp initialised: the SVD-free
    laws reach warp through here first)."""
    wp.init()
    T = WARP_FLOATS[dtype]
    vec3 = wp.types.vector(3, T)
    mat33 = wp.types.matrix((3, 3), T)
    module = f"gca_laws_fused_{T.__name__}"

    @wp.func
    def cofactor(f: mat33):
        """d det(F) / dF: rows are cross products of the other two rows."""
        r0 = vec3(f[0, 0], f[0, 1], f[0, 2])
        r1 = vec3(f[1, 0], f[1, 1], f[1, 2])
        r2 = vec3(f[2, 0], f[2, 1], f[2, 2])
        return wp.matrix_from_rows(wp.cross(r1, r2), wp.cross(r2, r0), wp.cross(r0, r1))

    @wp.func
    def safe_recip(d: T, eps: T):
        """1/d with |d| clamped to >= eps, sign kept (0 counts as +)."""
        if d < T(0.0):
            return T(-1.0) / wp.max(-d, eps)
        return T(1.0) / wp.max(d, eps)

    @wp.func
    def sym_of_row(X: wp.array2d(dtype=T), p: int):
        """sym(M) of the row-major 3x3 M = X[p].reshape(3, 3)."""
        M = mat33(X[p, 0], X[p, 1], X[p, 2], X[p, 3], X[p, 4], X[p, 5], X[p, 6], X[p, 7], X[p, 8])
        return T(0.5) * (M + wp.transpose(M))

    @wp.func
    def store_sym(G: mat33, out: wp.array2d(dtype=T), p: int):
        """out[p] = vec(sym(G)) (the VJP of M -> sym(M))."""
        S = T(0.5) * (G + wp.transpose(G))
        for i in range(3):
            for j in range(3):
                out[p, 3 * i + j] = S[i, j]

    @wp.func
    def store_features(f: mat33, u: mat33, sv: vec3, vh: mat33, p: int, R: wp.array(dtype=mat33),
                       z: wp.array2d(dtype=T)):
        """Particle ``p``'s R = U Vh and z = [sigma - 1, vec(F^T F - I), det F - 1] from its SVD."""
        R[p] = u @ vh
        C = wp.transpose(f) @ f
        for i in range(3):
            z[p, i] = sv[i] - T(1.0)
            for j in range(3):
                shift = T(0.0)
                if i == j:
                    shift = T(1.0)
                z[p, 3 + 3 * i + j] = C[i, j] - shift
        z[p, 12] = wp.determinant(f) - T(1.0)

    @wp.kernel(module=module)
    def features(F: wp.array(dtype=mat33), U: wp.array(dtype=mat33), s: wp.array(dtype=vec3),
                 Vh: wp.array(dtype=mat33), R: wp.array(dtype=mat33), z: wp.array2d(dtype=T)):
        p = wp.tid()
        store_features(F[p], U[p], s[p], Vh[p], p, R, z)

    @wp.kernel(module=module)
    def features_adjoint(F: wp.array(dtype=mat33), U: wp.array(dtype=mat33), s: wp.array(dtype=vec3),
                         Vh: wp.array(dtype=mat33), v_R: wp.array(dtype=mat33), v_z: wp.array2d(dtype=T),
                         eps: T, v_F: wp.array(dtype=mat33)):
        p = wp.tid()
        f = F[p]
        u = U[p]
        vh = Vh[p]
        sv = s[p]
        v_C = mat33(v_z[p, 3], v_z[p, 4], v_z[p, 5], v_z[p, 6], v_z[p, 7], v_z[p, 8], v_z[p, 9], v_z[p, 10],
                    v_z[p, 11])
        D = wp.diag(vec3(v_z[p, 0], v_z[p, 1], v_z[p, 2]))
        X = wp.transpose(u) @ v_R[p] @ wp.transpose(vh)
        K = mat33()
        for i in range(3):
            for j in range(3):
                if i != j:
                    K[i, j] = (X[i, j] - X[j, i]) * safe_recip(sv[i] + sv[j], eps)
        v_F[p] = u @ (D + K) @ vh + f @ (v_C + wp.transpose(v_C)) + v_z[p, 12] * cofactor(f)

    @wp.kernel(module=module)
    def elastic_head(X: wp.array2d(dtype=T), R: wp.array(dtype=mat33), F: wp.array(dtype=mat33), scale: T,
                     tau: wp.array(dtype=mat33)):
        p = wp.tid()
        tau[p] = (scale * R[p] @ sym_of_row(X, p)) @ wp.transpose(F[p])

    @wp.kernel(module=module)
    def elastic_head_adjoint(X: wp.array2d(dtype=T), R: wp.array(dtype=mat33), F: wp.array(dtype=mat33), scale: T,
                             v_tau: wp.array(dtype=mat33), v_X: wp.array2d(dtype=T), v_R: wp.array(dtype=mat33),
                             v_F: wp.array(dtype=mat33)):
        p = wp.tid()
        S = sym_of_row(X, p)
        r = R[p]
        v_P = v_tau[p] @ F[p]
        v_F[p] = wp.transpose(v_tau[p]) @ (scale * r @ S)
        v_R[p] = scale * v_P @ S
        store_sym(scale * wp.transpose(r) @ v_P, v_X, p)

    @wp.kernel(module=module)
    def plastic_head(X: wp.array2d(dtype=T), R: wp.array(dtype=mat33), F: wp.array(dtype=mat33), alpha: T,
                     F_e: wp.array(dtype=mat33)):
        p = wp.tid()
        F_e[p] = F[p] + alpha * R[p] @ sym_of_row(X, p)

    @wp.kernel(module=module)
    def plastic_head_adjoint(X: wp.array2d(dtype=T), R: wp.array(dtype=mat33), alpha: T,
                             v_Fe: wp.array(dtype=mat33), v_X: wp.array2d(dtype=T), v_R: wp.array(dtype=mat33)):
        p = wp.tid()
        v_R[p] = alpha * v_Fe[p] @ sym_of_row(X, p)
        store_sym(alpha * wp.transpose(R[p]) @ v_Fe[p], v_X, p)

    @wp.func
    def polar_vjp(u: mat33, sv: vec3, vh: mat33, v_R: mat33, eps: T):
        """v_F of R = U Vh given v_R (the rotation term of ``features_adjoint``)."""
        X = wp.transpose(u) @ v_R @ wp.transpose(vh)
        K = mat33()
        for i in range(3):
            for j in range(3):
                if i != j:
                    K[i, j] = (X[i, j] - X[j, i]) * safe_recip(sv[i] + sv[j], eps)
        return u @ K @ vh

    @wp.func
    def corotated_stress(f: mat33, R: mat33, mu: T, lam: T):
        """tau = 2 mu (F - R) F^T + lam J (J - 1) I of one particle, R = U Vh its polar rotation."""
        J = wp.determinant(f)
        return (T(2.0) * mu) * (f - R) @ wp.transpose(f) + (lam * J * (J - T(1.0))) * wp.identity(3, dtype=T)

    @wp.kernel(module=module)
    def corotated(F: wp.array(dtype=mat33), U: wp.array(dtype=mat33), Vh: wp.array(dtype=mat33),
                  mu: wp.array(dtype=T), lam: wp.array(dtype=T), per: int, tau: wp.array(dtype=mat33)):
        p = wp.tid()
        tau[p] = corotated_stress(F[p], U[p] @ Vh[p], mu[p * per], lam[p * per])

    @wp.kernel(module=module)
    def corotated_adjoint(F: wp.array(dtype=mat33), U: wp.array(dtype=mat33), s: wp.array(dtype=vec3),
                          Vh: wp.array(dtype=mat33), mu: wp.array(dtype=T), lam: wp.array(dtype=T), per: int,
                          v_tau: wp.array(dtype=mat33), eps: T, v_F: wp.array(dtype=mat33), v_mu: wp.array(dtype=T),
                          v_lam: wp.array(dtype=T)):
        p = wp.tid()
        f = F[p]
        G = v_tau[p]
        R = U[p] @ Vh[p]
        J = wp.determinant(f)
        m2 = T(2.0) * mu[p * per]
        trG = wp.trace(G)
        grad = m2 * ((G + wp.transpose(G)) @ f - wp.transpose(G) @ R)
        grad += (lam[p * per] * (T(2.0) * J - T(1.0)) * trG) * cofactor(f)
        v_F[p] = grad + polar_vjp(U[p], s[p], Vh[p], -m2 * G @ f, eps)
        D = (f - R) @ wp.transpose(f)
        acc = T(0.0)
        for i in range(3):
            for j in range(3):
                acc += G[i, j] * D[i, j]
        v_mu[p] = T(2.0) * acc
        v_lam[p] = trG * J * (J - T(1.0))

    @wp.func
    def neo_hookean_stress(f: mat33, mu: T, lam: T, j_min: T):
        """tau = mu (F F^T - I) + lam log(max(J, j_min)) I of one particle."""
        log_J = wp.log(wp.max(wp.determinant(f), j_min))
        eye = wp.identity(3, dtype=T)
        return mu * (f @ wp.transpose(f) - eye) + (lam * log_J) * eye

    svd3 = make_svd_kernel(dtype).svd3

    @wp.kernel(module=module)
    def svd_features(F: wp.array(dtype=mat33), keep: int, U: wp.array(dtype=mat33), s: wp.array(dtype=vec3),
                     Vh: wp.array(dtype=mat33), R: wp.array(dtype=mat33), z: wp.array2d(dtype=T)):
        """The SVD kernel and :func:`features` in one pass (``_Features``'s forward since session 52: one launch, F
        read once, the SVD kept in registers); (U, sigma, Vh) stored only where ``keep`` (a backward will read them:
        a rollout's forward without gradients stores none)."""
        p = wp.tid()
        f = F[p]
        u, sv, vh = svd3(f)
        if keep != 0:
            U[p] = u
            s[p] = sv
            Vh[p] = vh
        store_features(f, u, sv, vh, p, R, z)

    @wp.func
    def analytic_stress(kind: int, f: mat33, mu: T, lam: T, j_min: T):
        """Kirchhoff stress of the analytic law ``kind`` (:data:`ANALYTIC_KINDS`) of one particle, the SVD inlined:
        the same functions as the laws' kernels, for kernels that fuse the stress into a transfer."""
        if kind == COROTATED:
            U, s, Vh = svd3(f)
            return corotated_stress(f, U @ Vh, mu, lam)
        return neo_hookean_stress(f, mu, lam, j_min)

    @wp.kernel(module=module)
    def neo_hookean(F: wp.array(dtype=mat33), mu: wp.array(dtype=T), lam: wp.array(dtype=T), per: int, j_min: T,
                    tau: wp.array(dtype=mat33)):
        p = wp.tid()
        tau[p] = neo_hookean_stress(F[p], mu[p * per], lam[p * per], j_min)

    @wp.kernel(module=module)
    def neo_hookean_adjoint(F: wp.array(dtype=mat33), mu: wp.array(dtype=T), lam: wp.array(dtype=T), per: int,
                            j_min: T, v_tau: wp.array(dtype=mat33), v_F: wp.array(dtype=mat33),
                            v_mu: wp.array(dtype=T), v_lam: wp.array(dtype=T)):
        p = wp.tid()
        f = F[p]
        G = v_tau[p]
        J = wp.determinant(f)
        trG = wp.trace(G)
        grad = mu[p * per] * (G + wp.transpose(G)) @ f
        if J >= j_min:  # as torch's clamp: the gradient passes where J >= j_min (the bound included)
            grad += (lam[p * per] * trG / J) * cofactor(f)
        v_F[p] = grad
        D = f @ wp.transpose(f)
        acc = T(0.0)
        for i in range(3):
            for j in range(3):
                acc += G[i, j] * D[i, j]
        v_mu[p] = acc - trG
        v_lam[p] = trG * wp.log(wp.max(J, j_min))

    return types.SimpleNamespace(features=features, svd_features=svd_features, features_adjoint=features_adjoint,
                                 elastic_head=elastic_head,
                                 corotated=corotated, corotated_adjoint=corotated_adjoint,
                                 neo_hookean=neo_hookean, neo_hookean_adjoint=neo_hookean_adjoint,
                                 elastic_head_adjoint=elastic_head_adjoint, plastic_head=plastic_head,
                                 plastic_head_adjoint=plastic_head_adjoint, analytic_stress=analytic_stress,
                                 mat33=mat33, vec3=vec3, T=T)


def _launch(kernel, n: int, device: torch.device, args: list) -> None:
    with on_torch_stream(device):
        wp.launch(kernel, dim=n, inputs=args, device=wp.device_from_torch(device))


# torch -> warp views (contiguous copies where needed): [N,3,3] as mat33, [N,3] as vec3, [N,k] as 2-D;
# callers skip empty batches (warp refuses to view a zero-size tensor)
def _m(t: torch.Tensor, k) -> wp.array:
    return wp.from_torch(t.contiguous(), dtype=k.mat33)


def _v(t: torch.Tensor, k) -> wp.array:
    return wp.from_torch(t.contiguous(), dtype=k.vec3)


def _a(t: torch.Tensor) -> wp.array:
    return wp.from_torch(t.contiguous())


def features_of_svd(F: torch.Tensor, U: torch.Tensor, sigma: torch.Tensor, Vh: torch.Tensor):
    """(R [N,3,3], z [N,13]) of F [N,3,3] from its SVD (U, sigma [N,3], Vh) by the ``features`` kernel, no autograd:
    the two-kernel path (the SVD kernel, then this) that ``svd_features`` fuses."""
    k = make_law_kernels(F.dtype)
    R = torch.empty_like(F)
    z = torch.empty(F.shape[0], N_FEATURES, dtype=F.dtype, device=F.device)
    if F.shape[0]:
        _launch(k.features, F.shape[0], F.device, [_m(F, k), _m(U, k), _v(sigma, k), _m(Vh, k), _m(R, k), _a(z)])
    return R, z


class _Features(torch.autograd.Function):
    """F [N,3,3] -> (R [N,3,3] polar rotation, z [N,13] rest-shifted invariants)."""

    @staticmethod
    def forward(ctx, F):
        F = F.detach().contiguous()
        n = F.shape[0]
        if warp_runs(F):  # the SVD and the features in one kernel; the SVD stored only for a backward
            k = make_law_kernels(F.dtype)
            R = torch.empty_like(F)
            z = torch.empty(n, N_FEATURES, dtype=F.dtype, device=F.device)
            keep = bool(ctx.needs_input_grad[0])
            m = n if keep else 1
            U, Vh = (torch.empty(m, 3, 3, dtype=F.dtype, device=F.device) for _ in range(2))
            sigma = torch.empty(m, 3, dtype=F.dtype, device=F.device)
            if n:
                _launch(k.svd_features, n, F.device, [_m(F, k), int(keep), _m(U, k), _v(sigma, k), _m(Vh, k),
                                                       _m(R, k), _a(z)])
        else:  # torch's SVD (a CPU where warp has no compiler: gca.laws.svd), then the features kernel
            U, sigma, Vh = _svd_rotations(F)
            R, z = features_of_svd(F, U, sigma, Vh)
        ctx.save_for_backward(F, U, sigma, Vh)
        return R, z

    @staticmethod
    @once_differentiable
    def backward(ctx, v_R, v_z):
        F, U, sigma, Vh = ctx.saved_tensors
        k = make_law_kernels(F.dtype)
        v_R = torch.zeros_like(F) if v_R is None else v_R
        v_z = torch.zeros(F.shape[0], N_FEATURES, dtype=F.dtype, device=F.device) if v_z is None else v_z
        v_F = torch.empty_like(F)
        if F.shape[0]:
            _launch(k.features_adjoint, F.shape[0], F.device,
                    [_m(F, k), _m(U, k), _v(sigma, k), _m(Vh, k), _m(v_R, k), _a(v_z), k.T(default_eps(F.dtype)),
                     _m(v_F, k)])
        return v_F


class _ElasticHead(torch.autograd.Function):
    """(X [N,9], R, F) -> tau = scale R sym(X) F^T [N,3,3]."""

    @staticmethod
    def forward(ctx, X, R, F, scale):
        X, R, F = (t.detach().contiguous() for t in (X, R, F))
        k = make_law_kernels(F.dtype)
        tau = torch.empty_like(F)
        if F.shape[0]:
            _launch(k.elastic_head, F.shape[0], F.device, [_a(X), _m(R, k), _m(F, k), k.T(scale), _m(tau, k)])
        ctx.save_for_backward(X, R, F)
        ctx.scale = scale
        return tau

    @staticmethod
    @once_differentiable
    def backward(ctx, v_tau):
        X, R, F = ctx.saved_tensors
        k = make_law_kernels(F.dtype)
        v_X, v_R, v_F = torch.empty_like(X), torch.empty_like(R), torch.empty_like(F)
        if F.shape[0]:
            _launch(k.elastic_head_adjoint, F.shape[0], F.device,
                    [_a(X), _m(R, k), _m(F, k), k.T(ctx.scale), _m(v_tau, k), _a(v_X), _m(v_R, k),
                     _m(v_F, k)])
        return v_X, v_R, v_F, None


class _PlasticHead(torch.autograd.Function):
    """(X [N,9], R, F) -> F_e = F + alpha R sym(X) [N,3,3]."""

    @staticmethod
    def forward(ctx, X, R, F, alpha):
        X, R, F = (t.detach().contiguous() for t in (X, R, F))
        k = make_law_kernels(F.dtype)
        F_e = torch.empty_like(F)
        if F.shape[0]:
            _launch(k.plastic_head, F.shape[0], F.device, [_a(X), _m(R, k), _m(F, k), k.T(alpha), _m(F_e, k)])
        ctx.save_for_backward(X, R)
        ctx.alpha = alpha
        return F_e

    @staticmethod
    @once_differentiable
    def backward(ctx, v_Fe):
        X, R = ctx.saved_tensors
        k = make_law_kernels(R.dtype)
        v_Fe = v_Fe.contiguous()
        v_X, v_R = torch.empty_like(X), torch.empty_like(R)
        if R.shape[0]:
            _launch(k.plastic_head_adjoint, R.shape[0], R.device,
                    [_a(X), _m(R, k), k.T(ctx.alpha), _m(v_Fe, k), _a(v_X), _m(v_R, k)])
        return v_X, v_R, v_Fe, None


def _lame(name: str, F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(mu [1] or [N], lam likewise) in F's dtype for an analytic law ``name``, checked (one line naming the law)."""
    if F.dtype not in WARP_FLOATS:
        raise TypeError(f"{_WHERE}: F must be float32 or float64, got {F.dtype}")
    n = F.shape[0]
    mu_v, lam_v = mu.reshape(-1).to(F.dtype), lam.reshape(-1).to(F.dtype)
    if mu_v.shape[0] != lam_v.shape[0] or mu_v.shape[0] not in (1, n):
        raise ValueError(f"{_WHERE}: {name}: mu and lam must both be scalars or both of shape [N={n}], got "
                         f"{tuple(mu.shape)} and {tuple(lam.shape)}")
    return mu_v, lam_v


def _per(mu: torch.Tensor) -> int:
    """1 for [N] moduli (N = 0 included: review, session 29), 0 for one modulus for every particle."""
    return int(mu.shape[0] != 1)


def _lame_grads(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Zeroed per-particle (v_mu, v_lam) [N] for an adjoint kernel to fill."""
    return tuple(torch.zeros(F.shape[0], dtype=F.dtype, device=F.device) for _ in range(2))


def _lame_out(per: int, v_mu: torch.Tensor, v_lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The moduli's gradients in their own shape: one modulus for every particle takes the particles' summed
    shares."""
    if per:
        return v_mu, v_lam
    return v_mu.sum(0, keepdim=True), v_lam.sum(0, keepdim=True)


@dataclasses.dataclass(frozen=True)
class AnalyticStress:
    """An analytic elastic law in the form a transfer kernel evaluates inline (``analytic_stress`` of
    :func:`make_law_kernels`; ``gca.sim.fused_step`` puts it inside P2G).

    Attributes:
        kind: :data:`COROTATED` or :data:`NEO_HOOKEAN`.
        mu, lam: Lame parameters [Pa], [1] (every particle) or [N], F's dtype, contiguous.
        j_min: lower clamp of J inside the neo-Hookean log [1] (unused by the corotated law).
    """

    kind: int
    mu: torch.Tensor
    lam: torch.Tensor
    j_min: float = 0.0

    def __post_init__(self):
        if self.kind not in ANALYTIC_KINDS.values():
            raise ValueError(f"{_WHERE}: AnalyticStress: kind={self.kind} is none of {ANALYTIC_KINDS}")

    @property
    def per(self) -> int:
        """1 for [N] moduli, 0 for one pair for every particle (the kernels index ``mu[p * per]``)."""
        return _per(self.mu)


def analytic(name: str, F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, j_min: float = 0.0):
    """The :class:`AnalyticStress` of law ``name`` (a key of :data:`ANALYTIC_KINDS`) for F [N,3,3], moduli checked
    and detached; None where autograd records and a modulus requires a gradient (the fused transfer has no
    backward: a gradient through them must take the generic step)."""
    if torch.is_grad_enabled() and (mu.requires_grad or lam.requires_grad):
        return None
    mu_v, lam_v = _lame(f"{name} (fused)", F, mu.detach(), lam.detach())
    return AnalyticStress(ANALYTIC_KINDS[name], mu_v.contiguous(), lam_v.contiguous(), float(j_min))


class _Corotated(torch.autograd.Function):
    """(F [N,3,3], mu, lam [1] or [N]) -> tau = 2 mu (F - R) F^T + lam J (J - 1) I [N,3,3]."""

    @staticmethod
    def forward(ctx, F, mu, lam):
        F = F.detach().contiguous()
        mu, lam = mu.detach().contiguous(), lam.detach().contiguous()
        U, sigma, Vh = _svd_rotations(F)
        k = make_law_kernels(F.dtype)
        tau = torch.empty_like(F)
        per = _per(mu)
        if F.shape[0]:
            _launch(k.corotated, F.shape[0], F.device, [_m(F, k), _m(U, k), _m(Vh, k), _a(mu), _a(lam), per, _m(tau, k)])
        ctx.save_for_backward(F, U, sigma, Vh, mu, lam)
        ctx.per = per
        return tau

    @staticmethod
    @once_differentiable
    def backward(ctx, v_tau):
        F, U, sigma, Vh, mu, lam = ctx.saved_tensors
        k = make_law_kernels(F.dtype)
        n = F.shape[0]
        v_F = torch.empty_like(F)
        v_mu, v_lam = _lame_grads(F)
        if n:
            _launch(k.corotated_adjoint, n, F.device,
                    [_m(F, k), _m(U, k), _v(sigma, k), _m(Vh, k), _a(mu), _a(lam), ctx.per, _m(v_tau, k),
                     k.T(default_eps(F.dtype)), _m(v_F, k), _a(v_mu), _a(v_lam)])
        return (v_F, *_lame_out(ctx.per, v_mu, v_lam))


def corotated_tau(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Fixed corotated Kirchhoff stress ``2 mu (F - R) F^T + lam J (J - 1) I`` [N,3,3] (Pa) in two warp kernels
    (the SVD, then the stress), with a hand-written adjoint; the same law as
    :func:`gca.laws.elastic.corotated_tau` (tested in values and gradients, float64 gradchecks).

    Args:
        F: elastic deformation gradients [N, 3, 3] (float32/float64).
        mu, lam: Lame parameters [Pa] as tensors of shape [] or [N] (differentiable; no host read, so the
            law is capturable in a CUDA graph).

    Adjoint: with G = v_tau, v_F = 2 mu ((G + G^T) F - G^T R) + lam (2J - 1) tr(G) cof(F) + polar_vjp(-2 mu G F),
    v_mu = 2 <G, (F - R) F^T>, v_lam = tr(G) J (J - 1).
    """
    return _Corotated.apply(F, *_lame("corotated_tau", F, mu, lam))


class _NeoHookean(torch.autograd.Function):
    """(F [N,3,3], mu, lam [1] or [N], j_min) -> tau = mu (F F^T - I) + lam log(max(J, j_min)) I [N,3,3]."""

    @staticmethod
    def forward(ctx, F, mu, lam, j_min):
        F = F.detach().contiguous()
        mu, lam = mu.detach().contiguous(), lam.detach().contiguous()
        k = make_law_kernels(F.dtype)
        tau = torch.empty_like(F)
        per = _per(mu)
        if F.shape[0]:
            _launch(k.neo_hookean, F.shape[0], F.device, [_m(F, k), _a(mu), _a(lam), per, k.T(j_min), _m(tau, k)])
        ctx.save_for_backward(F, mu, lam)
        ctx.per, ctx.j_min = per, j_min
        return tau

    @staticmethod
    @once_differentiable
    def backward(ctx, v_tau):
        F, mu, lam = ctx.saved_tensors
        k = make_law_kernels(F.dtype)
        n = F.shape[0]
        v_F = torch.empty_like(F)
        v_mu, v_lam = _lame_grads(F)
        if n:
            _launch(k.neo_hookean_adjoint, n, F.device,
                    [_m(F, k), _a(mu), _a(lam), ctx.per, k.T(ctx.j_min), _m(v_tau, k), _m(v_F, k), _a(v_mu),
                     _a(v_lam)])
        return (v_F, *_lame_out(ctx.per, v_mu, v_lam), None)


def neo_hookean_tau(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, j_min: float) -> torch.Tensor:
    """Compressible neo-Hookean Kirchhoff stress ``mu (F F^T - I) + lam log(max(J, j_min)) I`` [N,3,3] (Pa) in
    one warp kernel, with a hand-written adjoint (one kernel); the same law as :func:`gca.laws.ood.neo_hookean_tau`
    (tested in values and gradients, float64 gradchecks), for the PAC-NeRF-style elastic rows and the elastomer's
    ground truth (issue 20 item 2: ~15 torch kernels per step forward and more backward before).

    Args:
        F: elastic deformation gradients [N, 3, 3] (float32/float64).
        mu, lam: Lame parameters [Pa] as tensors of shape [] or [N] (differentiable; no host read, so the
            law is capturable in a CUDA graph).
        j_min: lower clamp of J = det F inside the log [1] (no volumetric gradient below it, as torch's clamp).

    Adjoint: with G = v_tau, v_F = mu (G + G^T) F + lam tr(G) cof(F) / J (J >= j_min), v_mu = <G, F F^T - I>,
    v_lam = tr(G) log(max(J, j_min)).
    """
    return _NeoHookean.apply(F, *_lame("neo_hookean_tau", F, mu, lam), float(j_min))


def features(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R [N,3,3], z [N,13]) of F [N,3,3] (float32/float64, CPU with warp or CUDA), differentiable."""
    if F.dtype not in WARP_FLOATS:
        raise TypeError(f"{_WHERE}: F must be float32 or float64, got {F.dtype}")
    return _Features.apply(F)


def elastic_head(X: torch.Tensor, R: torch.Tensor, F: torch.Tensor, scale: float) -> torch.Tensor:
    """tau = scale R sym(X.reshape(-1, 3, 3)) F^T [N,3,3] (Pa), differentiable in X, R, F."""
    return _ElasticHead.apply(X, R, F, float(scale))


def plastic_head(X: torch.Tensor, R: torch.Tensor, F: torch.Tensor, alpha: float) -> torch.Tensor:
    """F_e = F + alpha R sym(X.reshape(-1, 3, 3)) [N,3,3], differentiable in X, R, F."""
    return _PlasticHead.apply(X, R, F, float(alpha))
