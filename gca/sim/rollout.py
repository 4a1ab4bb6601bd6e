"""Rollout driver: a material and an MPM solver over many steps, with per-frame checkpointing.

Per step (``docs/architecture.md``): ``tau = material.stress(F)``,
``x, v, C, F_trial = solver.step(x, v, C, F, tau, vol, mass)``, ``F = material.project(F_trial)``.

Memory. With ``checkpoint=True`` each frame's steps run under ``torch.utils.checkpoint``
(non-reentrant): autograd keeps only the state at frame starts and recomputes a frame's steps
(laws included) during backward, so memory grows with the number of frames, not of steps.

Health checks, once per frame (one host sync): non-finite state, particles moving more than one
cell per step, and too many particles sitting on the position clamp (they left the domain) all
raise :class:`SimulationDiverged` with the step, the particle counts and the law.

Speed. With ``graph`` (default on CUDA) each frame's forward and recompute-backward are replayed
from CUDA graphs (``gca.sim.graph``) instead of launching ~40 kernels per step from Python.
"""

from __future__ import annotations

import dataclasses

import torch
from torch.utils.checkpoint import checkpoint as torch_checkpoint

from gca.sim.cfl import refinement
from gca.sim.frame import law_name, simulate_frame_trial
from gca.sim.graph import graphed_frame
from gca.sim.solver import MPMSolver

_WHERE = "gca/sim/rollout.py"


class SimulationDiverged(RuntimeError):
    """The simulation produced non-finite or runaway state (message names step, counts and law)."""


@dataclasses.dataclass
class Rollout:
    """Per-frame output of :func:`rollout`; frame 0 is the initial state.

    Attributes:
        x: positions [n_frames + 1, N, 3] (m, sim frame).
        F: elastic deformation gradients [n_frames + 1, N, 3, 3] (for the Gaussians' covariances).
        v: velocities [n_frames + 1, N, 3] (m/s).
        C: APIC affine fields at the last frame [N, 3, 3] (1/s).
        clamped: particles on the position clamp at each frame [n_frames + 1] (count).
        F_trial: trial deformation gradients of each frame's last step, before the plastic
            projection [n_frames + 1, N, 3, 3] (frame 0: the initial F). CPR fits the plastic
            hypotheses on (F_trial, F) pairs.
    """

    x: torch.Tensor
    F: torch.Tensor
    v: torch.Tensor
    C: torch.Tensor
    clamped: list
    F_trial: torch.Tensor | None = None
    refine: int = 1  # each step was taken as this many steps of dt / refine (CFL refinement)
    wave_speed: float | None = None  # the material's wave speed estimate the CFL check used [m/s]


def check_state(solver: MPMSolver, x, v, F, step: int, law: str) -> int:
    """Raise :class:`SimulationDiverged` on broken state; return the count of clamped particles.

    Args:
        solver: for dt, dx, the clamp range and the tolerated clamped fraction.
        x, v, F: state after ``step`` steps ([N, 3], [N, 3], [N, 3, 3]).
        step: steps taken so far.
        law: law name for the message.
    """
    cfg = solver.cfg
    n = x.shape[0]
    lo, hi = cfg.clamp_range
    with torch.no_grad():
        finite = torch.isfinite(x).all(1) & torch.isfinite(v).all(1) & torch.isfinite(F).flatten(1).all(1)
        tol = 1e-3 * cfg.dx  # float32 rounding of the clamp bounds is far below this
        on_clamp = ((x <= lo + tol) | (x >= hi - tol)).any(1) & finite
        speed = torch.where(finite, v.norm(dim=1), torch.zeros_like(v[:, 0]))
        n_bad, n_clamped, v_max = torch.stack([(~finite).sum().to(x.dtype), on_clamp.sum().to(x.dtype),
                                               speed.max()]).tolist()
    where = f"{_WHERE}: after step {step}, law {law}"
    if n_bad:
        raise SimulationDiverged(f"{where}: {int(n_bad)} of {n} particles have non-finite x, v or F "
                                 f"(dt={cfg.dt:g} s; check the CFL bound and the law's stress)")
    if v_max * cfg.dt > cfg.dx:
        raise SimulationDiverged(f"{where}: max speed {v_max:.4g} m/s moves particles more than one cell "
                                 f"(dx={cfg.dx:.4g} m) per step (dt={cfg.dt:g} s) in a population of {n}")
    if n_clamped > cfg.max_clamped_fraction * n:
        raise SimulationDiverged(f"{where}: {int(n_clamped)} of {n} particles sit on the domain clamp "
                                 f"[{lo:.4g}, {hi:.4g}] m (left the domain; limit "
                                 f"{cfg.max_clamped_fraction:g} of them)")
    return int(n_clamped)


