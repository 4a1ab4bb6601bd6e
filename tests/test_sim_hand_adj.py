"""P2G's and G2P's adjoints written out (``gca.sim.kernels.p2g_adj``, ``g2p4_adj``; ``MPMSolver.hand_p2g_adj``,
``hand_g2p_adj``) against warp's generated adjoints of ``p2g`` and ``g2p4``: the same gradients to rounding on kept
grids (the walls' clamp reached), stacked runs and the training path (the reverse sweep over graphed frames' eager
twin), a float64 gradient check, negative controls, the switches' defaults; and on a GPU at the duck's density
(``-m gpu``)."""

import pytest
import torch

from gca.sim.solver import MPMSolver, SimConfig
from tests.test_sim_agg_p2g import _lattice_ball, _state
from tests.test_sim_vec4_p2g import _recorded_launches

TOL = {torch.float64: 1e-12, torch.float32: 2e-5}  # relative to each gradient's largest entry


def _cfg(dtype, n_grid=16):
    return SimConfig(n_grid=n_grid, dt=1e-3, bound=2, boundary="friction", friction=0.5, dtype=str(dtype)[6:],
                     max_refine=1)


def _grads(solver, state, cots, skip=None):
    """(the step's outputs, the gradients of (x, v, C, F, tau) for the cotangents ``cots``, the launches)."""
    x, v, C, F, tau, vol, mass = state
    inputs = [t.clone().requires_grad_() for t in (x, v, C, F, tau)]
    with _recorded_launches(skip=skip) as calls:
        out = solver.step(*inputs, vol, mass)
        grads = torch.autograd.grad(out, inputs, cots(out))
    return out, grads, calls


def _cots(out):
    g = torch.Generator().manual_seed(7)
    return [torch.randn(o.shape, generator=g, dtype=o.dtype) for o in out]


def _close(a, b, dtype):
    assert float(b.abs().max()) > 0
    assert float((a - b).abs().max()) <= TOL[dtype] * float(b.abs().max())


# switch -> (its kernel, warp's adjoint it replaces, the other switches it needs on in both arms)
SWITCHES = {"hand_p2g_adj": ("p2g_adj", "p2g", {}), "hand_g2p_adj": ("g2p4_adj", "g2p4", {"vec4_g2p_adj": True})}


def _solver(dtype, switch, on, runs=1, run=None):
    solver = MPMSolver(_cfg(dtype))
    if runs > 1:
        solver = solver.with_runs(run, runs)
    solver.keep_grid = True
    for name, value in SWITCHES[switch][2].items():
        setattr(solver, name, value)
    setattr(solver, switch, on)
    return solver


