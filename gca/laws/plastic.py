"""Analytic plastic return maps (the CPR hypothesis set H_p, after NCLaw ``material/preset.py``).

Each function maps trial deformation gradients F [N,3,3] (after an MPM step) to elastic ones F_e
[N,3,3]. Return maps work in Hencky strain eps = log(sigma) of the SVD F = U diag(sigma) Vh and
rebuild F_e = U diag(exp eps') Vh; particles inside the yield surface are returned unchanged (F
itself, so their gradient is the identity). Parameters are numbers or tensors of shape [] or [N].
"""

from __future__ import annotations

import math

import torch

from gca.laws.base import Plasticity, YoungPoisson, per_particle
from gca.laws.svd import check_F, det3, svd_map

__all__ = ["identity_plastic", "sigma_plastic", "von_mises_plastic", "drucker_prager_plastic",
           "drucker_prager_alpha", "PLASTIC_FORMS", "IdentityPlasticity", "SigmaPlasticity",
           "VonMisesPlasticity", "DruckerPragerPlasticity"]

SIGMA_MIN = 0.05  # lower clamp of singular values before the log (NCLaw) [1]
J_MIN = 1e-3  # lower clamp of det F in the fluid projection [1]
NORM_FLOOR = 1e-30  # added under the square root of ||dev eps||^2 (keeps its gradient finite at 0)


def identity_plastic(F: torch.Tensor) -> torch.Tensor:
    """No plasticity: F_e = F. F [N,3,3] -> [N,3,3]."""
    check_F(F, "identity_plastic")
    return F


def sigma_plastic(F: torch.Tensor, j_min: float = J_MIN) -> torch.Tensor:
    """Fluid projection: F_e = J^(1/3) I (keeps the volume change, forgets all shear).

    Args:
        F: trial deformation gradients [N, 3, 3].
        j_min: lower clamp of J = det F (NCLaw has none and returns NaN for J <= 0) [1].

    Returns:
        F_e [N, 3, 3].
    """
    check_F(F, "sigma_plastic")
    J = det3(F).clamp(min=j_min)
    return J.pow(1.0 / 3.0)[:, None, None] * torch.eye(3, dtype=F.dtype, device=F.device)


def hencky_split(sigma: torch.Tensor, sigma_min: float = SIGMA_MIN):
    """Hencky strain of singular values [N,3] -> (eps [N,3], dev eps [N,3], ||dev eps|| [N,1], tr eps [N,1])."""
    eps = torch.log(sigma.clamp(min=sigma_min))
    tr = eps.sum(dim=-1, keepdim=True)
    dev = eps - tr / 3
    norm = torch.sqrt((dev * dev).sum(dim=-1, keepdim=True) + NORM_FLOOR)
    return eps, dev, norm, tr


def _von_mises_map(sigma, mu, sigma_y, sigma_min):
    eps, dev, norm, _ = hencky_split(sigma, sigma_min)
    d_gamma = (norm - sigma_y / (2 * mu)).clamp(min=0)
    return torch.exp(eps - d_gamma / norm * dev)


def _keep_inside(F: torch.Tensor, F_proj: torch.Tensor, yielded: torch.Tensor) -> torch.Tensor:
    """F_proj where yielded [N] else F (exactly)."""
    return torch.where(yielded[:, None, None], F_proj, F)


def von_mises_plastic(F: torch.Tensor, mu, sigma_y, sigma_min: float = SIGMA_MIN) -> torch.Tensor:
    """Von Mises return map in Hencky strain (NCLaw ``VonMisesPlasticity``).

    With eps = log max(sigma, sigma_min) and its deviator eps_hat: d_gamma = ||eps_hat|| - sigma_y/(2 mu);
    where d_gamma > 0, eps <- eps - d_gamma eps_hat / ||eps_hat||, so ||dev eps'|| = sigma_y / (2 mu).

    Args:
        F: trial deformation gradients [N, 3, 3].
        mu: shear modulus [Pa], shape [] or [N].
        sigma_y: yield stress [Pa], shape [] or [N].
        sigma_min: lower clamp of the singular values [1].

    Returns:
        F_e [N, 3, 3].
    """
    check_F(F, "von_mises_plastic")
    mu, sigma_y = per_particle(mu, F, "mu", 1), per_particle(sigma_y, F, "sigma_y", 1)
    F_proj, sigma = svd_map(F, _von_mises_map, mu, sigma_y, sigma_min)
    with torch.no_grad():
        norm = hencky_split(sigma, sigma_min)[2]
        yielded = (norm > sigma_y / (2 * mu)).reshape(-1)
    return _keep_inside(F, F_proj, yielded)


def drucker_prager_alpha(friction_angle_deg):
    """Cone slope alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) of the friction angle phi [deg]."""
    phi = friction_angle_deg if isinstance(friction_angle_deg, torch.Tensor) else torch.tensor(
        float(friction_angle_deg), dtype=torch.float64)
    s = torch.sin(phi * (math.pi / 180.0))
    return math.sqrt(2.0 / 3.0) * 2 * s / (3 - s)


def _drucker_prager_map(sigma, mu, lam, alpha, cohesion, sigma_min):
    eps, dev, norm, tr = hencky_split(sigma, sigma_min)
    shifted = tr - 3 * cohesion
    d_gamma = norm + (3 * lam + 2 * mu) / (2 * mu) * shifted * alpha
    compressed = eps - d_gamma.clamp(min=0) / norm * dev
    apex = torch.zeros_like(eps) + cohesion
    return torch.exp(torch.where(shifted < 0, compressed, apex))


