"""Ground-truth-only laws, deliberately outside the CPR hypothesis library (paper Tab. "OOD").

- :func:`neo_hookean_tau`: compressible neo-Hookean elastomer (SVD-free; also the PAC-NeRF-style rows' elastic law;
  its fast path, :func:`gca.laws.fused.neo_hookean_tau`, is one warp kernel each way).
- :func:`viscoplastic_plastic`: Herschel-Bulkley-type viscoplastic flow (yield stress plus a
  rate-dependent relaxation of the excess deviatoric strain), for the non-Newtonian bottle scene.
"""

from __future__ import annotations

import torch

from gca.laws import fused
from gca.laws.base import Elasticity, Plasticity, YoungPoisson, per_particle
from gca.laws.plastic import SIGMA_MIN, hencky_split
from gca.laws.svd import bmm3, check_F, det3, svd_map, warp_runs

__all__ = ["neo_hookean_tau", "viscoplastic_plastic", "NeoHookeanElasticity", "ViscoplasticPlasticity"]

J_MIN = 1e-3  # lower clamp of J inside log J (finite stress for degenerate/inverted F) [1]


def neo_hookean_tau(F: torch.Tensor, mu, lam, j_min: float = J_MIN) -> torch.Tensor:
    """Compressible neo-Hookean elasticity: tau = mu (F F^T - I) + lam log(J) I.

    Guard: J is clamped to ``j_min`` inside the log (finite, strongly restoring pressure when a
    particle is crushed or inverted; zero volumetric gradient below the clamp).

    Args:
        F: elastic deformation gradients [N, 3, 3].
        mu, lam: Lame parameters [Pa], shape [] or [N].
        j_min: lower clamp of J = det F [1].

    Returns:
        tau [N, 3, 3] (Pa).
    """
    check_F(F, "neo_hookean_tau")
    mu, lam = per_particle(mu, F, "mu", 2), per_particle(lam, F, "lam", 2)
    I = torch.eye(3, dtype=F.dtype, device=F.device).expand_as(F)
    log_J = torch.log(det3(F).clamp(min=j_min))[:, None, None]
    return mu * (bmm3(F, F.transpose(1, 2)) - I) + lam * log_J * I


def _plastic_increment(over, mu, eta, n, dt):
    """d_gamma = min(dt ((2 mu over)/eta)^(1/n), over) [N,1], with a finite gradient at over = 0."""
    positive = over > 0
    base = torch.where(positive, 2 * mu * over / eta, torch.ones_like(over))
    rate = torch.where(positive, base.pow(1.0 / n), torch.zeros_like(over))
    return torch.minimum(dt * rate, over)


def _viscoplastic_map(sigma, mu, sigma_y, eta, n, dt, sigma_min):
    eps, dev, norm, _ = hencky_split(sigma, sigma_min)
    over = (norm - sigma_y / (2 * mu)).clamp(min=0)
    return torch.exp(eps - _plastic_increment(over, mu, eta, n, dt) / norm * dev)


