"""Particle trajectories for pretraining the neural prior M_0 (NCLaw-style data, reference notes §5.1).

A trajectory is a thrown body of one analytic material: a cube, sphere, ellipsoid or capsule, sampled
on a particle lattice aligned with the simulation grid (spacing ``dx / particles_per_cell``) inside the
randomly rotated shape, resting its lowest particle a little above the floor's wall region and launched
with a rigid velocity ``v = v_lin + omega x (x - c)``. ``v_lin`` points downwards (at most
``max_tilt_deg`` away from -y) with speed ~ U(speed); omega ~ U(-max_spin, max_spin)^3 (NCLaw:
|v_lin| ~ U(0, 3) m/s with y forced down, omega ~ U(0, 3)^3 rad/s). The analytic law is simulated
with the project's MPM solver and the **full state** ``(x, v, C, F)`` of every step is stored, so the
training can restart from any ground-truth step (teacher forcing).

Everything is seeded: one ``torch.Generator`` per trajectory, from (seed, split, index).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import torch

from gca.laws.base import Material
from gca.laws.pretrain import random_rotations
from gca.sim import MPMSolver, check_cfl
from gca.sim.frame import law_name, simulate_frame
from gca.sim.rollout import check_state

_WHERE = "gca/train/prior_data.py"
SHAPES = ("cube", "sphere", "ellipsoid", "capsule")
SPLITS = {"train": 0, "heldout": 1}  # stream index of the trajectory seeds


@dataclasses.dataclass(frozen=True)
class PriorDataConfig:
    """How the pretraining trajectories are drawn (params ``prior.train.data``)."""

    shapes: tuple[str, ...] = SHAPES  # body shapes drawn uniformly, from SHAPES
    particles_per_axis: int = 16  # particles across the body's largest extent {paper: 12, ci: 6} [count]
    particles_per_cell: int = 2  # lattice points per grid cell and axis (spacing dx / this) [count]
    n_steps: int = 500  # simulated steps per trajectory {paper: 400, ci: 80} [count]
    speed: tuple[float, float] = (0.5, 3.0)  # launch speed range |v_lin| [m/s]
    max_tilt_deg: float = 60.0  # largest angle between v_lin and straight down [deg]
    max_spin: float = 3.0  # angular velocity components ~ U(-max_spin, max_spin) [rad/s]
    floor_gap: tuple[float, float] = (0.0, 0.1)  # lowest particle above the floor's wall region [m]

    def __post_init__(self):
        for name in ("shapes", "speed", "floor_gap"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        problems = []
        if not self.shapes or set(self.shapes) - set(SHAPES):
            problems.append(f"shapes={self.shapes} must be a non-empty subset of {SHAPES}")
        if self.particles_per_axis < 2 or self.particles_per_cell < 1 or self.n_steps < 2:
            problems.append("need particles_per_axis >= 2, particles_per_cell >= 1, n_steps >= 2")
        if len(self.speed) != 2 or not 0 <= self.speed[0] <= self.speed[1]:
            problems.append(f"speed={self.speed} must be [min, max] with 0 <= min <= max")
        if len(self.floor_gap) != 2 or not 0 <= self.floor_gap[0] <= self.floor_gap[1]:
            problems.append(f"floor_gap={self.floor_gap} must be [min, max] with 0 <= min <= max")
        if not (0 <= self.max_tilt_deg <= 90 and self.max_spin >= 0):
            problems.append("need 0 <= max_tilt_deg <= 90 and max_spin >= 0")
        if problems:
            raise ValueError(f"{_WHERE}: bad PriorDataConfig: " + "; ".join(problems))


@dataclasses.dataclass
class Trajectory:
    """Ground-truth states of one body at every step (step 0 is the launch state).

    Attributes:
        x: positions [T+1, N, 3] (m, sim frame).
        v: velocities [T+1, N, 3] (m/s).
        C: APIC affine fields [T+1, N, 3, 3] (1/s).
        F: elastic deformation gradients [T+1, N, 3, 3].
        vol: particle volumes [N] (m^3).
        mass: particle masses [N] (kg).
        info: shape, seed, launch velocity and spin (for logs).
    """

    x: torch.Tensor
    v: torch.Tensor
    C: torch.Tensor
    F: torch.Tensor
    vol: torch.Tensor
    mass: torch.Tensor
    info: dict

    @property
    def n_steps(self) -> int:
        return self.x.shape[0] - 1

    def state(self, step: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The ground-truth ``(x [N,3], v [N,3], C [N,3,3], F [N,3,3])`` after ``step`` steps."""
        return self.x[step], self.v[step], self.C[step], self.F[step]


