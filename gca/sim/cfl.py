"""CFL time-step check for explicit MPM."""

from __future__ import annotations

import math


class CFLError(ValueError):
    """The time step is too large for the material's wave speed and the particle speeds."""


def max_stable_dt(dx: float, wave_speed: float, max_velocity: float = 0.0, cfl: float = 0.5) -> float:
    """Largest admissible step ``cfl * dx / (c + |v|max)`` [s].

    Args:
        dx: cell size [m].
        wave_speed: fastest elastic wave speed c of the material [m/s] (e.g. sqrt((lam + 2 mu) / rho)).
        max_velocity: largest particle speed |v|max [m/s].
        cfl: Courant number in (0, 1].
    """
    if not (dx > 0 and wave_speed >= 0 and max_velocity >= 0 and 0 < cfl <= 1):
        raise ValueError(f"gca/sim/cfl.py: need dx > 0, c >= 0, |v|max >= 0, 0 < cfl <= 1; got "
                         f"dx={dx}, c={wave_speed}, |v|max={max_velocity}, cfl={cfl}")
    speed = wave_speed + max_velocity
    return math.inf if speed == 0 else cfl * dx / speed


def check_cfl(dt: float, dx: float, wave_speed: float, max_velocity: float = 0.0, cfl: float = 0.5) -> float:
    """Refuse ``dt > cfl * dx / (c + |v|max)``.

    Args:
        dt: time step [s].
        dx: cell size [m].
        wave_speed: material wave speed c [m/s].
        max_velocity: largest particle speed [m/s].
        cfl: Courant number in (0, 1].

    Returns:
        The admissible bound [s] (for logging).

    Raises:
        CFLError: naming dt, the bound and the quantities it came from.
    """
    if not math.isfinite(wave_speed) or not math.isfinite(max_velocity):
        raise CFLError(f"gca/sim/cfl.py: non-finite wave speed {wave_speed} or max velocity {max_velocity}")
    bound = max_stable_dt(dx, wave_speed, max_velocity, cfl)
    if dt > bound:
        raise CFLError(
            f"gca/sim/cfl.py: dt={dt:.3g} s exceeds the CFL bound {bound:.3g} s = cfl {cfl} * dx {dx:.4g} m "
            f"/ (wave speed {wave_speed:.4g} m/s + |v|max {max_velocity:.4g} m/s); lower sim.dt to "
            f"<= {bound:.3g} s (more steps per frame) or use a coarser grid")
    return bound


def refinement(cfg, wave_speed: float, max_velocity: float) -> int:
    """Smallest k <= ``cfg.max_refine`` with ``dt / k`` inside the CFL bound (1 when dt already is).

    A learned law can stiffen during training past the bound the scene's dt was chosen for; with
    ``max_refine > 1`` the rollout then takes k smaller steps per step (same frames, same physics,
    more accurate time integration) instead of refusing.

    Raises:
        CFLError: even ``dt / max_refine`` exceeds the bound (or the speeds are non-finite).
    """
    if not (math.isfinite(wave_speed) and math.isfinite(max_velocity)):
        check_cfl(cfg.dt, cfg.dx, wave_speed, max_velocity, cfg.cfl)  # raises, naming the values
    bound = max_stable_dt(cfg.dx, wave_speed, max_velocity, cfg.cfl)
    k = max(1, math.ceil(cfg.dt / bound * (1 - 1e-12)))
    if k > cfg.max_refine:
        raise CFLError(f"gca/sim/cfl.py: dt={cfg.dt:.3g} s exceeds the CFL bound {bound:.3g} s = cfl {cfg.cfl} * dx "
                       f"{cfg.dx:.4g} m / (wave speed {wave_speed:.4g} m/s + |v|max {max_velocity:.4g} m/s) by "
                       f"more than sim.max_refine={cfg.max_refine} sub-steps allow (needs {k}): lower sim.dt, "
                       f"raise sim.max_refine or use a coarser grid")
    return k