@pytest.mark.parametrize("switch", list(SWITCHES))
@pytest.mark.parametrize("runs", [1, 2], ids=["one_run", "two_runs"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_written_out_adjoint_gives_warps_gradients(dtype, runs, switch):
    # on a kept grid (training's backward), with the friction walls and the position clamp reached (particles from
    # 0.02 to 0.98 of a box whose clamp is at 0.125 / 0.875) and, for two runs, the stacked grids' offsets: every
    # input's gradient to rounding, the written-out kernel launched instead of warp's adjoint, the forward untouched
    kernel, replaced, _ = SWITCHES[switch]
    state = _state(300, seed=41, lo=0.02, hi=0.98, dtype=dtype)
    run = (torch.arange(300) % runs).to(torch.int32)
    results = {}
    for hand in (True, False):
        solver = _solver(dtype, switch, hand, runs, run)
        out, grads, calls = _grads(solver, state, _cots)
        adjoints = {name for name, adjoint in calls if adjoint}
        assert ((kernel, False) in calls and replaced not in adjoints) if hand else \
            (replaced in adjoints and (kernel, False) not in calls)
        results[hand] = (out, grads)
    for a, b in zip(results[True][0], results[False][0]):
        assert torch.equal(a, b)
    for a, b in zip(results[True][1], results[False][1]):
        _close(a, b, dtype)
    if switch == "hand_g2p_adj":
        assert not solver._scratch_grid("g2p_adj", runs).numpy().any()  # the accumulator left zero (unpacked)


@pytest.mark.parametrize("switch, only", [("hand_p2g_adj", (1, 2, 4)), ("hand_g2p_adj", (3,))])
def test_without_the_written_out_adjoint_the_gradients_change(switch, only):
    # the negative control: the kernel not launched -> the gradients only it reaches are zero (P2G's: v, C, tau;
    # G2P's: F) and x's differs: the comparison above sees the kernel's work
    dtype = torch.float64
    state = _state(200, seed=42, lo=0.05, hi=0.95, dtype=dtype)
    _, full, _ = _grads(_solver(dtype, switch, True), state, _cots)
    _, broken, _ = _grads(_solver(dtype, switch, True), state, _cots, skip=SWITCHES[switch][0])
    assert all(float(broken[i].abs().max()) == 0 and float(full[i].abs().max()) > 0 for i in only)
    assert float((broken[0] - full[0]).abs().max()) > 1e-6 * float(full[0].abs().max())


@pytest.mark.grad
def test_the_step_with_the_written_out_adjoint_passes_a_float64_gradcheck():
    cfg = SimConfig(n_grid=8, dt=1e-3, bound=1, boundary="friction", friction=0.3, dtype="float64", max_refine=1)
    x, v, C, F, tau, vol, mass = _state(24, seed=43, lo=0.3, hi=0.7)
    solver = MPMSolver(cfg)
    solver.keep_grid = solver.hand_p2g_adj = solver.hand_g2p_adj = solver.vec4_g2p_adj = True

    def f(x, v, C, F, tau):
        return solver.step(x, v, C, F, tau, vol, mass)

    ins = [t.clone().requires_grad_() for t in (x, v, C, F, 1e-2 * tau)]
    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_the_training_path_with_the_written_out_adjoints_matches_warps():
    # the reverse sweep over frames with the grid stash (training's path, graphed frames' eager twin), both switches
    # (and the accumulator G2P's needs) against warp's adjoints: the trajectory bitwise, the gradients of v0 and the
    # law's parameters to rounding, both kernels launched by the sweep
    from test_sim_graph import _law, _scene
    from test_sim_stash import _solver as _stash_solver, _swept

    material, scene = _law(), _scene()
    results = {}
    for hand in (True, False):
        solver = _stash_solver()
        solver.hand_p2g_adj = solver.hand_g2p_adj = hand
        solver.vec4_g2p_adj = True
        with _recorded_launches() as calls:
            results[hand] = _swept(solver, material, scene)
        assert (("p2g_adj", False) in calls) == hand and (("g2p4_adj", False) in calls) == hand
    (x1, g1, _), (x0, g0, _) = results[True], results[False]
    assert torch.equal(x1, x0)
    for a, b in zip(g1, g0):
        _close(a, b, torch.float64)


def test_the_hand_switches_default_to_cuda_and_follow_refinement():
    import types

    solver = MPMSolver(_cfg(torch.float32))
    assert solver.hand_p2g_adj is None and solver.hand_g2p_adj is None  # on CUDA since session 52's measurement
    assert not solver.hands_p2g_adj and not solver.hands_g2p_adj  # None: CUDA only; this solver runs on the CPU
    cuda = MPMSolver(_cfg(torch.float32))
    cuda.device, cuda.wp_device = torch.device("cuda", 0), types.SimpleNamespace(arch=90)  # a device faked
    assert cuda.hands_p2g_adj and cuda.hands_g2p_adj  # with vec4_g2p_adj's default there
    cuda.vec4_g2p_adj = False
    assert not cuda.hands_g2p_adj and cuda.hands_p2g_adj
    solver.hand_p2g_adj = solver.hand_g2p_adj = True
    assert solver.hands_p2g_adj and not solver.hands_g2p_adj  # G2P's needs the accumulator (vec4_g2p_adj: CUDA)
    solver.vec4_g2p_adj = True
    assert solver.hands_g2p_adj
    solver.agg_g2p = True
    assert not solver.hands_g2p_adj  # agg_g2p takes precedence, as over vec4_g2p_adj
    fine = solver.refined(2)
    assert fine.hand_p2g_adj is True and fine.hand_g2p_adj is True


@pytest.mark.gpu
@pytest.mark.parametrize("vec4", [False, True], ids=["scalar", "vector_switches"])
def test_the_written_out_adjoint_matches_warps_on_cuda(vec4):
    # float32 on the GPU at the duck's density (~38 particles a cell), with and without the vector switches
    cfg = SimConfig(n_grid=32, dt=2e-4, bound=2, boundary="friction", friction=0.3, dtype="float32", max_refine=1)
    x = _lattice_ball(3.76, 32, 30000, torch.float32, "cuda")
    _, v, C, F, tau, vol, mass = _state(x.shape[0], seed=44, dtype=torch.float32, device="cuda")
    state = (x, 0.1 * v, 0.1 * C, F, tau, vol, mass)
    results = []
    for hand in (False, True):
        solver = MPMSolver(cfg, "cuda")
        solver.keep_grid, solver.hand_p2g_adj, solver.hand_g2p_adj = True, hand, hand and vec4
        solver.vec4_step = solver.vec4_g2p_adj = vec4
        _, grads, _ = _grads(solver, state, lambda out: [torch.ones_like(o) for o in out])
        results.append(grads)
    for a, b in zip(results[1], results[0]):
        assert torch.isfinite(a).all()
        assert float((a - b).abs().max()) <= 1e-4 * float(b.abs().max())
