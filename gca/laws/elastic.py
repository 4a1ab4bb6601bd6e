"""Analytic elastic laws (the CPR hypothesis set H_e of the paper, after NCLaw ``material/preset.py``).

Every function maps elastic deformation gradients F [N,3,3] to the **Kirchhoff stress**
tau = P F^T [N,3,3] in Pa. Moduli ``mu``, ``lam`` (Pa) are numbers or tensors of shape [] or [N]
(so CPR can fit them per law by least squares, and they carry gradients). J = det F.
"""

from __future__ import annotations

import torch

from gca.laws import fused
from gca.laws.base import Elasticity, YoungPoisson, lame, per_particle
from gca.laws.svd import bmm3, check_F, det3, polar_rotation, svd_map, warp_runs

__all__ = ["lame", "corotated_tau", "stvk_tau", "volume_tau", "sigma_tau", "ELASTIC_FORMS",
           "CorotatedElasticity", "StVKElasticity", "VolumeElasticity", "SigmaElasticity"]

SIGMA_MIN = 0.05  # lower clamp of singular values inside log (NCLaw's plasticity clamp) [1]


def _eye_like(F: torch.Tensor) -> torch.Tensor:
    return torch.eye(3, dtype=F.dtype, device=F.device).expand_as(F)


def corotated_tau(F: torch.Tensor, mu, lam) -> torch.Tensor:
    """Fixed corotated elasticity: tau = 2 mu (F - R) F^T + lam J (J - 1) I.

    Args:
        F: elastic deformation gradients [N, 3, 3].
        mu, lam: Lame parameters [Pa], shape [] or [N].

    Returns:
        tau [N, 3, 3] (Pa). R is the polar rotation (exact gradient at F = I).
    """
    check_F(F, "corotated_tau")
    mu, lam = per_particle(mu, F, "mu", 2), per_particle(lam, F, "lam", 2)
    J = det3(F)[:, None, None]
    return 2 * mu * bmm3(F - polar_rotation(F), F.transpose(1, 2)) + lam * J * (J - 1) * _eye_like(F)


def stvk_tau(F: torch.Tensor, mu, lam) -> torch.Tensor:
    """St. Venant-Kirchhoff elasticity, the textbook form: tau = F S F^T.

    S = 2 mu E + lam tr(E) I is the second Piola-Kirchhoff stress of the Green strain
    E = 1/2 (F^T F - I). NCLaw's ``StVKElasticity`` returns a different expression,
    2 mu F E + lam J (J - 1) I (a Piola-type term without the trailing F^T, plus the corotated
    volume term); it is not objective (tau(Q F) != Q tau(F) Q^T), so it is not reproduced here.

    Args:
        F: elastic deformation gradients [N, 3, 3].
        mu, lam: Lame parameters [Pa], shape [] or [N].

    Returns:
        tau [N, 3, 3] (Pa).
    """
    check_F(F, "stvk_tau")
    mu, lam = per_particle(mu, F, "mu", 2), per_particle(lam, F, "lam", 2)
    I = _eye_like(F)
    E = 0.5 * (bmm3(F.transpose(1, 2), F) - I)
    tr_E = torch.diagonal(E, dim1=1, dim2=2).sum(-1)[:, None, None]
    S = 2 * mu * E + lam * tr_E * I
    return bmm3(bmm3(F, S), F.transpose(1, 2))


def volume_tau(F: torch.Tensor, lam) -> torch.Tensor:
    """Volume-only (fluid) elasticity, NCLaw "taichi" mode: tau = lam J (J - 1) I.

    Args:
        F: elastic deformation gradients [N, 3, 3].
        lam: first Lame parameter [Pa] (acts as a bulk stiffness), shape [] or [N].

    Returns:
        tau [N, 3, 3] (Pa), a pure pressure.
    """
    check_F(F, "volume_tau")
    lam = per_particle(lam, F, "lam", 2)
    J = det3(F)[:, None, None]
    return lam * J * (J - 1) * _eye_like(F)


def _hencky_principal(sigma: torch.Tensor, mu, lam, sigma_min: float) -> torch.Tensor:
    """Principal Kirchhoff stresses 2 mu eps + lam tr(eps), eps = log(max(sigma, sigma_min)). [N,3]."""
    eps = torch.log(sigma.clamp(min=sigma_min))
    return 2 * mu * eps + lam * eps.sum(dim=-1, keepdim=True)