def trajectory_seed(seed: int, split: str, index: int) -> int:
    """Seed of trajectory ``index`` of ``split`` ("train" or "heldout"): disjoint streams per split."""
    if split not in SPLITS:
        raise ValueError(f"{_WHERE}: unknown split {split!r}; expected one of {list(SPLITS)}")
    return (int(seed) * 2 + SPLITS[split]) * 1_000_003 + int(index)


def inside_shape(kind: str, p: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """Which body-frame points lie inside a shape centred at the origin.

    Args:
        kind: one of SHAPES. cube/ellipsoid: half-extents ``half``; sphere: radius ``half[0]``;
            capsule: axis along x, radius ``half[1]``, total half-length ``half[0]``.
        p: body-frame points [M, 3] (m).
        half: shape half-extents [3] (m).

    Returns:
        Boolean mask [M].
    """
    if kind == "cube":
        return (p.abs() <= half).all(dim=1)
    if kind in ("sphere", "ellipsoid"):
        return ((p / half).square().sum(dim=1)) <= 1.0
    if kind == "capsule":
        r = half[1]
        seg = (half[0] - r).clamp(min=0)
        nearest = torch.stack([p[:, 0].clamp(-seg, seg), torch.zeros_like(p[:, 0]), torch.zeros_like(p[:, 0])], 1)
        return (p - nearest).norm(dim=1) <= r
    raise ValueError(f"{_WHERE}: unknown shape {kind!r}; expected one of {SHAPES}")


def shape_half_extents(kind: str, length: float, generator: torch.Generator) -> torch.Tensor:
    """Half-extents [3] (m) of a shape whose largest extent is ``length`` (random aspect ratios)."""
    aspect = 0.5 + 0.5 * torch.rand(2, generator=generator, dtype=torch.float64)
    if kind == "ellipsoid":
        return 0.5 * length * torch.cat([torch.ones(1, dtype=torch.float64), aspect])
    if kind == "capsule":
        radius = 0.5 * length * (0.3 + 0.2 * aspect[0])
        return torch.stack([torch.tensor(0.5 * length, dtype=torch.float64), radius, radius])
    return torch.full((3,), 0.5 * length, dtype=torch.float64)


def lattice_body(kind: str, half: torch.Tensor, rotation: torch.Tensor, spacing: float) -> torch.Tensor:
    """Grid-aligned lattice points inside the rotated shape, centred near the origin.

    Args:
        kind: one of SHAPES.
        half: half-extents [3] (m).
        rotation: body-to-sim rotation [3, 3].
        spacing: lattice spacing h (m); points sit at (i + 1/2) h.

    Returns:
        Positions [N, 3] (m, float64) relative to the shape centre.
    """
    radius = float(half.norm())
    n = math.ceil(radius / spacing) + 1
    axis = (torch.arange(-n, n, dtype=torch.float64) + 0.5) * spacing
    p = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    return p[inside_shape(kind, p @ rotation, half)]  # p @ R = (R^T p^T)^T: sim -> body frame


def place_on_floor(x: torch.Tensor, cfg: PriorDataConfig, solver: MPMSolver,
                   generator: torch.Generator) -> torch.Tensor:
    """Translate a body [N, 3] to a random horizontal spot, lowest particle ``floor_gap`` above the walls.

    The wall region is the ``bound`` cells at each face; a particle feels it when its stencil reaches
    a wall node, i.e. below ``(bound + 1/2) dx``. Horizontal centres keep the body that far from the sides.
    """
    dx, bound = solver.cfg.dx, solver.cfg.bound
    wall = (bound + 0.5) * dx
    lo, hi = x.min(dim=0).values, x.max(dim=0).values
    u = torch.rand(3, generator=generator, dtype=torch.float64)
    room = (1.0 - 2 * wall) - (hi - lo)
    if bool((room[[0, 2]] < 0).any()) or float(hi[1] - lo[1]) + wall + cfg.floor_gap[1] > 1.0 - wall:
        raise ValueError(f"{_WHERE}: a body of extent {(hi - lo).tolist()} m does not fit the domain with walls "
                         f"of {bound} cells (dx={dx:g} m); lower particles_per_axis or floor_gap")
    gap = cfg.floor_gap[0] + u[1] * (cfg.floor_gap[1] - cfg.floor_gap[0])
    shift = torch.stack([wall + u[0] * room[0] - lo[0], wall + gap - lo[1], wall + u[2] * room[2] - lo[2]])
    return x + shift


def launch_velocity(x: torch.Tensor, cfg: PriorDataConfig, generator: torch.Generator):
    """Rigid launch velocities v = v_lin + omega x (x - c) [N, 3] (m/s), plus (v_lin [3], omega [3])."""
    g = generator
    tilt = math.radians(cfg.max_tilt_deg) * torch.rand((), generator=g, dtype=torch.float64)
    azimuth = 2 * math.pi * torch.rand((), generator=g, dtype=torch.float64)
    direction = torch.stack([torch.sin(tilt) * torch.cos(azimuth), -torch.cos(tilt), torch.sin(tilt) * torch.sin(azimuth)])
    speed = cfg.speed[0] + (cfg.speed[1] - cfg.speed[0]) * torch.rand((), generator=g, dtype=torch.float64)
    v_lin = speed * direction
    omega = cfg.max_spin * (2 * torch.rand(3, generator=g, dtype=torch.float64) - 1)
    v = v_lin + torch.cross(omega.expand_as(x), x - x.mean(dim=0), dim=1)
    return v, v_lin, omega


def sample_body(cfg: PriorDataConfig, solver: MPMSolver, seed: int):
    """Draw one body: (x0 [N,3], v0 [N,3], vol [N]) in float64 on the CPU, plus its description."""
    g = torch.Generator().manual_seed(int(seed))
    spacing = solver.cfg.dx / cfg.particles_per_cell
    kind = cfg.shapes[int(torch.randint(len(cfg.shapes), (1,), generator=g))]
    half = shape_half_extents(kind, cfg.particles_per_axis * spacing, g)
    rotation = random_rotations(1, g, math.pi, torch.float64)[0]
    x = lattice_body(kind, half, rotation, spacing)
    if x.shape[0] < 8:
        raise ValueError(f"{_WHERE}: a {kind} of half-extents {half.tolist()} m holds only {x.shape[0]} lattice "
                         f"points at spacing {spacing:g} m; raise particles_per_axis")
    x = place_on_floor(x, cfg, solver, g)
    v, v_lin, omega = launch_velocity(x, cfg, g)
    vol = torch.full((x.shape[0],), spacing ** 3, dtype=torch.float64)
    info = {"shape": kind, "seed": int(seed), "n_particles": int(x.shape[0]),
            "v_lin": v_lin.tolist(), "omega": omega.tolist()}
    return x, v, vol, info


@torch.no_grad()
def simulate_trajectory(solver: MPMSolver, material: Material, x0, v0, vol, n_steps: int, info: dict) -> Trajectory:
    """Simulate ``material`` from rest deformation and store every step's state.

    Args:
        solver: MPM solver (dtype and device of the stored tensors).
        material: analytic material (stress, project, rho, wave_speed).
        x0: positions [N, 3] (m); v0: velocities [N, 3] (m/s); vol: volumes [N] (m^3).
        n_steps: steps to simulate.
        info: description stored with the trajectory.

    Raises:
        CFLError: dt too large for the material and the launch speeds.
        SimulationDiverged: the ground truth itself blew up (message names the step and the law).
    """
    dtype, device = solver.dtype, solver.device
    x, v, vol = (t.to(dtype=dtype, device=device) for t in (x0, v0, vol))
    mass = vol * material.rho.to(dtype=dtype, device=device)
    check_cfl(solver.cfg.dt, solver.cfg.dx, material.wave_speed(), float(v.norm(dim=1).max()), solver.cfg.cfl)
    C = torch.zeros(x.shape[0], 3, 3, dtype=dtype, device=device)
    F = torch.eye(3, dtype=dtype, device=device).repeat(x.shape[0], 1, 1)
    states = [(x, v, C, F)]
    for step in range(1, n_steps + 1):
        x, v, C, F = simulate_frame(solver, material, 1, x, v, C, F, vol, mass)
        check_state(solver, x, v, F, step, law_name(material))
        states.append((x, v, C, F))
    xs, vs, Cs, Fs = (torch.stack(s) for s in zip(*states))
    return Trajectory(xs, vs, Cs, Fs, vol, mass, dict(info))


def make_trajectories(solver: MPMSolver, material: Material, cfg: PriorDataConfig, seeds: Sequence[int],
                      progress=None) -> list[Trajectory]:
    """One simulated :class:`Trajectory` per seed (``progress``: optional callable run after each)."""
    material = material.to(dtype=solver.dtype, device=solver.device)
    trajectories = []
    for seed in seeds:
        x0, v0, vol, info = sample_body(cfg, solver, seed)
        trajectories.append(simulate_trajectory(solver, material, x0, v0, vol, cfg.n_steps, info))
        if progress is not None:
            progress()
    return trajectories
