"""Pretraining data of the neural prior: lattice bodies, placement, launch, stored full states."""

import math

import pytest
import torch
import warp as wp

from gca.laws.presets import material_from_preset
from gca.sim import MPMSolver, SimConfig
from gca.train.prior import window_loss
from gca.train.prior_data import (PriorDataConfig, inside_shape, lattice_body, make_trajectories, sample_body,
                                  trajectory_seed)

wp.config.quiet = True
JELLY = {"elasticity": "corotated", "plasticity": "identity", "E": 1.0e5, "nu": 0.2, "rho": 1000}
SIM = SimConfig(n_grid=16, dt=8e-4, bound=2, boundary="friction", friction=0.4, max_refine=1)
DATA = PriorDataConfig(particles_per_axis=6, n_steps=12, speed=(1.5, 3.0), max_tilt_deg=45.0, floor_gap=(0.0, 0.03))


@pytest.fixture(scope="module")
def solver():
    return MPMSolver(SIM)


@pytest.fixture(scope="module")
def trajectory(solver):
    with torch.random.fork_rng(devices=[]):
        return make_trajectories(solver, material_from_preset(JELLY), DATA, [trajectory_seed(0, "train", 0)])[0]


def test_axis_aligned_cube_is_the_full_lattice():
    # A cube of side 6 h, unrotated, holds exactly 6^3 lattice points at (i + 1/2) h.
    h = 0.01
    x = lattice_body("cube", torch.full((3,), 3 * h, dtype=torch.float64), torch.eye(3, dtype=torch.float64), h)
    assert x.shape == (216, 3)
    offsets = x / h - 0.5
    torch.testing.assert_close(offsets, offsets.round(), rtol=0, atol=1e-9)  # on the lattice


@pytest.mark.parametrize("kind,volume", [("sphere", 4 / 3 * math.pi), ("cube", 8.0),
                                         ("capsule", math.pi * 0.25 * (4 / 3 * 0.5 + 1.0))])
def test_lattice_volume_matches_the_shape(kind, volume):
    # half-extents (1, 0.5, 0.5) for the capsule (radius 0.5, segment half-length 0.5), 1 otherwise; h = 1/20.
    half = torch.tensor([1.0, 0.5, 0.5] if kind == "capsule" else [1.0, 1.0, 1.0], dtype=torch.float64)
    R = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64))[0]
    x = lattice_body(kind, half, R, 0.05)
    assert x.shape[0] * 0.05 ** 3 == pytest.approx(volume, rel=0.03)
    assert inside_shape(kind, x @ R, half).all()


def test_body_rests_above_the_floor_and_is_launched_rigidly_downwards(solver):
    wall = (SIM.bound + 0.5) * SIM.dx
    for i in range(6):
        x, v, vol, info = sample_body(DATA, solver, trajectory_seed(1, "train", i))
        assert wall - 1e-12 <= float(x[:, 1].min()) <= wall + DATA.floor_gap[1] + 1e-12
        assert float(x[:, [0, 2]].min()) >= wall and float(x[:, [0, 2]].max()) <= 1 - wall
        v_lin, omega = torch.tensor(info["v_lin"], dtype=torch.float64), torch.tensor(info["omega"], dtype=torch.float64)
        assert DATA.speed[0] <= float(v_lin.norm()) <= DATA.speed[1]
        assert -float(v_lin[1]) >= float(v_lin.norm()) * math.cos(math.radians(DATA.max_tilt_deg)) - 1e-12
        rigid = v_lin + torch.cross(omega.expand_as(x), x - x.mean(0), dim=1)
        torch.testing.assert_close(v, rigid)
        assert float(vol[0]) == pytest.approx((SIM.dx / DATA.particles_per_cell) ** 3)


def test_seeds_reproduce_bodies_and_splits_differ(solver):
    a = sample_body(DATA, solver, trajectory_seed(0, "train", 2))
    b = sample_body(DATA, solver, trajectory_seed(0, "train", 2))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    seeds = {trajectory_seed(s, split, i) for s in range(3) for split in ("train", "heldout") for i in range(100)}
    assert len(seeds) == 600


def test_stored_states_restart_exactly_with_the_same_law(trajectory, solver):
    # Teacher forcing restarts from stored full states: the analytic law itself has zero window loss,
    # a stiffer one (negative control) does not, once the body touches the floor.
    T = trajectory.n_steps
    assert trajectory.x.shape[0] == T + 1 and trajectory.C.shape[1:] == (trajectory.x.shape[1], 3, 3)
    assert torch.equal(trajectory.F[0], torch.eye(3).expand_as(trajectory.F[0]))
    material, stiff = material_from_preset(JELLY), material_from_preset({**JELLY, "E": 3.0e5})
    with torch.no_grad():
        assert float(window_loss(solver, material, trajectory, T - 6, 6)) == 0.0
        assert float(window_loss(solver, stiff, trajectory, T - 6, 6)) > 0.0


def test_bad_data_config_and_oversized_body_are_refused(solver):
    with pytest.raises(ValueError, match="prior_data.py.*shapes"):
        PriorDataConfig(shapes=("torus",), particles_per_axis=12, n_steps=400)
    with pytest.raises(ValueError, match="does not fit the domain"):
        sample_body(PriorDataConfig(particles_per_axis=40, n_steps=400), solver, 0)