def viscoplastic_plastic(F: torch.Tensor, mu, sigma_y, eta, n, dt: float,
                         sigma_min: float = SIGMA_MIN) -> torch.Tensor:
    """Herschel-Bulkley viscoplastic flow in Hencky strain (Bingham for n = 1).

    With the deviatoric Hencky strain eps_hat and its excess over the von Mises surface
    e = ||eps_hat|| - sigma_y/(2 mu) (so 2 mu e is the deviatoric overstress in Pa), the plastic
    strain rate is gamma_dot = (2 mu e / eta)^(1/n) [1/s] (Herschel-Bulkley: overstress = eta gamma_dot^n).
    One step removes d_gamma = min(dt gamma_dot, e) along eps_hat: the step never crosses the yield
    surface (unconditionally stable), a small eta or large dt recovers von Mises, a large eta gives
    slow creep. n < 1 is shear-thinning, n > 1 shear-thickening.

    Args:
        F: trial deformation gradients [N, 3, 3].
        mu: shear modulus [Pa]; sigma_y: yield stress [Pa]; eta: consistency [Pa s^n] (viscosity
            [Pa s] for n = 1); n: flow index [1]. Each shape [] or [N].
        dt: time step of the simulation [s].
        sigma_min: lower clamp of the singular values [1].

    Returns:
        F_e [N, 3, 3].
    """
    check_F(F, "viscoplastic_plastic")
    if not dt > 0:
        raise ValueError(f"gca/laws/ood.py: viscoplastic_plastic needs a time step dt > 0 s, got {dt}")
    mu, sigma_y = per_particle(mu, F, "mu", 1), per_particle(sigma_y, F, "sigma_y", 1)
    eta, n = per_particle(eta, F, "eta", 1), per_particle(n, F, "n", 1)
    F_proj, sigma = svd_map(F, _viscoplastic_map, mu, sigma_y, eta, n, float(dt), sigma_min)
    with torch.no_grad():
        yielded = (hencky_split(sigma, sigma_min)[2] > sigma_y / (2 * mu)).reshape(-1)
    return torch.where(yielded[:, None, None], F_proj, F)


class NeoHookeanElasticity(YoungPoisson, Elasticity):
    """Neo-Hookean elastomer (see :func:`neo_hookean_tau`): the elastomer's ground truth and the PAC-NeRF-style
    rows' elastic law (``gca.train.law.CATEGORY_LAWS``, learnable E and nu there).

    ``fast_path`` (default True): the stress in one warp kernel each way with a hand-written adjoint
    (:func:`gca.laws.fused.neo_hookean_tau`) where warp runs; False, or elsewhere, the torch reference
    :func:`neo_hookean_tau`. Same values and gradients to rounding (tested); an implementation choice, not part of
    the law.
    """

    fast_path: bool = True

    def __init__(self, E: float = 2e5, nu: float = 0.4, learnable: bool = False):
        super().__init__()
        self._init_young_poisson(E, nu, learnable)

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        if self.fast_path and warp_runs(F):
            check_F(F, "NeoHookeanElasticity")
            return fused.neo_hookean_tau(F, self.mu, self.lam, J_MIN)
        return neo_hookean_tau(F, self.mu, self.lam)

    def analytic_stress(self, F: torch.Tensor):
        """The law for a fused transfer (:func:`gca.laws.fused.analytic`), or None where the fast path is off."""
        return fused.analytic("neo_hookean", F, self.mu, self.lam, J_MIN) if self.fast_path and warp_runs(F) else None


class ViscoplasticPlasticity(YoungPoisson, Plasticity):
    """Herschel-Bulkley viscoplastic flow (see :func:`viscoplastic_plastic`); ground truth only.

    Args:
        E: Young's modulus [Pa]; nu: Poisson's ratio [1] (mu sets the strain-stress scale);
        yield_stress: [Pa]; viscosity: consistency eta [Pa s^n]; flow_index: n [1]; dt: step [s].
    """

    def __init__(self, E: float, nu: float, yield_stress: float, viscosity: float, flow_index: float,
                 dt: float):
        super().__init__()
        self._init_young_poisson(E, nu, learnable=False)
        for name, value in {"yield_stress": yield_stress, "viscosity": viscosity, "flow_index": flow_index,
                            "dt": dt}.items():
            if not value > 0:
                raise ValueError(f"gca/laws/ood.py: ViscoplasticPlasticity: {name} must be > 0, got {value}")
        dtype = self.log_E.dtype
        self.register_buffer("yield_stress", torch.as_tensor(float(yield_stress), dtype=dtype))
        self.register_buffer("viscosity", torch.as_tensor(float(viscosity), dtype=dtype))
        self.register_buffer("flow_index", torch.as_tensor(float(flow_index), dtype=dtype))
        self.dt = float(dt)

    def forward(self, F_trial: torch.Tensor) -> torch.Tensor:
        return viscoplastic_plastic(F_trial, self.mu, self.yield_stress, self.viscosity, self.flow_index, self.dt)
