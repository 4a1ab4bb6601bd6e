"""Law interfaces and the material container.

Conventions (docs/architecture.md): an :class:`Elasticity` maps the *elastic* deformation gradient
F [N,3,3] to the **Kirchhoff stress** tau = P F^T [N,3,3] (Pa); a :class:`Plasticity` maps the trial
deformation gradient after an MPM step to the new elastic one (return mapping). A :class:`Material`
holds one of each plus the density. Analytic laws parametrise stiffness by a learnable ``log_E``
(Young's modulus, Pa) and a fixed ``nu`` buffer (Poisson's ratio), as NCLaw does.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


def lame(E, nu):
    """Lame parameters from Young's modulus and Poisson's ratio (floats or tensors), validated.

    Validation reads ``nu`` on the host (a sync for a CUDA tensor): call it where a law is built, not
    per step; the laws' per-step path uses :func:`lame_unchecked` (``nu`` was validated at construction).

    Args:
        E: Young's modulus [Pa], > 0.
        nu: Poisson's ratio [1], in (-1, 0.5).

    Returns:
        (mu, lam) [Pa]: mu = E / (2 (1 + nu)), lam = E nu / ((1 + nu)(1 - 2 nu)).
    """
    nu_t = torch.as_tensor(nu)
    if not bool(((nu_t > -1) & (nu_t < 0.5)).all()):
        raise ValueError(f"gca/laws/base.py: lame: Poisson's ratio must lie in (-1, 0.5), got {nu}")
    return lame_unchecked(E, nu)


def lame_unchecked(E, nu):
    """:func:`lame` without the host-side check of ``nu`` (no host sync: safe inside a CUDA graph)."""
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def per_particle(p, F: torch.Tensor, name: str, trailing: int) -> torch.Tensor:
    """A scalar or per-particle law parameter as a tensor broadcastable against F-shaped data.

    Args:
        p: number, tensor of shape [] or [N].
        F: [N, 3, 3] reference for N, dtype and device.
        name: parameter name for error messages.
        trailing: number of singleton dims to append to a [N] parameter (2 for [N,3,3] data, 1 for [N,3]).

    Returns:
        p as a tensor of shape [] or [N, 1, ...] on F's device and dtype.
    """
    if isinstance(p, (int, float)):  # a device fill, not a blocking host -> device copy
        return torch.full((), float(p), dtype=F.dtype, device=F.device)
    t = torch.as_tensor(p, dtype=F.dtype, device=F.device)
    if t.ndim == 0:
        return t
    if t.ndim == 1 and t.shape[0] == F.shape[0]:
        return t.reshape(-1, *([1] * trailing))
    raise ValueError(f"gca/laws: parameter {name} must be a scalar or of shape [N={F.shape[0]}], "
                     f"got {tuple(t.shape)}")


class Elasticity(nn.Module):
    """Elastic law: F [N,3,3] -> Kirchhoff stress tau = P F^T [N,3,3] (Pa)."""

    def forward(self, F: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        raise NotImplementedError(f"gca/laws/base.py: {type(self).__name__} must implement forward(F) -> tau")

    def wave_speed(self, rho: torch.Tensor) -> float:
        """Largest P-wave speed sqrt((lam + 2 mu) / rho) [m/s] (for the CFL check)."""
        raise NotImplementedError(f"gca/laws/base.py: {type(self).__name__} does not define wave_speed(rho)")

    def analytic_stress(self, F: torch.Tensor):
        """This law as a :class:`gca.laws.fused.AnalyticStress` that a transfer kernel can evaluate inline (forward
        only), or None (the default: neural and torch-only laws, or the fast path off)."""
        return None


class Plasticity(nn.Module):
    """Plastic return map: trial F [N,3,3] -> elastic F_e [N,3,3]."""

    def forward(self, F_trial: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        raise NotImplementedError(f"gca/laws/base.py: {type(self).__name__} must implement forward(F_trial) -> F_e")


class YoungPoisson:
    """Mixin for analytic laws: learnable ``log_E`` (E in Pa) and a ``nu`` buffer; mu, lam derived."""

    def _init_young_poisson(self, E, nu, learnable: bool = True) -> None:
        E_t = torch.as_tensor(E, dtype=torch.get_default_dtype())
        if not bool((E_t > 0).all()):
            raise ValueError(f"gca/laws: {type(self).__name__}: Young's modulus E must be > 0 Pa, got {E}")
        lame(E_t, torch.as_tensor(nu, dtype=E_t.dtype))  # validates nu
        self.log_E = nn.Parameter(torch.log(E_t), requires_grad=learnable)
        self.register_buffer("nu", torch.as_tensor(nu, dtype=E_t.dtype))

    @property
    def E(self) -> torch.Tensor:
        """Young's modulus [Pa], shape [] or [N]."""
        return torch.exp(self.log_E)

    @property
    def mu(self) -> torch.Tensor:
        """Shear modulus [Pa] (``nu`` validated at construction: no host sync per step)."""
        return lame_unchecked(self.E, self.nu)[0]

    @property
    def lam(self) -> torch.Tensor:
        """First Lame parameter [Pa] (no host sync per step)."""
        return lame_unchecked(self.E, self.nu)[1]

    def wave_speed(self, rho) -> float:
        """Largest P-wave speed sqrt((lam + 2 mu) / rho) [m/s]."""
        with torch.no_grad():
            c2 = (self.lam + 2 * self.mu) / torch.as_tensor(rho, dtype=self.log_E.dtype, device=self.log_E.device)
            return float(torch.sqrt(c2).max())


