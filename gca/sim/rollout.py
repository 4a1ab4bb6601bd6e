"""Rollout driver: a material and an MPM solver over many steps, with per-frame checkpointing.

Per step (``docs/architecture.md``): ``tau = material.stress(F)``,
``x, v, C, F_trial = solver.step(x, v, C, F, tau, vol, mass)``, ``F = material.project(F_trial)``.

Memory. With ``checkpoint=True`` each frame's steps run under ``torch.utils.checkpoint``
(non-reentrant): autograd keeps only the state at frame starts and recomputes a frame's steps
(laws included) during backward, so memory grows with the number of frames, not of steps.

Health checks, once per frame (one host sync; a swept rollout reads them all after its last frame):
non-finite state, particles moving more than one cell per step, and too many particles sitting on the
position clamp (they left the domain) all raise :class:`SimulationDiverged` with the step, the particle
counts and the law.

Speed. With ``graph`` (default on CUDA) each frame's forward and recompute-backward are replayed
from CUDA graphs (``gca.sim.graph``) instead of launching ~40 kernels per step from Python. Where the frames can
stash their grids (:func:`gca.sim.frame.stashable`) and all of them fit ``MPMSolver.stash_mib``, a frame runner's
rollout (swept or graphed) keeps each frame's stash from its forward pass, and the frames' recomputes skip P2G.
Where the runner also keeps its networks' MLP outputs (``MPMSolver.mlp_stash_mib``), the first frames whose MLP
stashes fit that budget keep them too, and their recomputes launch no MLP forward (:func:`_mlp_frames`).
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Callable

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
    sweep: "ReverseSweep | None" = None  # rollout(..., sweep=True): its reverse-mode pass (no autograd graph)


def check_state(solver: MPMSolver, x, v, F, step: int, law: str) -> int:
    """Raise :class:`SimulationDiverged` on broken state; return the count of clamped particles (one host read).

    Args:
        solver: for dt, dx, the clamp range and the tolerated clamped fraction.
        x, v, F: state after ``step`` steps ([N, 3], [N, 3], [N, 3, 3]).
        step: steps taken so far.
        law: law name for the message.
    """
    return judge_state(solver, x.shape[0], state_stats(solver, x, v, F).tolist(), step, law)


def state_stats(solver: MPMSolver, x, v, F) -> torch.Tensor:
    """(non-finite particles, particles on the clamp, max speed [m/s]) of a state, as a device tensor [3] (no host
    read: :func:`judge_state` reads them)."""
    lo, hi = solver.cfg.clamp_range
    with torch.no_grad():
        finite = torch.isfinite(x).all(1) & torch.isfinite(v).all(1) & torch.isfinite(F).flatten(1).all(1)
        tol = 1e-3 * solver.cfg.dx  # float32 rounding of the clamp bounds is far below this
        on_clamp = ((x <= lo + tol) | (x >= hi - tol)).any(1) & finite
        speed = torch.where(finite, v.norm(dim=1), torch.zeros_like(v[:, 0]))
        return torch.stack([(~finite).sum().to(x.dtype), on_clamp.sum().to(x.dtype), speed.max()])


def judge_state(solver: MPMSolver, n: int, stats, step: int, law: str) -> int:
    """Raise :class:`SimulationDiverged` when the :func:`state_stats` values ``stats`` (host floats) of a state of
    ``n`` particles after ``step`` steps are broken; else return its clamped count."""
    cfg = solver.cfg
    lo, hi = cfg.clamp_range
    n_bad, n_clamped, v_max = stats
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
            graph: bool | None = None, sweep: bool = False) -> Rollout:
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
        sweep: run the frames without autograd (through the frame runner, graphed where ``graph``) and
            attach a :class:`ReverseSweep` as ``Rollout.sweep``: the caller then differentiates frame by frame,
            last first, instead of through an autograd graph of the whole rollout. The returned tensors do
            not require grad; ``v0``'s graph (a learned launch) is reached by :meth:`ReverseSweep.finish`. The
            health checks are read by :meth:`ReverseSweep.judge` (``clamped`` is empty until then), so the call
            returns while the GPU still simulates.

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
    # the swept rollout (training) reads its health checks once, after its last frame, so that the host queues the
    # frames and goes on (to the renders) while the GPU simulates; a broken frame is still named by its step (the
    # frames after it ran on broken state: the stencil's clamped base index keeps every access in the grid)
    checks = [state_stats(solver, x, v, F)] if sweep else None
    xs, vs, Fs, Ftrs, clamped = [x], [v], [F], [F], [] if sweep else [check_state(solver, x, v, F, 0, law)]
    if graph is None:
        graph = solver.cfg.cuda_graphs and solver.device.type == "cuda"
    # a swept rollout always runs through a frame runner; without ``graph`` (sim.cuda_graphs off) its eager twin
    runner = solver.frame_graphs(material, steps_per_frame, x0.shape[0], None if graph else False) \
        if graph or sweep else None
    if runner is not None:
        runner.bind(vol, mass)
    stash = runner is not None and _stash_fits(runner, solver, n_steps // steps_per_frame)
    mlp_frames = _mlp_frames(runner, solver, n_steps // steps_per_frame) if stash else 0
    grids = [] if sweep and stash else None  # each frame's grid stash, for the sweep
    Cs = [C]
    if sweep:
        x, v, C, F = (t.detach() for t in (x, v, C, F))
    for frame in range(n_steps // steps_per_frame):
        args = (solver, material, steps_per_frame, x, v, C, F, vol, mass)
        if sweep:
            x, v, C, F, F_trial = runner.forward(x, v, C, F)
            if grids is not None:
                grids.append(runner.stashed(mlp=frame < mlp_frames))
        elif runner is not None:
            x, v, C, F, F_trial = graphed_frame(runner, x, v, C, F, stash, mlp=frame < mlp_frames)
        elif checkpoint and torch.is_grad_enabled():
            x, v, C, F, F_trial = torch_checkpoint(simulate_frame_trial, *args, use_reentrant=False)
        else:
            x, v, C, F, F_trial = simulate_frame_trial(*args)
        if sweep:
            checks.append(state_stats(solver, x, v, F))
        else:
            clamped.append(check_state(solver, x, v, F, (frame + 1) * steps_per_frame, law))
        xs.append(x)
        vs.append(v)
        Cs.append(C)
        Fs.append(F)
        Ftrs.append(F_trial)
    detach = (lambda t: t.detach()) if sweep else (lambda t: t)  # noqa: E731
    traj = Rollout(x=torch.stack([detach(t) for t in xs]), F=torch.stack([detach(t) for t in Fs]),
                   v=torch.stack([detach(t) for t in vs]), C=C, clamped=clamped,
                   F_trial=torch.stack([detach(t) for t in Ftrs]), refine=k, wave_speed=c)
    if sweep:  # the sweep holds the frames, not the Rollout (no reference cycle: each iteration's frames are freed
        # as soon as it ends, not at the next garbage collection; a 200-iteration run peaked at 9.4 GiB with the cycle)
        traj.sweep = ReverseSweep(runner, (traj.x, traj.v, Cs, traj.F), v0, traj.clamped, lambda: [
            judge_state(solver, x0.shape[0], row, f * steps_per_frame, law)
            for f, row in enumerate(torch.stack(checks).tolist())], grids)
    return traj


def _stash_fits(runner, solver: MPMSolver, n_frames: int) -> bool:
    """Whether a rollout of ``n_frames`` frames through ``runner`` keeps its frames' grid stashes: the frames can
    stash (:attr:`gca.sim.graph.FrameGraphs.stashes`) and all of them fit ``solver.stash_mib``."""
    return runner.stashes and n_frames * runner.stash_bytes <= solver.stash_mib * 2 ** 20


def _mlp_frames(runner, solver: MPMSolver, n_frames: int) -> int:
    """How many of a rollout's ``n_frames`` frames (the first ones) keep their MLP stash beside their grid stash: as
    many as fit ``solver.mlp_stash_mib`` (0 where the runner keeps none: :attr:`gca.sim.graph.FrameGraphs.mlp_nets`).
    Which frames does not change the peak (every frame's stash is alive when the forward pass ends)."""
    per = runner.mlp_stash_bytes
    if per <= 0:
        return 0
    return min(n_frames, int(solver.mlp_stash_mib * 2 ** 20 // per))


class ReverseSweep:
    """The reverse-mode pass of a rollout run with ``sweep=True``, one frame at a time, last frame first.

    Reverse-mode differentiation of the rollout, as autograd would do it through the frames' graph, but driven
    by the caller: it hands in the cotangents of ``x_f`` and ``F_f`` (its losses' gradients at frame ``f``) in
    decreasing ``f`` (:meth:`add`); each frame's adjoint (:meth:`gca.sim.graph.FrameGraphs.backward`: the frame
    recomputed from its saved start state and differentiated, replayed from CUDA graphs on a GPU) runs as soon
    as the cotangent of that frame's outputs is complete. On CUDA the adjoints go to a side stream (after an
    event of the caller's stream), so the caller's host work for the earlier frames (losses, their host reads)
    overlaps the adjoints of the later ones instead of preceding all of them. The result equals autograd's
    through the same frames up to float rounding (the parameters' per-frame gradients are summed in another
    order; tests/test_sim_rollout.py).

    Args:
        runner: the frame runner the forward used (``gca.sim.graph.FrameGraphs``).
        frames: the frame-start states of every frame: x [n_frames + 1, N, 3], v [n_frames + 1, N, 3], C (a list of
            n_frames + 1 [N, 3, 3]) and F [n_frames + 1, N, 3, 3].
        v0: the initial velocity as given to the rollout (with its graph when it requires grad).
        clamped: the rollout's ``clamped`` list, filled by :meth:`judge`.
        checks: reads the rollout's per-frame health checks (one host read), raising :class:`SimulationDiverged` at
            the first broken frame, and returns the clamped counts (:meth:`judge`).
        grids: each frame's grid stash from its forward (``FrameGraphs.stashed``; the frame's adjoint then replays
            it instead of recomputing P2G, and drops it), or None: every frame recomputed.
    """

    def __init__(self, runner, frames: tuple, v0: torch.Tensor, clamped: list, checks: Callable[[], list],
                 grids: list | None = None):
        self.runner, self.v0, self.clamped, self._checks, self.grids = runner, v0, clamped, checks, grids
        self.xs, self.vs, self.Cs, self.Fs = frames
        self.judged = False
        self.last = self.xs.shape[0] - 1
        self.top = self.last  # frames above top have been swept; cot is that of frame top's outputs
        self.next = self.last + 1  # add() takes frames below this one
        zero = lambda t: torch.zeros_like(t)  # noqa: E731
        self.stream = _side_stream(self.xs.device)
        with self._on_side():
            self.cot = [zero(self.xs[-1]), zero(self.vs[-1]), zero(self.Cs[-1]), zero(self.Fs[-1])]
            self.grads: list = [None] * len(runner.params)
        self.done = False

    def judge(self) -> None:
        """Read the rollout's health checks (once; one host read, which waits for the simulation): raise
        :class:`SimulationDiverged` naming the first broken frame's step, else fill ``traj.clamped``. The swept
        rollout returns before its frames are checked so that the host can queue work (the renders) meanwhile;
        :meth:`add` and :meth:`finish` judge first when the caller has not."""
        if not self.judged:
            self.clamped[:] = self._checks()
            self.judged = True

    @property
    def added(self) -> bool:
        """Whether any cotangent was added (:meth:`add`)."""
        return self.next <= self.last

    def _on_side(self):
        return torch.cuda.stream(self.stream) if self.stream is not None else contextlib.nullcontext()

    def add(self, frame: int, g_x: torch.Tensor | None, g_F: torch.Tensor | None) -> None:
        """Add the cotangents [N, 3] / [N, 3, 3] of ``x`` and ``F`` at ``frame`` (None: zero); frames must come in
        decreasing order (each at most once). Sweeps the frames above ``frame`` first (asynchronously on CUDA)."""
        if self.done:
            raise ValueError(f"{_WHERE}: cotangents for frame {frame} after finish()")
        self.judge()
        if not 0 <= frame < self.next:
            raise ValueError(f"{_WHERE}: cotangents for frame {frame} after those of frame {self.next} (or past the "
                             f"last frame, {self.last}): frames must come last first, once each")
        self.next = frame
        if self.stream is not None:  # the side stream starts after what the caller queued so far (g_x, g_F)
            self.stream.wait_stream(torch.cuda.current_stream(self.stream.device))
            for g in (g_x, g_F):
                if g is not None:
                    g.record_stream(self.stream)
        with self._on_side():
            self._sweep_to(frame)
            if g_x is not None:
                self.cot[0] = self.cot[0] + g_x
            if g_F is not None:
                self.cot[3] = self.cot[3] + g_F

    def _sweep_to(self, frame: int) -> None:
        """Adjoints of the frames ``top .. frame + 1`` (the current stream is the side stream)."""
        for f in range(self.top, frame, -1):
            state = (self.xs[f - 1], self.vs[f - 1], self.Cs[f - 1], self.Fs[f - 1])
            grids = None
            if self.grids is not None:  # frame f - 1 -> f's stash, dropped once its adjoint is queued
                grids, self.grids[f - 1] = self.grids[f - 1], None
                if self.stream is not None:  # made on the caller's stream: not reused before the side stream read it
                    for t in grids:
                        t.record_stream(self.stream)
            out = self.runner.backward(state, (*self.cot, torch.zeros_like(self.cot[3])), grids)
            self.cot = list(out[:4])
            self.grads = [g if a is None else a + g for a, g in zip(self.grads, out[4:])]
        self.top = min(self.top, frame)

    def finish(self) -> None:
        """Sweep the remaining frames, add the parameters' gradients into their ``.grad`` and backpropagate the
        initial velocity's cotangent into ``v0``'s graph (when it requires grad); the caller's stream then waits
        for the side stream. With no cotangent ever added (a method without image terms) nothing is swept and no
        ``.grad`` is touched, as autograd would not have run."""
        if self.done:
            raise ValueError(f"{_WHERE}: finish() called twice")
        self.judge()
        if not self.added:  # nothing to differentiate
            self._release()
            return
        if self.stream is not None:
            self.stream.wait_stream(torch.cuda.current_stream(self.stream.device))
        with self._on_side():
            self._sweep_to(0)
        self._release()
        if self.stream is not None:  # made on the side stream, used from now on on the caller's
            for t in (*self.grads, self.cot[1]):
                if t is not None:
                    t.record_stream(torch.cuda.current_stream(self.stream.device))
        for p, g in zip(self.runner.params, self.grads):
            if g is not None:
                p.grad = g if p.grad is None else p.grad + g
        if self.v0.requires_grad:
            torch.autograd.backward(self.v0, self.cot[1])

    def abandon(self) -> None:
        """Stop here (the caller's error): its stream waits for what the side stream still has queued (which reads
        the frames and the runner's buffers), and nothing is added to any ``.grad``."""
        if not self.done:
            self._release()

    def _release(self) -> None:
        if self.stream is not None:
            torch.cuda.current_stream(self.stream.device).wait_stream(self.stream)
        self.done = True
        self.xs = self.vs = self.Cs = self.Fs = None  # the frames are the caller's again (freed with the Rollout)
        self.grids = None


_SIDE_STREAMS: dict = {}


def _side_stream(device: torch.device):
    """One side CUDA stream per device for the reverse sweeps (None off CUDA)."""
    if device.type != "cuda":
        return None
    if device not in _SIDE_STREAMS:
        _SIDE_STREAMS[device] = torch.cuda.Stream(device)
    return _SIDE_STREAMS[device]
