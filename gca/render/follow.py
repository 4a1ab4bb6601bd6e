"""Gaussians follow MPM particles through a sparse binding (NeuMA's Particle-GS, full gradients).

A binding ``W [G, P]`` (rows sum to 1) ties each Gaussian to a few particles. Given the initial
Gaussians ``(means0 [G, 3], covs0 [G, 3, 3])`` and particles ``x0 [P, 3]`` in the sim frame, and
the current particle state ``(x [P, 3], F [P, 3, 3])``:

    means = means0 + W (x - x0)          (displacement interpolation)
    F_g   = W F                           (per-Gaussian deformation gradient)
    covs  = F_g covs0 F_g^T               (PhysGaussian's Sigma = F Sigma0 F^T)

Unlike NeuMA (whose covariance update ran outside autograd), gradients reach both ``x`` and ``F``.
"""

from __future__ import annotations

import dataclasses

import torch

from gca.linalg import bmm3

_WHERE = "gca/render/follow.py"


class BindingError(ValueError):
    """A malformed binding (names the file and the problem)."""


@dataclasses.dataclass(frozen=True)
class Binding:
    """Sparse Gaussian -> particle weights ``W [G, P]`` in COO form.

    Attributes:
        rows: Gaussian index of each entry [E] (int64).
        cols: particle index of each entry [E] (int64).
        weights: entry weights [E]; for each Gaussian they sum to 1.
        n_gaussians: G.
        n_particles: P.
    """

    rows: torch.Tensor
    cols: torch.Tensor
    weights: torch.Tensor
    n_gaussians: int
    n_particles: int

    def __post_init__(self) -> None:
        E = self.rows.shape[0]
        if self.rows.shape != (E,) or self.cols.shape != (E,) or self.weights.shape != (E,):
            raise BindingError(f"{_WHERE}: rows/cols/weights must be [E] each, got "
                               f"{tuple(self.rows.shape)}, {tuple(self.cols.shape)}, {tuple(self.weights.shape)}")
        if E and (self.rows.min() < 0 or self.rows.max() >= self.n_gaussians):
            raise BindingError(f"{_WHERE}: Gaussian indices outside [0, {self.n_gaussians})")
        if E and (self.cols.min() < 0 or self.cols.max() >= self.n_particles):
            raise BindingError(f"{_WHERE}: particle indices outside [0, {self.n_particles})")
        sums = torch.zeros(self.n_gaussians, dtype=torch.float64, device=self.weights.device)
        sums.index_add_(0, self.rows, self.weights.detach().to(torch.float64))
        worst = (sums - 1.0).abs().max().item() if self.n_gaussians else 0.0
        if worst > 1e-4:
            raise BindingError(f"{_WHERE}: binding rows must sum to 1 (worst |sum - 1| = {worst:.3g}; "
                               "a Gaussian without particles?)")

    @classmethod
    def from_sparse(cls, W: torch.Tensor) -> "Binding":
        """Build from a torch sparse COO matrix ``[G, P]``."""
        if not W.is_sparse or W.ndim != 2:
            raise BindingError(f"{_WHERE}: expected a 2-D torch sparse COO tensor, got layout {W.layout}")
        W = W.coalesce()
        rows, cols = W.indices()
        return cls(rows=rows, cols=cols, weights=W.values(), n_gaussians=W.shape[0], n_particles=W.shape[1])

    def to_sparse(self) -> torch.Tensor:
        """The binding as a torch sparse COO matrix ``[G, P]``."""
        indices = torch.stack([self.rows, self.cols])
        shape = (self.n_gaussians, self.n_particles)
        return torch.sparse_coo_tensor(indices, self.weights, shape, check_invariants=True).coalesce()

    def apply(self, values: torch.Tensor) -> torch.Tensor:
        """``W @ values`` for per-particle values ``[P, ...]`` -> ``[G, ...]`` (differentiable).

        The entries' particle values are gathered by ``index_select``, whose backward scatters by ``index_add``
        (atomic adds on CUDA, as the MPM's P2G does), not by advanced indexing, whose backward is the sort-based
        ``index_put_(accumulate=True)``: session 52's duck profile spent 6.5 ms of a training iteration's GPU time
        (20 calls, ~330 us each) there. The same values; the gradient's sums to float rounding."""
        assert values.shape[0] == self.n_particles, \
            f"{_WHERE}: expected [{self.n_particles}, ...] particle values, got {tuple(values.shape)}"
        w = self.weights.to(values.dtype).reshape((-1,) + (1,) * (values.ndim - 1))
        out = values.new_zeros((self.n_gaussians,) + tuple(values.shape[1:]))
        return out.index_add(0, self.rows, w * values.index_select(0, self.cols))