def sigma_tau(F: torch.Tensor, mu, lam, sigma_min: float = SIGMA_MIN) -> torch.Tensor:
    """Hencky ("sigma") elasticity: tau = U diag(2 mu eps + lam tr(eps)) U^T, eps = log sigma.

    Guard: singular values are clamped to ``sigma_min`` before the log, so extreme compression and
    inversion (sigma_3 < 0, see :func:`gca.laws.svd.svd`) give a large but finite restoring stress;
    below the clamp the stress no longer changes with that singular value (zero gradient there).
    Evaluated by :func:`gca.laws.svd.svd_map` with ``left=True``: exact gradients at F = I.

    Args:
        F: elastic deformation gradients [N, 3, 3].
        mu, lam: Lame parameters [Pa], shape [] or [N].
        sigma_min: lower clamp of the singular values [1].

    Returns:
        tau [N, 3, 3] (Pa).
    """
    check_F(F, "sigma_tau")
    mu, lam = per_particle(mu, F, "mu", 1), per_particle(lam, F, "lam", 1)
    return svd_map(F, _hencky_principal, mu, lam, sigma_min, left=True)[0]


ELASTIC_FORMS = {"corotated": corotated_tau, "stvk": stvk_tau, "volume": volume_tau, "sigma": sigma_tau}
"""The elastic hypothesis set H_e (paper Sec. CPR): name -> tau(F, ...)."""


class CorotatedElasticity(YoungPoisson, Elasticity):
    """Fixed corotated elasticity (see :func:`corotated_tau`) with learnable log_E, fixed nu.

    ``fast_path`` (default True): the stress in warp kernels with a hand-written adjoint
    (:func:`gca.laws.fused.corotated_tau`: the SVD kernel and one stress kernel instead of ~15 torch kernels
    per step) where warp runs; False, or elsewhere, the torch reference :func:`corotated_tau`. Same values and
    gradients to rounding (tested); an implementation choice, not part of the law.
    """

    fast_path: bool = True

    def __init__(self, E: float = 1e5, nu: float = 0.2, learnable: bool = True):
        super().__init__()
        self._init_young_poisson(E, nu, learnable)

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        if self.fast_path and warp_runs(F):
            check_F(F, "CorotatedElasticity")
            return fused.corotated_tau(F, self.mu, self.lam)
        return corotated_tau(F, self.mu, self.lam)

    def analytic_stress(self, F: torch.Tensor):
        """The law for a fused transfer (:func:`gca.laws.fused.analytic`), or None where the fast path is off."""
        return fused.analytic("corotated", F, self.mu, self.lam) if self.fast_path and warp_runs(F) else None


class StVKElasticity(YoungPoisson, Elasticity):
    """St. Venant-Kirchhoff elasticity (see :func:`stvk_tau`) with learnable log_E, fixed nu."""

    def __init__(self, E: float = 1e5, nu: float = 0.2, learnable: bool = True):
        super().__init__()
        self._init_young_poisson(E, nu, learnable)

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        return stvk_tau(F, self.mu, self.lam)


class VolumeElasticity(YoungPoisson, Elasticity):
    """Fluid volume elasticity (see :func:`volume_tau`); lam from (E, nu), no shear stiffness."""

    def __init__(self, E: float = 1e5, nu: float = 0.3, learnable: bool = True):
        super().__init__()
        self._init_young_poisson(E, nu, learnable)

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        return volume_tau(F, self.lam)

    def wave_speed(self, rho) -> float:
        """Pressure-wave speed sqrt(lam / rho) [m/s] (no shear term)."""
        with torch.no_grad():
            return float(torch.sqrt(self.lam / torch.as_tensor(rho, dtype=self.log_E.dtype)).max())


class SigmaElasticity(YoungPoisson, Elasticity):
    """Hencky elasticity (see :func:`sigma_tau`) with learnable log_E, fixed nu."""

    def __init__(self, E: float = 3e5, nu: float = 0.25, learnable: bool = True, sigma_min: float = SIGMA_MIN):
        super().__init__()
        self._init_young_poisson(E, nu, learnable)
        self.sigma_min = sigma_min

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        return sigma_tau(F, self.mu, self.lam, self.sigma_min)
