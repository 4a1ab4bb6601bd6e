"""gca.sim's grid stash (``MPMSolver.stash_mib``): a rollout's forward pass keeps each step's P2G grid, and the
frames' recomputes take it instead of running P2G again. On the CPU P2G sums in one order, so the recompute's grid
is the forward's bit for bit: the stash must give exactly the gradients of the recompute, through the reverse sweep
(training's path) and through the graphed frames' autograd (the term shares' path), with batched runs too. A
perturbed stash must change them (it is read), and what cannot stash (analytic laws' fused frames, the reference
path, a rollout over the budget) must not."""

import warnings

import pytest
import torch
import warp as wp

from gca.laws.base import CompositeMaterial, Material
from gca.laws.elastic import CorotatedElasticity
from gca.laws.plastic import IdentityPlasticity
from gca.sim import MPMSolver, SimConfig, rollout
from gca.sim.frame import stashable
from gca.sim.graph import FrameGraphs
from test_sim_graph import _law, _scene

wp.config.quiet = True
F64 = torch.float64


def _solver(dtype="float64", stash_mib=1536.0):
    solver = MPMSolver(SimConfig(n_grid=12, dt=1e-3, bound=1, boundary="friction", friction=0.3, dtype=dtype,
                                 max_refine=1))
    solver.stash_mib = stash_mib
    return solver


def _swept(solver, material, scene, n_steps=8, per_frame=2, perturb=None):
    """(trajectory x, gradients of v0 and the material's trainable parameters) of a per-frame loss through the
    reverse sweep, and the sweep's stash list as made (None: no stash). ``perturb``: scales frame 1's stash."""
    x0, v0, vol, mass = scene
    v0 = v0.clone().requires_grad_(True)
    out = rollout(solver, material, x0, v0, vol, mass, n_steps, per_frame, sweep=True)
    stash = None if out.sweep.grids is None else list(out.sweep.grids)
    if perturb is not None:
        out.sweep.grids[1][0].mul_(perturb)  # frame 1 -> 2's momenta
    params = [p for p in material.parameters() if p.requires_grad]
    for p in params:
        p.grad = None
    for f in range(out.x.shape[0] - 1, 0, -1):
        x, F = (t[f].detach().requires_grad_() for t in (out.x, out.F))
        w = torch.linspace(0.5, 1.5, x.shape[0], dtype=x.dtype, device=x.device)[:, None]
        loss = (w * x).square().sum() * f + (F ** 2).sum()
        out.sweep.add(f, *torch.autograd.grad(loss, [x, F]))
    out.sweep.finish()
    return out.x, [v0.grad, *(p.grad.clone() for p in params)], stash


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_swept_stash_gives_the_recomputes_gradients_bitwise(dtype):
    material = _law(dtype=F64 if dtype == "float64" else torch.float32)
    scene = _scene(dtype=F64 if dtype == "float64" else torch.float32)
    x_ref, g_ref, none = _swept(_solver(dtype, stash_mib=0.0), material, scene)
    x, g, stash = _swept(_solver(dtype), material, scene)
    assert none is None and stash is not None and len(stash) == 4  # one stash per frame, each [2 steps, ...]
    assert all(t.shape[0] == 2 for s in stash for t in s) and float(stash[0][1].sum()) > 0  # the masses scattered
    assert torch.equal(x, x_ref)
    assert all(float(t.abs().max()) > 0 for t in g_ref)
    for a, b in zip(g, g_ref):
        assert torch.equal(a, b)
    # negative control: the replay reads the stash (a perturbed one moves every gradient that passes frame 1)
    _, g_bad, _ = _swept(_solver(dtype), material, scene, perturb=1.01)
    assert not torch.allclose(g_bad[0], g_ref[0], rtol=1e-6)