def follow(binding: Binding, means0: torch.Tensor, covs0: torch.Tensor, x0: torch.Tensor,
           x: torch.Tensor, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Move and deform bound Gaussians with the particles.

    Args:
        binding: :class:`Binding` ``W [G, P]``.
        means0: initial Gaussian means [G, 3] (sim frame, m).
        covs0: initial Gaussian covariances [G, 3, 3] (sim frame, m^2).
        x0: initial particle positions [P, 3] (m).
        x: current particle positions [P, 3] (m), or [T, P, 3]: T states at once (e.g. a training iteration's
            video frames).
        F: current (elastic) deformation gradients [P, 3, 3] ([T, P, 3, 3]).

    Returns:
        ``(means [(T,) G, 3], covs [(T,) G, 3, 3])``; differentiable w.r.t. ``x`` and ``F``.
    """
    G, P = binding.n_gaussians, binding.n_particles
    assert means0.shape == (G, 3) and covs0.shape == (G, 3, 3), \
        f"{_WHERE}: means0/covs0 must be [{G}, 3]/[{G}, 3, 3], got {tuple(means0.shape)}/{tuple(covs0.shape)}"
    lead = x.shape[:-2]
    assert x0.shape == (P, 3) and x.shape == (*lead, P, 3) and F.shape == (*lead, P, 3, 3) and len(lead) <= 1, \
        f"{_WHERE}: x0/x/F must be [{P}, 3]/[(T,) {P}, 3]/[(T,) {P}, 3, 3], got " \
        f"{tuple(x0.shape)}/{tuple(x.shape)}/{tuple(F.shape)}"
    # the binding maps particle rows to Gaussian rows: the frames ride along as trailing dims
    means = means0 + binding.apply((x - x0).movedim(-2, 0)).movedim(0, -2)
    F_g = binding.apply(F.movedim(-3, 0)).movedim(0, -3)
    covs = bmm3(bmm3(F_g, covs0), F_g.transpose(-1, -2))
    return means, covs


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] from quaternions [N, 4] (w, x, y, z; normalised here)."""
    assert quats.ndim == 2 and quats.shape[1] == 4, f"{_WHERE}: quats must be [N, 4], got {tuple(quats.shape)}"
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1)
    return R.reshape(-1, 3, 3)


def covariance_from_scale_rot(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """3DGS covariances ``R diag(exp(log_scales))^2 R^T`` [N, 3, 3].

    Args:
        log_scales: log standard deviations along the local axes [N, 3] (the .ply ``scale_*`` fields).
        quats: rotations as (w, x, y, z) quaternions [N, 4] (the .ply ``rot_*`` fields; normalised here).
    """
    assert log_scales.ndim == 2 and log_scales.shape[1] == 3 and quats.shape == (log_scales.shape[0], 4), \
        f"{_WHERE}: log_scales [N, 3] and quats [N, 4] expected, got {tuple(log_scales.shape)}, {tuple(quats.shape)}"
    R = quat_to_rotmat(quats)
    M = R * torch.exp(log_scales)[:, None, :]
    return bmm3(M, M.transpose(-1, -2))


_EIGH_CHUNK = 16384  # matrices per batched eigh call on CUDA


def smallest_axis_normal(covs: torch.Tensor) -> torch.Tensor:
    """Unit direction of each covariance's smallest axis [N, 3] (the flat Gaussian's normal).

    The sign is arbitrary (shade two-sided). Computed without gradients: eigenvector derivatives are
    undefined for repeated eigenvalues (round Gaussians), and shading is used for ground truth only.

    Args:
        covs: covariances [N, 3, 3] (symmetrised here).
    """
    assert covs.ndim == 3 and covs.shape[1:] == (3, 3), f"{_WHERE}: covs must be [N, 3, 3], got {tuple(covs.shape)}"
    with torch.no_grad():
        sym = 0.5 * (covs + covs.transpose(-1, -2))
        # cuSOLVER's batched eigh fails (CUSOLVER_STATUS_INTERNAL_ERROR) on ~1e5 3x3 matrices on an H100:
        # solve in chunks there. The CPU path is a single call.
        if sym.is_cuda and sym.shape[0]:
            try:
                vectors = torch.cat([torch.linalg.eigh(part)[1] for part in sym.split(_EIGH_CHUNK)])
            except RuntimeError:  # a cuSOLVER failure: the host solver gives the same answer
                vectors = torch.linalg.eigh(sym.cpu())[1].to(sym.device)
        else:
            vectors = torch.linalg.eigh(sym)[1] if sym.shape[0] else sym
    return vectors[..., :, 0]
