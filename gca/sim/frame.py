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
from gca.laws.neural import frame_mlp_sums
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


def simulate_frame_trial(solver, material, n_steps: int, x, v, C, F, vol, mass, grids=None):
    """:func:`simulate_frame` that also returns the last step's trial F [N,3,3] (before plasticity).

    A LoRA-adapted law forms its merged weights once for the frame (:func:`gca.laws.lora.merged_weights`),
    not once per step: same values and gradients, ~60 fewer small kernels per step forward and backward. With the
    solver's ``frame_mlp_grads`` (on by default since session 58), a network on the fused Triton MLP also sums its
    weight gradients once for the frame (:func:`gca.laws.neural.frame_mlp_sums`): the same gradients to float
    rounding.

    ``grids``: the frame's grid stash, ``(mv [n_steps, R G, G, G, 3], m [n_steps, R G, G, G])``; step ``i`` records
    its grid into entry ``i`` (no gradient recorded) or replays it (``MPMSolver.step``'s ``grid``). Only a frame
    that takes the generic step can stash (:func:`stashable`).
    """
    F_trial = F
    law = fused_law(solver, material, x, v, C, F)
    if grids is not None and law is not None:
        raise ValueError("gca/sim/frame.py: a frame of an analytic law's fused step has no grid stash "
                         "(stashable(solver, material) is False)")
    if law is not None and n_steps >= 1 and solver.frames_fused and _purely_elastic(material):  # a whole frame
        x, v, C, F_trial = solver.frame_fused(x, v, C, F, law, vol, mass, n_steps)
        return x, v, C, material.project(F_trial), F_trial
    with merged_weights(material), frame_mlp_sums(material, getattr(solver, "frame_mlp_grads", False)):
        for i in range(n_steps):
            if law is not None:
                x, v, C, F_trial = solver.step_fused(x, v, C, F, law, vol, mass)
            else:
                tau = material.stress(F)
                x, v, C, F_trial = solver.step(x, v, C, F, tau, vol, mass,
                                               grid=None if grids is None else (grids[0][i], grids[1][i]))
            F = material.project(F_trial)
    return x, v, C, F, F_trial


def stashable(solver, material) -> bool:
    """Whether a frame of ``material`` can keep a grid stash (``MPMSolver.stash_mib``): its forward pass, run without
    autograd, takes the generic step (no analytic law fused into P2G, :func:`fused_law`), and the solver keeps the
    grid for its backward (``keep_grid``)."""
    return solver.stash_mib > 0 and solver.keep_grid and not _has_fused_form(solver, material)


def _has_fused_form(solver, material) -> bool:
    """Whether :func:`fused_law` gives ``material`` an analytic law where no gradient is asked for."""
    if not getattr(solver, "fuse_analytic", False) or getattr(type(material), "stress", None) is not Material.stress:
        return False
    return _owner(type(material.elasticity), "forward") is _owner(type(material.elasticity), "analytic_stress")


def fused_law(solver, material, x, v, C, F):
    """The material's elastic law for :meth:`gca.sim.solver.MPMSolver.step_fused` (its stress inside P2G), formed
    once for the frame; None where a frame must take the generic step: the solver's ``fuse_analytic`` off, a law
    with no analytic form (neural, composite, torch-only), an elasticity whose ``forward`` is not the class's that
    defines its analytic form (a subclass that changes the law), a material whose ``stress`` is not its
    elasticity's, or a gradient asked for (the state, a parameter of the material or a tensor its moduli come from
    requires one while autograd records: ``gca.laws.fused.analytic`` says None then).
    """
    if not _has_fused_form(solver, material):
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
