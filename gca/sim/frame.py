"""One frame of simulation: ``n_steps`` steps of a material on the MPM solver, no autograd policy.

Per step (``docs/architecture.md``): ``tau = material.stress(F)``,
``x, v, C, F_trial = solver.step(x, v, C, F, tau, vol, mass)``, ``F = material.project(F_trial)``.
The lowest module of ``gca.sim`` above the kernels: ``graph`` replays these steps from CUDA graphs and
``rollout`` strings frames together, so both import it and it imports neither.
"""

from __future__ import annotations

import torch

from gca.laws.base import Material
from gca.laws.lora import merged_weights
from gca.laws.plastic import IdentityPlasticity


def law_name(material) -> str:
    """Readable name of a material and its laws, for diagnostics."""
    parts = [type(getattr(material, a)).__name__ for a in ("elasticity", "plasticity") if hasattr(material, a)]
    return f"{type(material).__name__}({', '.join(parts)})" if parts else type(material).__name__


def simulate_frame(solver, material, n_steps: int, x, v, C, F, vol, mass):
    """Run ``n_steps`` steps of ``material`` from state ``(x [N,3], v [N,3], C [N,3,3], F [N,3,3])``.

    Returns:
        The new ``(x, v, C, F)`` with F the projected elastic deformation gradient.
    """
    return simulate_frame_trial(solver, material, n_steps, x, v, C, F, vol, mass)[:4]


def simulate_frame_trial(solver, material, n_steps: int, x, v, C, F, vol, mass):
    """:func:`simulate_frame` that also returns the last step's trial F [N,3,3] (before plasticity).

    A LoRA-adapted law forms its merged weights once for the frame (:func:`gca.laws.lora.merged_weights`),
    not once per step: same values and gradients, ~60 fewer small kernels per step forward and backward.
    """
    F_trial = F
    law = fused_law(solver, material, x, v, C, F)
    if law is not None and n_steps >= 1 and solver.frames_fused and _purely_elastic(material):  # a whole frame
        x, v, C, F_trial = solver.frame_fused(x, v, C, F, law, vol, mass, n_steps)
        return x, v, C, material.project(F_trial), F_trial
    with merged_weights(material):
        for _ in range(n_steps):
            if law is not None:
                x, v, C, F_trial = solver.step_fused(x, v, C, F, law, vol, mass)
            else:
                tau = material.stress(F)
                x, v, C, F_trial = solver.step(x, v, C, F, tau, vol, mass)
            F = material.project(F_trial)
    return x, v, C, F, F_trial


def fused_law(solver, material, x, v, C, F):
    """The material's elastic law for :meth:`gca.sim.solver.MPMSolver.step_fused` (its stress inside P2G), formed
    once for the frame; None where a frame must take the generic step: the solver's ``fuse_analytic`` off, a law
    with no analytic form (neural, composite, torch-only), an elasticity whose ``forward`` is not the class's that
    defines its analytic form (a subclass that changes the law), a material whose ``stress`` is not its
    elasticity's, or a gradient asked for (the state, a parameter of the material or a tensor its moduli come from
    requires one while autograd records: ``gca.laws.fused.analytic`` says None then).
    """
    if not getattr(solver, "fuse_analytic", False) or getattr(type(material), "stress", None) is not Material.stress:
        return None
    if _owner(type(material.elasticity), "forward") is not _owner(type(material.elasticity), "analytic_stress"):
        return None
    if torch.is_grad_enabled() and (any(t.requires_grad for t in (x, v, C, F))
                                    or any(p.requires_grad for p in material.parameters())):
        return None
    return material.elasticity.analytic_stress(F)


def _purely_elastic(material) -> bool:
    """F_e = F_trial exactly: the identity plastic law itself (not a subclass) and the material's own ``project``."""
    return type(material.plasticity) is IdentityPlasticity and type(material).project is Material.project


def _owner(cls: type, name: str) -> type | None:
    """The class of ``cls``'s MRO whose body defines attribute ``name``."""
    return next((c for c in cls.__mro__ if name in vars(c)), None)