class Material(nn.Module):
    """One elastic law, one plastic law and the density.

    Args:
        elasticity: F -> tau module.
        plasticity: F_trial -> F_e module.
        rho: density [kg/m^3], scalar or [N].
    """

    def __init__(self, elasticity: Elasticity, plasticity: Plasticity, rho):
        super().__init__()
        if not isinstance(elasticity, Elasticity) or not isinstance(plasticity, Plasticity):
            raise TypeError(f"gca/laws/base.py: Material needs an Elasticity and a Plasticity, got "
                            f"{type(elasticity).__name__}, {type(plasticity).__name__}")
        rho_t = torch.as_tensor(rho, dtype=torch.get_default_dtype())
        if not bool((rho_t > 0).all()):
            raise ValueError(f"gca/laws/base.py: Material: density rho must be > 0 kg/m^3, got {rho}")
        self.elasticity, self.plasticity = elasticity, plasticity
        self.register_buffer("rho", rho_t)

    def stress(self, F: torch.Tensor) -> torch.Tensor:
        """Kirchhoff stress tau [N,3,3] (Pa) of elastic deformation gradients F [N,3,3]."""
        return self.elasticity(F)

    def project(self, F_trial: torch.Tensor) -> torch.Tensor:
        """Elastic deformation gradients F_e [N,3,3] from trial ones [N,3,3]."""
        return self.plasticity(F_trial)

    def wave_speed(self) -> float:
        """Largest P-wave speed [m/s] (CFL: dt < dx / wave_speed)."""
        return self.elasticity.wave_speed(self.rho)


def _check_count(F: torch.Tensor, total: int, where: str) -> None:
    if F.ndim != 3 or F.shape[0] != total:
        raise ValueError(f"gca/laws/base.py: {where}: expected F of shape [{total}, 3, 3] (sum of part counts), "
                         f"got {tuple(F.shape)}")


class _CompositeElasticity(Elasticity):
    """Applies each part's elasticity to its contiguous particle range."""

    def __init__(self, parts: Sequence[Elasticity], counts: Sequence[int]):
        super().__init__()
        self.parts, self.counts = nn.ModuleList(parts), list(counts)

    def forward(self, F: torch.Tensor) -> torch.Tensor:
        _check_count(F, sum(self.counts), "CompositeMaterial.stress")
        return torch.cat([law(Fk) for law, Fk in zip(self.parts, F.split(self.counts))])

    def wave_speed(self, rho) -> float:
        rhos = torch.as_tensor(rho).reshape(-1).expand(sum(self.counts)).split(self.counts)
        return max(law.wave_speed(r) for law, r in zip(self.parts, rhos))


class _CompositePlasticity(Plasticity):
    """Applies each part's plasticity to its contiguous particle range."""

    def __init__(self, parts: Sequence[Plasticity], counts: Sequence[int]):
        super().__init__()
        self.parts, self.counts = nn.ModuleList(parts), list(counts)

    def forward(self, F_trial: torch.Tensor) -> torch.Tensor:
        _check_count(F_trial, sum(self.counts), "CompositeMaterial.project")
        return torch.cat([law(Fk) for law, Fk in zip(self.parts, F_trial.split(self.counts))])


class CompositeMaterial(Material):
    """Different materials on contiguous particle index ranges (particles 0..n0-1 use part 0, ...).

    Args:
        materials: the parts (each a :class:`Material` with a scalar or per-part density).
        counts: particles per part [count]; F passed to stress/project must have sum(counts) rows.
    """

    def __init__(self, materials: Sequence[Material], counts: Sequence[int]):
        counts = [int(c) for c in counts]
        if len(materials) != len(counts) or not materials or min(counts) < 0:
            raise ValueError(f"gca/laws/base.py: CompositeMaterial needs one non-negative count per material, "
                             f"got {len(materials)} materials and counts {counts}")
        rho = torch.cat([m.rho.reshape(-1).expand(c) for m, c in zip(materials, counts)])
        super().__init__(_CompositeElasticity([m.elasticity for m in materials], counts),
                         _CompositePlasticity([m.plasticity for m in materials], counts), rho)
        self.counts = counts
