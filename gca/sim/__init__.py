"""gca.sim: differentiable MLS-MPM on the unit cube (warp kernels, torch bridge, rollout driver).

Public API::

    SimConfig, MPMSolver(cfg, device).step(x, v, C, F, tau, vol, mass) -> (x, v, C, F_trial)
    rollout(solver, material, x0, v0, vol, mass, n_steps, steps_per_frame, checkpoint=True) -> Rollout
    check_cfl(dt, dx, wave_speed, max_velocity=0, cfl=0.5), CFLError, SimulationDiverged
"""

from gca.sim.cfl import CFLError, check_cfl, max_stable_dt
from gca.sim.rollout import Rollout, SimulationDiverged, rollout
from gca.sim.solver import MPMSolver, SimConfig

__all__ = ["SimConfig", "MPMSolver", "rollout", "Rollout", "SimulationDiverged", "check_cfl",
           "max_stable_dt", "CFLError"]
