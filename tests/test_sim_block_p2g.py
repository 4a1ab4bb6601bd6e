"""gca.sim.kernels.scatter_block: forward P2G summed per thread block in shared memory before the grid's atomics
(the generic step's ``p2g_block``, the fused step's ``p2g_stress_block`` and ``g2p_p2g_block``), against the
per-particle kernels on the CPU: with warp's CPU blocks on (``wp.config.enable_cpu_blocks``: a block's threads
really cooperate, as on a GPU) and off (a block is one thread), on lattice-ordered particles ~64 per cell (the
paper profile's density: every block's window fits) and on scattered ones (no window fits: the direct scatter),
runs sharing a launch; the grid's mass and momentum conserved (a node left out of the window's flush breaks them)."""

import numpy as np
import pytest
import torch
import warp as wp

from gca.laws.base import Material
from gca.laws.elastic import CorotatedElasticity
from gca.laws.plastic import IdentityPlasticity
from gca.sim.frame import simulate_frame
from gca.sim.kernels import BLOCK, KERNELS, WINDOW, block_dim, grid_size, launch_blocks
from gca.sim.solver import MPMSolver, SimConfig

N_GRID = 16


@pytest.fixture(params=[True, False], ids=["cpu_blocks", "one_thread_blocks"])
def cpu_blocks(request, monkeypatch):
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", request.param)
    assert block_dim("cpu") == (BLOCK if request.param else 1)
    return request.param


def _lattice_ball(radius: float = 0.1, per_cell_axis: int = 4):
    """Particles on a lattice of spacing dx / ``per_cell_axis`` inside a ball, in meshgrid order (as
    ``gca.assets.particles`` samples objects): ~64 per cell for 4."""
    s = 1.0 / N_GRID / per_cell_axis
    a = np.arange(-radius, radius + 1e-9, s)
    X, Y, Z = np.meshgrid(a, a, a, indexing="ij")
    P = np.stack([X, Y, Z], -1).reshape(-1, 3)
    return P[(P ** 2).sum(1) <= radius ** 2] + np.array([0.5, 0.3, 0.45])


def _scattered(n: int, seed: int):
    return np.random.default_rng(seed).uniform(0.1, 0.9, (n, 3))


def _windows_fit(x: np.ndarray, run: np.ndarray, B: int) -> np.ndarray:
    """Whether each block of ``B`` particles has a stencil box of at most WINDOW nodes (runs' grids stacked)."""
    base = np.floor(x * N_GRID - 0.5).astype(int)
    base[:, 0] += run * grid_size(N_GRID)
    fits = []
    for b in range(0, len(x), B):
        e = base[b:b + B].max(0) - base[b:b + B].min(0) + 3
        fits.append(np.prod(e) <= WINDOW)
    return np.array(fits)


def _state(x: np.ndarray, dtype, seed: int = 0):
    """(x, v, C, F, tau, vol, mass) as torch tensors around positions ``x`` [N, 3]."""
    g = torch.Generator().manual_seed(seed)
    n = len(x)
    x = torch.tensor(x, dtype=dtype)
    v = 0.5 * torch.randn(n, 3, generator=g, dtype=dtype)
    C = 2.0 * torch.randn(n, 3, 3, generator=g, dtype=dtype)
    F = torch.eye(3, dtype=dtype) + 0.1 * torch.randn(n, 3, 3, generator=g, dtype=dtype)
    tau = 1e4 * torch.randn(n, 3, 3, generator=g, dtype=dtype)
    vol = (0.5 + torch.rand(n, generator=g, dtype=dtype)) * 1e-6
    return x, v, C, F, tau, vol, 1000.0 * vol