def drucker_prager_plastic(F: torch.Tensor, mu, lam, friction_angle_deg, cohesion=0.0,
                           sigma_min: float = SIGMA_MIN) -> torch.Tensor:
    """Drucker-Prager sand return map in Hencky strain (Klar et al. 2016, NCLaw).

    With eps = log max(sigma, sigma_min), t = tr(eps) - 3 c and
    d_gamma = ||eps_hat|| + (3 lam + 2 mu)/(2 mu) t alpha:
    compression (t < 0): eps <- eps - max(d_gamma, 0) eps_hat / ||eps_hat|| (onto the cone
    ||eps_hat|| = -alpha (3 lam + 2 mu)/(2 mu) t); tension (t >= 0): eps <- (c, c, c), i.e.
    F_e = exp(c) U Vh (the polar rotation for c = 0).

    Args:
        F: trial deformation gradients [N, 3, 3].
        mu, lam: Lame parameters [Pa], shape [] or [N].
        friction_angle_deg: friction angle phi [deg], shape [] or [N].
        cohesion: c, a log-strain offset of the cone apex (NCLaw convention, not a stress) [1].
        sigma_min: lower clamp of the singular values [1].

    Returns:
        F_e [N, 3, 3].
    """
    check_F(F, "drucker_prager_plastic")
    mu, lam = per_particle(mu, F, "mu", 1), per_particle(lam, F, "lam", 1)
    alpha = drucker_prager_alpha(per_particle(friction_angle_deg, F, "friction_angle_deg", 1))
    c = per_particle(cohesion, F, "cohesion", 1)
    F_proj, sigma = svd_map(F, _drucker_prager_map, mu, lam, alpha, c, sigma_min)
    with torch.no_grad():
        inside = (_drucker_prager_d_gamma(sigma, mu, lam, alpha, c, sigma_min) <= 0).reshape(-1)
    return _keep_inside(F, F_proj, ~inside)


def _drucker_prager_d_gamma(sigma, mu, lam, alpha, c, sigma_min):
    """d_gamma [N,1] where in compression, +inf in tension (always projected)."""
    _, _, norm, tr = hencky_split(sigma, sigma_min)
    shifted = tr - 3 * c
    d_gamma = norm + (3 * lam + 2 * mu) / (2 * mu) * shifted * alpha
    return torch.where(shifted < 0, d_gamma, torch.full_like(d_gamma, math.inf))


PLASTIC_FORMS = {"identity": identity_plastic, "sigma": sigma_plastic, "von_mises": von_mises_plastic,
                 "drucker_prager": drucker_prager_plastic}
"""The plastic hypothesis set H_p (paper Sec. CPR): name -> F_e(F, ...)."""


class IdentityPlasticity(Plasticity):
    """Purely elastic material: F_e = F_trial."""

    def forward(self, F_trial: torch.Tensor) -> torch.Tensor:
        return identity_plastic(F_trial)


class SigmaPlasticity(Plasticity):
    """Fluid projection F_e = J^(1/3) I (see :func:`sigma_plastic`)."""

    def forward(self, F_trial: torch.Tensor) -> torch.Tensor:
        return sigma_plastic(F_trial)


class VonMisesPlasticity(YoungPoisson, Plasticity):
    """Von Mises plasticity with learnable log_E and log yield stress, fixed nu."""

    def __init__(self, E: float = 3e5, nu: float = 0.25, yield_stress: float = 5e3, learnable: bool = True):
        super().__init__()
        self._init_young_poisson(E, nu, learnable)
        if not yield_stress > 0:
            raise ValueError(f"gca/laws/plastic.py: VonMisesPlasticity: yield_stress must be > 0 Pa, got {yield_stress}")
        log_y = torch.log(torch.as_tensor(yield_stress, dtype=self.log_E.dtype))
        self.log_yield_stress = torch.nn.Parameter(log_y, requires_grad=learnable)

    @property
    def yield_stress(self) -> torch.Tensor:
        """Yield stress sigma_y [Pa]."""
        return torch.exp(self.log_yield_stress)

    def forward(self, F_trial: torch.Tensor) -> torch.Tensor:
        return von_mises_plastic(F_trial, self.mu, self.yield_stress)


class DruckerPragerPlasticity(YoungPoisson, Plasticity):
    """Drucker-Prager plasticity with learnable log_E and friction angle [deg], fixed nu and cohesion."""

    def __init__(self, E: float = 1e6, nu: float = 0.2, friction_angle: float = 25.0, cohesion: float = 0.0,
                 learnable: bool = True):
        super().__init__()
        self._init_young_poisson(E, nu, learnable)
        if not 0 < friction_angle < 90:
            raise ValueError(f"gca/laws/plastic.py: friction_angle must be in (0, 90) deg, got {friction_angle}")
        self.friction_angle = torch.nn.Parameter(torch.as_tensor(float(friction_angle), dtype=self.log_E.dtype),
                                                 requires_grad=learnable)
        self.register_buffer("cohesion", torch.as_tensor(float(cohesion), dtype=self.log_E.dtype))

    def forward(self, F_trial: torch.Tensor) -> torch.Tensor:
        return drucker_prager_plastic(F_trial, self.mu, self.lam, self.friction_angle, self.cohesion)