def test_the_graphed_frames_stash_gives_the_recomputes_gradients_bitwise(monkeypatch):
    # the non-swept path (term shares, evaluation with gradients): autograd through graphed frames, twice (retained)
    material, scene = _law(), _scene()
    replays = []
    backward = FrameGraphs.backward
    monkeypatch.setattr(FrameGraphs, "backward", lambda self, s, c, grids=None: (
        replays.append(grids is not None), backward(self, s, c, grids))[1])

    def grads(solver):
        x0, v0, vol, mass = scene
        v0 = v0.clone().requires_grad_(True)
        out = rollout(solver, material, x0, v0, vol, mass, 8, 2, graph=True)
        loss = (out.x[-1] ** 2).sum() + (out.F[2] ** 2).sum() + 0.1 * out.F_trial[3].sum()
        params = [v0, *(p for p in material.parameters() if p.requires_grad)]
        first = torch.autograd.grad(loss, params, retain_graph=True)
        return first, torch.autograd.grad(2 * loss, params)

    (g_ref, _), (g, g2) = grads(_solver(stash_mib=0.0)), grads(_solver())
    assert replays == [False] * 8 + [True] * 8  # 4 frames, 2 backward passes each: recomputed, then replayed
    for a, b, c in zip(g, g_ref, g2):
        assert torch.equal(a, b) and torch.equal(c, 2 * b)  # a second backward replays the same stash


def test_batched_runs_stash_their_stacked_grids():
    material = _law()
    x0, v0, vol, mass = _scene(n=30)
    scene = (torch.cat([x0, x0]), torch.cat([v0, -v0]), torch.cat([vol, vol]), torch.cat([mass, mass]))
    run = torch.repeat_interleave(torch.arange(2, dtype=torch.int32), 30)
    composite = CompositeMaterial([material, _law(seed=1)], [30, 30])
    ref_solver, solver = _solver(stash_mib=0.0).with_runs(run, 2), _solver().with_runs(run, 2)
    x_ref, g_ref, _ = _swept(ref_solver, composite, scene)
    x, g, stash = _swept(solver, composite, scene)
    assert stash is not None and stash[0][0].shape[1] == 2 * solver.stash_shapes(1)[0][0]  # two stacked grids
    assert torch.equal(x, x_ref)
    for a, b in zip(g, g_ref):
        assert torch.equal(a, b)


def test_a_refined_rollout_stashes_its_substeps():
    # CFL refinement (dt 50 ms: 3 sub-steps per step here): the refined solver's frames stash their sub-steps, bitwise
    material, scene = _law(), _scene()

    def refined(stash_mib):
        solver = MPMSolver(SimConfig(n_grid=12, dt=5e-2, bound=1, boundary="friction", friction=0.3,
                                     dtype="float64", max_refine=4))
        solver.stash_mib = stash_mib
        return solver

    x_ref, g_ref, _ = _swept(refined(0.0), material, scene, n_steps=4)
    x, g, stash = _swept(refined(1536.0), material, scene, n_steps=4)
    assert stash is not None and stash[0][0].shape[0] > 2  # a frame of 2 steps stashed more sub-steps
    assert torch.equal(x, x_ref)
    for a, b in zip(g, g_ref):
        assert torch.equal(a, b)
    _, g_bad, _ = _swept(refined(1536.0), material, scene, n_steps=4, perturb=1.01)
    assert not torch.allclose(g_bad[0], g_ref[0], rtol=1e-6)


def test_toggling_the_stash_between_rollouts_takes_a_fitting_runner():
    # stash_mib 1536 -> 0 -> 1536 on one solver: each rollout's runner stashes as the solver says, same gradients
    material, scene = _law(), _scene()
    solver = _solver()
    results = []
    for mib in (1536.0, 0.0, 1536.0):
        solver.stash_mib = mib
        x, g, stash = _swept(solver, material, scene)
        assert (stash is not None) == (mib > 0)
        assert solver.frame_graphs(material, 2, scene[0].shape[0]).stashes == (mib > 0)
        results.append(g)
    for a, b, c in zip(*results):
        assert torch.equal(a, b) and torch.equal(a, c)


def test_an_abandoned_sweep_drops_its_stash():
    material, (x0, v0, vol, mass) = _law(), _scene()
    out = rollout(_solver(), material, x0, v0, vol, mass, 8, 2, sweep=True)
    assert out.sweep.grids is not None
    x, F = (t[4].detach().requires_grad_() for t in (out.x, out.F))
    out.sweep.add(4, *torch.autograd.grad((x ** 2).sum() + F.sum(), [x, F]))
    out.sweep.add(2, None, None)  # frames 4 and 3 swept: their stashes dropped as they went
    assert out.sweep.grids[3] is None and out.sweep.grids[2] is None and out.sweep.grids[1] is not None
    out.sweep.abandon()
    assert out.sweep.grids is None


