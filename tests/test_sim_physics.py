"""gca.sim physics with gca.laws materials: elastic wave speed and a bouncing ball."""

import math

import torch
import warp as wp

from gca.laws.base import Material
from gca.laws.elastic import CorotatedElasticity
from gca.laws.plastic import IdentityPlasticity
from gca.sim import MPMSolver, SimConfig, rollout

wp.config.quiet = True
RHO = 1000.0  # density [kg/m^3]


def lattice(lo, hi, h):
    """Cell-centred particle lattice of spacing h [m] filling the box [lo, hi] -> [P, 3] float32."""
    axes = [torch.arange(a + h / 2, b - h / 2 + 1e-9, h, dtype=torch.float64) for a, b in zip(lo, hi)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).float()


def elastic(E, nu):
    return Material(CorotatedElasticity(E, nu), IdentityPlasticity(), RHO)


def test_bar_wave_speed_matches_sqrt_E_over_rho():
    # Free-free bar (length L = 16 cells, 2 x 2 cells section) in its fundamental longitudinal mode:
    # v_x = A cos(pi s / L) at t = 0, so the length L(t) - L(0) ~ -sin(pi c t / L) returns to zero
    # at t = L / c. nu = 0 makes the bar and P-wave speeds both sqrt(E / rho) = 10 m/s.
    n, L, E, A = 32, 0.5, 1e5, 0.1
    dx = 1.0 / n
    h = dx / 2
    x = lattice((0.25, 0.5 - dx, 0.5 - dx), (0.25 + L, 0.5 + dx, 0.5 + dx), h)
    s = x[:, 0] - 0.25
    v = torch.zeros_like(x)
    v[:, 0] = A * torch.cos(math.pi * s / L)
    vol = torch.full((x.shape[0],), h**3)
    cfg = SimConfig(n_grid=n, dt=5e-4, gravity=(0, 0, 0), bound=2, boundary="sticky", friction=0.0, max_refine=1)
    with torch.no_grad():
        out = rollout(MPMSolver(cfg), elastic(E, 0.0), x, v, vol, vol * RHO, n_steps=130, steps_per_frame=1)
    ends = out.x[:, s > L - h, 0].mean(1) - out.x[:, s < h, 0].mean(1)
    dl = (ends - ends[0]).double()
    k_min = int(dl.argmin())
    assert dl[k_min] < -0.2 * 2 * A * L / (math.pi * 10.0)  # the bar did contract (amplitude 2AL/(pi c))
    k = k_min + int(torch.nonzero(dl[k_min:] >= 0)[0])
    t_half = (k - 1 + float(-dl[k - 1] / (dl[k] - dl[k - 1]))) * cfg.dt  # linear interpolation
    c_measured = L / t_half
    assert abs(c_measured / math.sqrt(E / RHO) - 1) < 0.10, c_measured


def test_elastic_ball_bounces_without_energy_gain():
    # A soft ball (E = 1e5 Pa) dropped on a slip floor: KE + PE never exceeds the initial energy
    # (elastic energy >= 0, APIC dissipates), it reaches the floor and comes back up.
    n = 16
    h = 1.0 / n / 2
    centre = torch.tensor([0.5, 0.4, 0.5])
    x = lattice((0.3, 0.2, 0.3), (0.7, 0.6, 0.7), h)
    x = x[(x - centre).norm(dim=1) < 0.15]
    mass = torch.full((x.shape[0],), h**3 * RHO)
    cfg = SimConfig(n_grid=n, dt=1.5e-3, bound=2, boundary="slip", friction=0.0, max_refine=1)
    with torch.no_grad():
        out = rollout(MPMSolver(cfg), elastic(1e5, 0.3), x, torch.zeros_like(x), mass / RHO, mass,
                      n_steps=200, steps_per_frame=2)
    g = 9.8
    energy = (0.5 * mass * out.v.pow(2).sum(-1) + mass * g * out.x[..., 1]).sum(1)
    assert bool(torch.isfinite(energy).all())
    assert energy.max() <= energy[0] * (1 + 1e-3), (energy.max() / energy[0]).item()
    vy = (mass * out.v[..., 1]).sum(1) / mass.sum()
    k_impact = int(vy.argmin())
    assert vy[k_impact] < -1.0  # fell about 0.13 m: ~1.6 m/s at impact
    assert vy[k_impact:].max() > 0.3 * -vy[k_impact]  # it bounced
    assert out.clamped[-1] == 0