def _p2g(kernel: str, state, run, n_runs: int, dtype):
    """The grid (m [R G, G, G], mv [R G, G, G, 3]) after one P2G by ``kernel`` ("p2g" or "p2g_block")."""
    k = KERNELS["float64" if dtype == torch.float64 else "float32"]
    G = grid_size(N_GRID)
    x, v, C, F, tau, vol, mass = state
    types = (k.vec3, k.vec3, k.mat33, k.mat33, k.T, k.T)
    ins = [wp.from_torch(t.contiguous(), dtype=ty) for t, ty in zip((x, v, C, tau, vol, mass), types)]
    mv = wp.zeros((n_runs * G, G, G), dtype=k.vec3, device="cpu")
    m = wp.zeros((n_runs * G, G, G), dtype=k.T, device="cpu")
    args = [*ins, wp.from_torch(run, dtype=wp.int32), 1e-3, float(N_GRID), N_GRID, mv, m]
    windows = wp.zeros(1, dtype=int, device="cpu")
    if kernel == "p2g":
        wp.launch(k.p2g, dim=x.shape[0], inputs=args, device="cpu")
    else:
        launch_blocks(k.p2g_block, x.shape[0], [*args, windows], "cpu")
    return wp.to_torch(m).clone(), wp.to_torch(mv).clone(), int(windows.numpy()[0])