def test_what_cannot_stash_does_not():
    solver = _solver()
    analytic = Material(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    assert not stashable(solver, analytic)  # its forward fuses the law into P2G: no grid to keep
    hybrid = Material(CorotatedElasticity(3e4, 0.3), _law().plasticity, 1e3).double()
    assert not stashable(solver, hybrid)  # an analytic elasticity under a neural plastic law still fuses its forward
    x0, v0, vol, mass = _scene()
    out = rollout(solver, analytic, x0, v0, vol, mass, 8, 2, sweep=True)
    assert out.sweep.grids is None
    out.sweep.abandon()
    material = _law()
    assert stashable(solver, material)
    solver.keep_grid = False  # the reference backward recomputes P2G under a tape
    assert not stashable(solver, material)
    solver.keep_grid = True
    runner = solver.frame_graphs(material, 2, x0.shape[0])
    solver.stash_mib = 3.9 * runner.stash_bytes / 2 ** 20  # 4 frames do not fit: the rollout recomputes them all
    out = rollout(solver, material, x0, v0, vol, mass, 8, 2, sweep=True)
    assert out.sweep.grids is None
    out.sweep.abandon()
    solver.stash_mib = 4.0 * runner.stash_bytes / 2 ** 20  # they fit
    out = rollout(solver, material, x0, v0, vol, mass, 8, 2, sweep=True)
    assert out.sweep.grids is not None
    out.sweep.abandon()


def test_an_analytic_law_off_the_fused_path_stashes_like_a_neural_one():
    # fuse_analytic off: the analytic law's forward takes the generic step, so it stashes, bitwise as before
    analytic = Material(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    results = []
    for mib in (0.0, 1536.0):
        solver = _solver(stash_mib=mib)
        solver.fuse_analytic = False
        assert stashable(solver, analytic) == (mib > 0)
        results.append(_swept(solver, analytic, _scene()))
    (x_ref, g_ref, _), (x, g, stash) = results
    assert stash is not None and torch.equal(x, x_ref)
    assert float(g_ref[1].abs()) > 0  # log E's gradient
    for a, b in zip(g, g_ref):
        assert torch.equal(a, b)


def test_a_bad_stash_is_refused_in_one_line():
    solver = _solver()
    x0, v0, vol, mass = _scene(n=5)
    C = torch.zeros(5, 3, 3, dtype=F64)
    F = torch.eye(3, dtype=F64).expand(5, 3, 3).contiguous()
    mv_shape, m_shape = solver.stash_shapes()
    with pytest.raises(ValueError, match="grid stash's m must be"):
        solver.step(x0, v0, C, F, C, vol, mass, grid=(torch.zeros(mv_shape, dtype=F64), torch.zeros(3, dtype=F64)))
    solver.keep_grid = False
    with pytest.raises(ValueError, match="needs keep_grid"):
        solver.step(x0, v0.requires_grad_(), C, F, C, vol, mass,
                    grid=(torch.zeros(mv_shape, dtype=F64), torch.zeros(m_shape, dtype=F64)))


@pytest.mark.gpu
def test_the_stash_on_cuda_graphs_equals_the_recompute():
    # on CUDA the stash is the forward's grid and a recompute's atomics sum in another order: equal to rounding
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    material = _law().cuda()
    scene = tuple(t.cuda() for t in _scene(n=400))

    def cuda_solver(stash_mib):
        solver = MPMSolver(SimConfig(n_grid=12, dt=1e-3, bound=1, boundary="friction", friction=0.3,
                                     dtype="float64", max_refine=1), "cuda")
        solver.stash_mib = stash_mib
        return solver

    x_ref, g_ref, _ = _swept(cuda_solver(0.0), material, scene)
    solver = cuda_solver(1536.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # a failed capture falls back to eager with a warning
        x, g, stash = _swept(solver, material, scene)
    runner = solver.frame_graphs(material, 2, 400)
    assert stash is not None and runner.capture and runner._rep_graph is not None
    torch.testing.assert_close(x, x_ref, rtol=1e-12, atol=1e-12)
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-12 * float(b.abs().max()))