def _check_inputs(x0, v0, vol, mass, n_steps, steps_per_frame):
    n = x0.shape[0] if x0.dim() == 2 else -1
    for name, t, shape in (("x0", x0, (n, 3)), ("v0", v0, (n, 3)), ("vol", vol, (n,)), ("mass", mass, (n,))):
        if tuple(t.shape) != shape:
            raise ValueError(f"{_WHERE}: {name} must have shape {shape} (N from x0), got {tuple(t.shape)}")
    if steps_per_frame < 1 or n_steps < 1 or n_steps % steps_per_frame:
        raise ValueError(f"{_WHERE}: n_steps={n_steps} must be a positive multiple of "
                         f"steps_per_frame={steps_per_frame}")


def rollout(solver: MPMSolver, material, x0, v0, vol, mass, n_steps: int, steps_per_frame: int,
            checkpoint: bool = True, C0=None, F0=None, wave_speed: float | None = None,
            graph: bool | None = None) -> Rollout:
    """Simulate ``material`` from ``(x0, v0)`` and return every frame.

    Args:
        solver: the MPM solver (its cfg gives dt, grid, walls, CFL number).
        material: object with ``stress(F) -> tau``, ``project(F_trial) -> F_e`` and ``wave_speed()``
            (``gca.laws.base.Material``).
        x0: initial positions [N, 3] (m, sim frame).
        v0: initial velocities [N, 3] (m/s); may require grad.
        vol: particle volumes [N] (m^3).
        mass: particle masses [N] (kg).
        n_steps: steps to simulate; a multiple of ``steps_per_frame``.
        steps_per_frame: steps between returned frames.
        checkpoint: recompute each frame's steps in backward instead of storing them.
        C0: initial affine fields [N, 3, 3] (default zero).
        F0: initial elastic deformation gradients [N, 3, 3] (default identity).
        wave_speed: material wave speed for the CFL check [m/s] (default ``material.wave_speed()``).
        graph: run each frame through :class:`gca.sim.graph.FrameGraphs` (CUDA graphs on a GPU, their
            eager twin on the CPU; same memory profile as ``checkpoint``). Default: on when the
            solver runs on CUDA and ``cfg.cuda_graphs`` is set.

    Returns:
        :class:`Rollout` with ``n_steps // steps_per_frame + 1`` frames.

    Raises:
        CFLError: dt / ``cfg.max_refine`` too large for the wave speed and the initial speeds.
        SimulationDiverged: non-finite or runaway state, or particles leaving the domain.
    """
    _check_inputs(x0, v0, vol, mass, n_steps, steps_per_frame)
    c = float(material.wave_speed() if wave_speed is None else wave_speed)
    k = refinement(solver.cfg, c, float(v0.detach().norm(dim=1).max()))
    solver, n_steps, steps_per_frame = solver.refined(k), n_steps * k, steps_per_frame * k
    eye = torch.eye(3, dtype=x0.dtype, device=x0.device)
    C = torch.zeros(x0.shape[0], 3, 3, dtype=x0.dtype, device=x0.device) if C0 is None else C0
    F = eye.expand(x0.shape[0], 3, 3).contiguous() if F0 is None else F0
    # the CFL estimate and the refinement in every diagnostic: a law stiffer under large strain than its estimate
    # (taken at small strain) shows as a blow-up at refine 1
    x, v, law = x0, v0, f"{law_name(material)} (CFL: wave speed estimate {c:.4g} m/s, {k} sub-step(s) per step)"
    xs, vs, Fs, Ftrs, clamped = [x], [v], [F], [F], [check_state(solver, x, v, F, 0, law)]
    if graph is None:
        graph = solver.cfg.cuda_graphs and solver.device.type == "cuda"
    runner = solver.frame_graphs(material, steps_per_frame, x0.shape[0]) if graph else None
    if runner is not None:
        runner.bind(vol, mass)
    for frame in range(n_steps // steps_per_frame):
        args = (solver, material, steps_per_frame, x, v, C, F, vol, mass)
        if runner is not None:
            x, v, C, F, F_trial = graphed_frame(runner, x, v, C, F)
        elif checkpoint and torch.is_grad_enabled():
            x, v, C, F, F_trial = torch_checkpoint(simulate_frame_trial, *args, use_reentrant=False)
        else:
            x, v, C, F, F_trial = simulate_frame_trial(*args)
        clamped.append(check_state(solver, x, v, F, (frame + 1) * steps_per_frame, law))
        xs.append(x)
        vs.append(v)
        Fs.append(F)
        Ftrs.append(F_trial)
    return Rollout(x=torch.stack(xs), F=torch.stack(Fs), v=torch.stack(vs), C=C, clamped=clamped,
                   F_trial=torch.stack(Ftrs), refine=k, wave_speed=c)