CASES = {  # name: (positions, run indices, runs)
    "lattice": lambda: (_lattice_ball(), None, 1),
    "scattered": lambda: (_scattered(700, 3), None, 1),
    "two_runs": lambda: (np.concatenate([_lattice_ball(), _lattice_ball(0.07)]), "split", 2),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_the_block_summed_p2g_equals_the_per_particle_kernel(case, dtype, rtol, cpu_blocks):
    x, run, n_runs = CASES[case]()
    n = len(x)
    run = np.zeros(n, int) if run is None else (np.arange(n) >= len(_lattice_ball())).astype(int)
    fits = _windows_fit(x, run, block_dim("cpu"))
    if case == "scattered":  # the premise: these take the direct scatter ...
        assert not fits.any() or not cpu_blocks
    else:  # ... these the window (a block straddling the two runs excepted)
        assert fits.mean() > (0.9 if cpu_blocks else 0.99)
    state = _state(x, dtype)
    run_t = torch.tensor(run, dtype=torch.int32)
    m_ref, mv_ref, _ = _p2g("p2g", state, run_t, n_runs, dtype)
    m, mv, windows = _p2g("p2g_block", state, run_t, n_runs, dtype)
    assert windows == int(fits.sum())  # the blocks whose box fits took the window, the others scattered directly
    for a, b in ((m, m_ref), (mv, mv_ref)):
        assert float((a - b).abs().max()) <= rtol * float(b.abs().max())
    # conservation: the grid holds every particle's mass and momentum (APIC's affine part sums to zero)
    mass, v = state[6], state[1]
    assert float(m.sum()) == pytest.approx(float(mass.sum()), rel=1e3 * rtol)
    assert float((mv.reshape(-1, 3).sum(0) - (mass[:, None] * v).sum(0)).abs().max()) <= \
        1e3 * rtol * float((mass[:, None] * v.abs()).sum())
    if n_runs == 2:  # each run's grid holds its own particles' mass only
        G = grid_size(N_GRID)
        for r in range(2):
            assert float(m[r * G:(r + 1) * G].sum()) == pytest.approx(float(mass[run_t == r].sum()), rel=1e3 * rtol)


def test_a_dropped_window_node_breaks_conservation():
    # negative control of the conservation check above: the reference grid with one occupied node cleared
    x = _lattice_ball()
    state = _state(x, torch.float64)
    m, mv, _ = _p2g("p2g", state, torch.zeros(len(x), dtype=torch.int32), 1, torch.float64)
    m.view(-1)[int(m.view(-1).argmax())] = 0.0
    assert float(m.sum()) != pytest.approx(float(state[6].sum()), rel=1e-9)


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_a_step_with_the_block_summed_p2g_equals_the_generic_step(dtype, rtol, cpu_blocks):
    # the solver's forward P2G takes p2g_block when block_p2g is on; the backward (p2g's adjoint, on the kept grid
    # or a taped recompute) is unchanged, so values and gradients agree to rounding
    cfg = SimConfig(n_grid=N_GRID, dt=1e-3, bound=2, boundary="friction", friction=0.3,
                    dtype=str(dtype)[6:], max_refine=1)
    state = _state(_lattice_ball(), dtype, seed=2)
    g = torch.Generator().manual_seed(5)
    cots = [torch.randn(t.shape, generator=g, dtype=dtype) for t in state[:4]]
    results = {}
    for block in (True, False):
        solver = MPMSolver(cfg)
        solver.block_p2g = block
        assert solver.blocks_p2g == block and solver.refined(2).blocks_p2g == block
        ins = [t.clone().requires_grad_() for t in state[:5]]
        outs = solver.step(*ins, *state[5:])
        results[block] = [o.detach() for o in outs] + list(torch.autograd.grad(outs, ins, cots))
        # every block fits its window here (one-thread blocks: one per particle); off, none is counted
        assert solver.block_windows() == (-(-len(state[0]) // block_dim("cpu")) if block else 0)
    assert float((results[True][0] - state[0]).abs().max()) > 1e-6  # the particles moved
    for a, b in zip(results[True], results[False]):
        assert float((a - b).abs().max()) <= rtol * float(b.abs().max())


def test_block_p2g_is_off_by_default_and_none_means_cuda_only():
    solver = MPMSolver(SimConfig(n_grid=8, dtype="float64"))
    assert solver.block_p2g is False and not solver.blocks_p2g  # measured slower on the H100 (NOTES session 32)
    solver.block_p2g = None
    assert not solver.blocks_p2g  # None: on CUDA only, and this is a CPU
    solver.block_p2g = True
    assert solver.blocks_p2g and solver.refined(3).blocks_p2g


@pytest.mark.parametrize("n_steps", [1, 4])
@pytest.mark.parametrize("frames", [True, False], ids=["one_pass_frame", "fused_steps"])
@pytest.mark.parametrize("case", ["lattice", "scattered"])
def test_a_fused_frame_with_the_block_summed_scatter_equals_the_generic_frame(case, frames, n_steps, cpu_blocks):
    # p2g_stress_block and g2p_p2g_block against the generic step (law, then transfers), float64; walls act
    cfg = SimConfig(n_grid=N_GRID, dt=5e-4, bound=2, boundary="friction", friction=0.3, dtype="float64",
                    max_refine=1)
    x = _lattice_ball() if case == "lattice" else _scattered(500, 4)
    x[:, 1] -= x[:, 1].min() - 1.5 / N_GRID  # the lowest particles inside the floor's wall region
    x, v, C, F, _, vol, mass = _state(x, torch.float64, seed=8)
    material = Material(CorotatedElasticity(1e5, 0.3, learnable=False), IdentityPlasticity(), 1000.0).double()
    results = {}
    for path in ("block", "fused", "generic"):
        solver = MPMSolver(cfg)
        solver.fuse_frames, solver.block_p2g = frames, path == "block"
        solver.fuse_analytic = path != "generic"
        with torch.no_grad():
            results[path] = simulate_frame(solver, material, n_steps, x, v, C, F, vol, mass)
        if path == "block":  # the lattice's blocks took the window at every step, the scattered ones none
            blocks = -(-len(x) // block_dim("cpu"))
            windows = solver.block_windows(reset=True)
            assert (windows == n_steps * blocks) if case == "lattice" else (windows < blocks or not cpu_blocks)
            assert solver.block_windows() == 0
    assert float((results["block"][0] - x).abs().max()) > 1e-6
    for a, b in zip(results["block"], results["generic"]):
        assert torch.isfinite(a).all()
        assert float((a - b).abs().max()) <= 1e-12 * float(b.abs().max())
    if not cpu_blocks:  # a one-thread block adds one particle's shares to the grid: the fused path's sums, bitwise
        for a, b in zip(results["block"], results["fused"]):
            assert torch.equal(a, b)


def test_a_batched_solver_counts_its_own_windows():
    # with_runs shares the parent's switches but not its window count (block_windows reads one solver's launches)
    cfg = SimConfig(n_grid=N_GRID, dt=1e-3, dtype="float64", max_refine=1)
    solver = MPMSolver(cfg)
    solver.block_p2g = True
    x = np.concatenate([_lattice_ball(), _lattice_ball(0.07)])
    state = _state(x, torch.float64)
    run = torch.tensor((np.arange(len(x)) >= len(_lattice_ball())).astype(np.int32))
    batched = solver.with_runs(run, 2)
    assert batched.blocks_p2g
    with torch.no_grad():
        batched.step(*state)
    assert batched.block_windows() > 0 and solver.block_windows() == 0
