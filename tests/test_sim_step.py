"""gca.sim step: float64 gradchecks, warp vs torch reference, conservation, free fall, grid safety."""

import pytest
import torch
import warp as wp

from gca.sim import MPMSolver, SimConfig
from gca.sim.reference import step_ref

wp.config.quiet = True
F64 = torch.float64


def _state(n, seed, lo=0.35, hi=0.65, dtype=F64, tau_scale=1e3):
    """Random particles in [lo, hi]^3 with random v, C, F near I and tau."""
    g = torch.Generator().manual_seed(seed)
    x = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=dtype)
    v = torch.randn(n, 3, generator=g, dtype=dtype)
    C = torch.randn(n, 3, 3, generator=g, dtype=dtype)
    F = torch.eye(3, dtype=dtype) + 0.1 * torch.randn(n, 3, 3, generator=g, dtype=dtype)
    tau = tau_scale * torch.randn(n, 3, 3, generator=g, dtype=dtype)
    vol = torch.full((n,), 1e-4, dtype=dtype)
    mass = 0.1 + torch.rand(n, generator=g, dtype=dtype) * 0.1
    return x, v, C, F, tau, vol, mass


def _multi_step(solver, n_steps):
    """x, v, C, F, tau -> state after n_steps (tau reused every step), as a gradcheck function."""
    def fn(x, v, C, F, tau, vol, mass):
        for _ in range(n_steps):
            x, v, C, F = solver.step(x, v, C, F, tau, vol, mass)
        return x, v, C, F
    return fn


def _floor_state(n, seed):
    """Particles just above the floor moving down, so the wall condition is active."""
    x, v, C, F, tau, vol, mass = _state(n, seed, lo=0.3, hi=0.6)
    x[:, 1] = 0.2 + 0.05 * torch.rand(n, generator=torch.Generator().manual_seed(seed + 1), dtype=F64)
    v[:, 1] = -v[:, 1].abs() - 1.0
    return x, v, C, F, tau, vol, mass


@pytest.mark.grad
@pytest.mark.parametrize("boundary", ["sticky", "slip", "friction"])
def test_step_gradcheck_float64(boundary):
    # 8^3 grid, 3 particles near the floor (bound = 2 cells reaches them), 2 steps.
    cfg = SimConfig(n_grid=8, dt=2e-3, bound=2, boundary=boundary, friction=0.3, dtype="float64", max_refine=1)
    fn = _multi_step(MPMSolver(cfg), 2)
    x, v, C, F, tau, vol, mass = _floor_state(3, seed=1)
    inputs = [t.requires_grad_() for t in (x, v, C, F, tau)]
    assert torch.autograd.gradcheck(lambda *a: fn(*a, vol, mass), inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


class _WrongBackward(torch.autograd.Function):
    """The solver step with a deliberately wrong backward: dL/dx scaled by 1.01."""

    @staticmethod
    def forward(ctx, x, v, C, F, tau, solver, vol, mass):
        ctx.solver, ctx.consts = solver, (vol, mass)
        ctx.save_for_backward(x, v, C, F, tau)
        return solver.step(x, v, C, F, tau, vol, mass)

    @staticmethod
    def backward(ctx, *v_outs):
        inputs = [t.detach().requires_grad_() for t in ctx.saved_tensors]
        with torch.enable_grad():
            outs = ctx.solver.step(*inputs, *ctx.consts)
        grads = list(torch.autograd.grad(outs, inputs, v_outs))
        grads[0] = grads[0] * 1.01
        return (*grads, None, None, None)


@pytest.mark.grad
def test_gradcheck_catches_wrong_backward():
    # Negative control: the same check and tolerances must reject a 1 % error in dL/dx.
    cfg = SimConfig(n_grid=8, dt=2e-3, bound=2, boundary="slip", dtype="float64", friction=0.0, max_refine=1)
    solver = MPMSolver(cfg)
    x, v, C, F, tau, vol, mass = _floor_state(3, seed=1)
    inputs = [t.requires_grad_() for t in (x, v, C, F, tau)]
    right = torch.autograd.gradcheck(lambda *a: solver.step(*a, vol, mass), inputs, eps=1e-6, atol=1e-7,
                                     rtol=1e-5)
    wrong = torch.autograd.gradcheck(lambda *a: _WrongBackward.apply(*a, solver, vol, mass), inputs, eps=1e-6,
                                     atol=1e-7, rtol=1e-5, raise_exception=False)
    assert right and not wrong


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 2e-4), (torch.float64, 1e-11)])
@pytest.mark.parametrize("boundary", ["sticky", "slip", "friction"])
def test_step_matches_torch_reference(boundary, dtype, tol):
    # Values and VJPs of the warp step against the dense torch reference, with walls active
    # (particles fill the whole box, some within the 2-cell walls). float32 tolerance: summation
    # order of the atomic scatter vs index_add (relative to each quantity's scale).
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=2, boundary=boundary, friction=0.5, dtype=str(dtype)[6:], max_refine=1)
    x, v, C, F, tau, vol, mass = _state(200, seed=2, lo=0.02, hi=0.98, dtype=dtype)
    inputs = [t.requires_grad_() for t in (x, v, C, F, tau)]
    outs = MPMSolver(cfg).step(*inputs, vol, mass)
    refs = step_ref(cfg, *inputs, vol, mass)
    cots = [torch.randn_like(o) for o in outs]
    grads = torch.autograd.grad(outs, inputs, cots)
    grads_ref = torch.autograd.grad(refs, inputs, cots)
    for name, a, b in zip(["x", "v", "C", "F", "dx", "dv", "dC", "dF", "dtau"], outs + grads, refs + grads_ref):
        assert (a - b).abs().max() <= tol * b.abs().max(), name


def test_p2g_g2p_conserve_mass_and_momentum():
    # Gravity and walls off: P2G conserves mass, P2G -> G2P conserves linear momentum exactly
    # (partition of unity and sum_i w_ip (x_i - x_p) = 0 of quadratic B-splines), whatever tau and C.
    cfg = SimConfig(n_grid=16, dt=1e-3, gravity=(0, 0, 0), bound=0, dtype="float64", boundary="sticky", friction=0.0,
                    max_refine=1)
    solver = MPMSolver(cfg)
    x, v, C, F, tau, vol, mass = _state(100, seed=3, lo=0.2, hi=0.8, tau_scale=1e5)
    m_grid, mv_grid = solver.grid(x, v, C, tau, vol, mass)
    p0 = (mass[:, None] * v).sum(0)
    torch.testing.assert_close(m_grid.sum(), mass.sum(), rtol=1e-13, atol=0)
    torch.testing.assert_close(mv_grid.reshape(-1, 3).sum(0), p0, rtol=0, atol=1e-12 * p0.abs().max())
    _, v1, _, _ = solver.step(x, v, C, F, tau, vol, mass)
    torch.testing.assert_close((mass[:, None] * v1).sum(0), p0, rtol=0, atol=1e-12 * p0.abs().max())
    assert (v1 - v).abs().max() > 1e-3  # the stress did act: conservation is not trivial


def test_padded_grid_takes_particles_on_the_domain_faces():
    # Positions exactly on the faces 0 and 1 stay inside the padded grid: no mass is lost.
    cfg = SimConfig(n_grid=8, gravity=(0, 0, 0), bound=0, clip=0.0, dtype="float64", dt=1e-3, boundary="sticky",
                    friction=0.0, max_refine=1)
    x = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [0.9999, 1e-4, 0.5]], dtype=F64)
    n = x.shape[0]
    z3, zm = torch.zeros(n, 3, dtype=F64), torch.zeros(n, 3, 3, dtype=F64)
    mass = torch.arange(1, n + 1, dtype=F64)
    m_grid, _ = MPMSolver(cfg).grid(x, z3, zm, zm, torch.ones(n, dtype=F64), mass)
    torch.testing.assert_close(m_grid.sum(), mass.sum(), rtol=1e-14, atol=0)


def test_free_fall_follows_gravity():
    # No stress, no walls reached: symplectic Euler gives y_n = y0 - g dt^2 n (n + 1) / 2 exactly,
    # i.e. g t^2 / 2 up to the O(dt) term g t dt / 2.
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=2, dtype="float64", boundary="sticky", friction=0.0, max_refine=1)
    solver = MPMSolver(cfg)
    x, _, _, _, _, vol, mass = _state(64, seed=4, lo=0.4, hi=0.6)
    x0 = x.clone()
    n = x.shape[0]
    v, C = torch.zeros(n, 3, dtype=F64), torch.zeros(n, 3, 3, dtype=F64)
    F, tau = torch.eye(3, dtype=F64).expand(n, 3, 3).contiguous(), torch.zeros(n, 3, 3, dtype=F64)
    steps, g, dt = 100, 9.8, cfg.dt
    for _ in range(steps):
        x, v, C, F = solver.step(x, v, C, F, tau, vol, mass)
    t = steps * dt
    drop = (x0[:, 1] - x[:, 1]).mean().item()
    assert drop == pytest.approx(g * dt**2 * steps * (steps + 1) / 2, rel=1e-9)
    assert abs(drop - g * t**2 / 2) <= g * t * dt / 2 * (1 + 1e-9)
    torch.testing.assert_close(x[:, [0, 2]], x0[:, [0, 2]], rtol=0, atol=1e-12)


def test_bad_inputs_raise_clear_errors():
    solver = MPMSolver(SimConfig(n_grid=8, dtype="float64", dt=1e-3, bound=3, boundary="sticky", friction=0.0,
                                 max_refine=1))
    x, v, C, F, tau, vol, mass = _state(4, seed=5)
    with pytest.raises(ValueError, match="gca/sim/solver.py: tau must have shape"):
        solver.step(x, v, C, F, tau[:3], vol, mass)
    with pytest.raises(ValueError, match="solver runs torch.float64"):
        solver.step(x.float(), v, C, F, tau, vol, mass)
    with pytest.raises(ValueError, match="boundary='ice'"):
        SimConfig(boundary="ice", dt=1e-3, bound=3, friction=0.0, max_refine=1)
    with pytest.raises(ValueError, match="bound=9"):
        SimConfig(n_grid=16, bound=9, dt=1e-3, boundary="sticky", friction=0.0, max_refine=1)


@pytest.mark.parametrize("boundary,vy,expected", [
    ("sticky", -1.0, (0.0, 0.0, 0.0)), ("slip", -1.0, (1.0, 0.0, 0.0)), ("friction", -1.0, (0.5, 0.0, 0.0)),
    ("sticky", 1.0, (0.0, 0.0, 0.0)), ("slip", 1.0, (1.0, 1.0, 0.0)), ("friction", 1.0, (1.0, 1.0, 0.0)),
])
def test_floor_conditions_hand_computed(boundary, vy, expected):
    # A slab in the floor layer y in [0.5 dx, 1.5 dx): all its stencil nodes (J = 0..2) lie in the
    # 3-cell floor wall, and the grid velocity is the uniform particle velocity (1, vy, 0).
    # Moving into the floor: sticky -> 0; slip drops v_y; friction mu_b = 0.5 also removes
    # mu_b * |v_n| = 0.5 from |v_t| = 1. Moving away: only sticky acts.
    cfg = SimConfig(n_grid=16, dt=1e-3, gravity=(0, 0, 0), bound=3, boundary=boundary, friction=0.5,
                    dtype="float64", max_refine=1)
    g = torch.Generator().manual_seed(6)
    n = 50
    x = torch.rand(n, 3, generator=g, dtype=F64) * torch.tensor([0.3, 1.0, 0.3], dtype=F64)
    x = x * torch.tensor([1.0, cfg.dx, 1.0], dtype=F64) + torch.tensor([0.35, 0.5 * cfg.dx, 0.35], dtype=F64)
    v = torch.tensor([1.0, vy, 0.0], dtype=F64).expand(n, 3).contiguous()
    zeros = torch.zeros(n, 3, 3, dtype=F64)
    F = torch.eye(3, dtype=F64).expand(n, 3, 3).contiguous()
    vol, mass = torch.full((n,), 1e-5, dtype=F64), torch.full((n,), 1e-2, dtype=F64)
    _, v1, C1, _ = MPMSolver(cfg).step(x, v, zeros, F, zeros, vol, mass)
    torch.testing.assert_close(v1, torch.tensor(expected, dtype=F64).expand(n, 3), rtol=0, atol=1e-12)
    torch.testing.assert_close(C1, zeros, rtol=0, atol=1e-9)


def _axial(M):
    """a_k = eps_kbc M_cb for M [N, 3, 3] -> [N, 3]."""
    return torch.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], dim=1)


def _angular_momentum(x, v, C, mass, dx):
    """APIC angular momentum sum_p m_p (x_p x v_p + dx^2/4 axial(C_p)) (quadratic B-splines: D = dx^2/4 I)."""
    return (mass[:, None] * (torch.cross(x, v, dim=1) + dx**2 / 4 * _axial(C))).sum(0)


def test_step_conserves_angular_momentum_for_symmetric_stress():
    # APIC transfers conserve L = sum m (x x v + D axial(C)) exactly; the stress term changes it by
    # -dt sum_p vol_p axial(tau_p) (derivation: sum_i w d x (A d) = axial(A D)), which is zero
    # for a symmetric (Kirchhoff) stress. The non-symmetric case checks the formula itself.
    cfg = SimConfig(n_grid=16, dt=1e-3, gravity=(0, 0, 0), bound=0, dtype="float64", boundary="sticky", friction=0.0,
                    max_refine=1)
    solver = MPMSolver(cfg)
    x, v, C, F, tau, vol, mass = _state(100, seed=7, lo=0.3, hi=0.7, tau_scale=1e4)
    L0 = _angular_momentum(x, v, C, mass, cfg.dx)
    for tau_p, expected_change in (
        (tau + tau.transpose(1, 2), torch.zeros(3, dtype=F64)),
        (tau, -cfg.dt * (vol[:, None] * _axial(tau)).sum(0)),
    ):
        x1, v1, C1, _ = solver.step(x, v, C, F, tau_p, vol, mass)
        L1 = _angular_momentum(x1, v1, C1, mass, cfg.dx)
        torch.testing.assert_close(L1 - L0, expected_change, rtol=0, atol=1e-12 * L0.abs().max())
    assert expected_change.abs().max() > 1e-6 * L0.abs().max()  # the negative case is not trivially zero


@pytest.mark.parametrize("min_node_mass", [0.0, 1e-15])
def test_tiny_stencil_weights_keep_gradients_finite(min_node_mass):
    """A particle 1e-7 m past a cell's centre gives its far corner node a mass of ~1e-40 kg (float32
    subnormal); the adjoint of mv / m is then v / m -> inf and the position gradient NaN. Nodes
    lighter than ``min_node_mass`` count as empty, which keeps it finite (0 reproduces the bug seen as
    a random 'non-finite gradients' divergence in paper-scale training)."""
    cfg = SimConfig(n_grid=16, dt=1e-4, bound=1, min_node_mass=min_node_mass, boundary="sticky", friction=0.0,
                    max_refine=1)
    dx = cfg.dx
    x = torch.tensor([[7.5 * dx + 1e-7] * 3, [0.3] * 3], dtype=torch.float32, requires_grad=True)
    v = torch.tensor([[0.3, -0.2, 0.1], [0.0, 0.0, 0.0]], requires_grad=True)
    C = torch.zeros(2, 3, 3, requires_grad=True)
    F = torch.eye(3).repeat(2, 1, 1).requires_grad_(True)
    tau = torch.zeros(2, 3, 3, requires_grad=True)
    vol = torch.full((2,), 1e-5)
    outs = MPMSolver(cfg).step(x, v, C, F, tau, vol, vol * 1000.0)
    sum(o.sum() for o in outs).backward()
    finite = all(bool(torch.isfinite(t.grad).all()) for t in (x, v, C, F, tau))
    assert finite == (min_node_mass > 0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_backward_from_the_kept_grid_equals_the_taped_recompute_without_replaying_the_step(dtype, monkeypatch):
    # The default backward runs the adjoint kernels on the grid its forward kept; the reference (keep_grid =
    # False) replays P2G, the grid update and G2P under a wp.Tape first. Same kernels, same order: on the CPU
    # (sequential atomics) the gradients are bitwise equal; the incoming cotangents are left as they were.
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=2, boundary="friction", friction=0.5, dtype=str(dtype)[6:], max_refine=1)
    x, v, C, F, tau, vol, mass = _state(200, seed=4, lo=0.02, hi=0.98, dtype=dtype)
    g = torch.Generator().manual_seed(5)
    cots = [torch.randn(t.shape, generator=g, dtype=dtype) for t in (x, v, C, F)]
    launches = []
    real_launch = wp.launch
    monkeypatch.setattr(wp, "launch", lambda *a, **k: launches.append(k.get("adjoint", False)) or real_launch(*a, **k))

    def grads(keep: bool):
        solver = MPMSolver(cfg)
        solver.keep_grid = keep
        inputs = [t.clone().requires_grad_() for t in (x, v, C, F, tau)]
        outs = solver.step(*inputs, vol, mass)
        launches.clear()
        before = [c.clone() for c in cots]
        result = torch.autograd.grad(outs, inputs, cots)
        assert all(torch.equal(a, b) for a, b in zip(cots, before))
        return result, list(launches)

    kept, kept_launches = grads(True)
    taped, taped_launches = grads(False)
    assert kept_launches == [True, True, True]  # three adjoints, no forward replayed
    assert taped_launches.count(False) == 3  # control: the reference replays the step's three kernels
    for a, b in zip(kept, taped):
        assert float(b.abs().max()) > 0
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_split_p2g_equals_the_per_particle_kernel(dtype):
    # The forward P2G with a thread per (particle, node) adds the same terms in the same order on the CPU: the
    # step's outputs are bitwise those of the per-particle kernel, which the backward's adjoint still uses.
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=2, boundary="friction", friction=0.5, dtype=str(dtype)[6:], max_refine=1)
    x, v, C, F, tau, vol, mass = _state(300, seed=6, lo=0.02, hi=0.98, dtype=dtype)
    outs = {}
    for split in (True, False):
        solver = MPMSolver(cfg)
        solver.split_p2g = split
        inputs = [t.clone().requires_grad_() for t in (x, v, C, F, tau)]
        step = solver.step(*inputs, vol, mass)
        outs[split] = (*step, *torch.autograd.grad(step, inputs, [torch.ones_like(o) for o in step]))
    assert float(outs[True][0].detach().sub(x).abs().max()) > 0  # the particles moved
    for a, b in zip(outs[True], outs[False]):
        assert torch.equal(a, b)


def _two_runs(dtype):
    """Two different particle sets (run 0: 40 particles, run 1: 25), overlapping in space."""
    a = _state(40, seed=7, dtype=dtype)
    b = _state(25, seed=8, lo=0.3, hi=0.6, dtype=dtype)
    return a, b


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_runs_in_one_launch_equal_each_run_stepped_alone(dtype):
    # Several runs share the launch (a grid each, stacked): values and gradients are those of stepping each run's
    # particles alone, bitwise on the CPU; the negative control puts both sets on one grid, where they interact.
    cfg = SimConfig(n_grid=12, dt=1e-3, bound=2, boundary="friction", friction=0.3, dtype=str(dtype)[6:], max_refine=1)
    solver = MPMSolver(cfg)
    a, b = _two_runs(dtype)
    g = torch.Generator().manual_seed(9)
    cots = [[torch.randn(t.shape, generator=g, dtype=dtype) for t in s[:4]] for s in (a, b)]

    def alone(s, cot):
        ins = [t.clone().requires_grad_() for t in s[:5]]
        outs = solver.step(*ins, *s[5:])
        return outs, torch.autograd.grad(outs, ins, cot)

    def together(run):
        ins = [torch.cat([sa, sb]).clone().requires_grad_() for sa, sb in zip(a[:5], b[:5])]
        outs = solver.step(*ins, torch.cat([a[5], b[5]]), torch.cat([a[6], b[6]]), run=run, n_runs=2)
        grads = torch.autograd.grad(outs, ins, [torch.cat(c) for c in zip(*cots)])
        return [(o[:40], o[40:]) for o in outs], [(gr[:40], gr[40:]) for gr in grads]

    refs = [alone(a, cots[0]), alone(b, cots[1])]
    run = torch.cat([torch.zeros(40, dtype=torch.int32), torch.ones(25, dtype=torch.int32)])
    outs, grads = together(run)
    for r, (ref_outs, ref_grads) in enumerate(refs):
        for o, ro in zip(outs, ref_outs):
            assert torch.equal(o[r].detach(), ro.detach())
        for gr, rg in zip(grads, ref_grads):
            assert torch.equal(gr[r], rg)
    mixed, _ = together(torch.zeros(65, dtype=torch.int32))  # control: one grid, the sets interact
    assert not torch.equal(mixed[1][0].detach(), refs[0][0][1].detach())


@pytest.mark.grad
def test_runs_in_one_launch_gradcheck_float64():
    cfg = SimConfig(n_grid=8, dt=2e-3, bound=2, boundary="slip", friction=0.0, dtype="float64", max_refine=1)
    solver = MPMSolver(cfg)
    x, v, C, F, tau, vol, mass = _floor_state(4, seed=3)
    run = torch.tensor([0, 1, 1, 0], dtype=torch.int32)
    ins = [t.requires_grad_() for t in (x, v, C, F, tau)]
    assert torch.autograd.gradcheck(lambda *t: solver.step(*t, vol, mass, run=run, n_runs=2), ins, eps=1e-6,
                                    atol=1e-7, rtol=1e-5)


def test_run_indices_are_checked():
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, dtype="float64", max_refine=1))
    x, v, C, F, tau, vol, mass = _state(5, seed=1)
    with pytest.raises(ValueError, match="needs the particles' run indices"):
        solver.step(x, v, C, F, tau, vol, mass, n_runs=2)
    with pytest.raises(ValueError, match=r"run must be an int32 tensor of shape \(5,\)"):
        solver.step(x, v, C, F, tau, vol, mass, run=torch.zeros(5, dtype=torch.int64), n_runs=2)
    with pytest.raises(ValueError, match="n_runs=0 must be an integer >= 1"):
        solver.step(x, v, C, F, tau, vol, mass, run=torch.zeros(5, dtype=torch.int32), n_runs=0)
    # the stacked grids' node index is int32 (warp's, the aggregated kernels' peer key): 11^3 nodes per run at n_grid 8
    with pytest.raises(ValueError, match="pass int32's node index"):
        solver.step(x, v, C, F, tau, vol, mass, run=torch.zeros(5, dtype=torch.int32), n_runs=2 ** 31 // 11 ** 3 + 1)


@pytest.mark.parametrize("split", [False, True])
def test_runs_through_the_taped_reference_and_the_split_p2g(split):
    # the reference backward (taped recompute) and the split P2G kernel take the runs' grids too: bitwise equal
    cfg = SimConfig(n_grid=12, dt=1e-3, bound=2, boundary="friction", friction=0.3, dtype="float64", max_refine=1)
    a, b = _two_runs(torch.float64)
    run = torch.cat([torch.zeros(40, dtype=torch.int32), torch.ones(25, dtype=torch.int32)])
    results = []
    for keep in (True, False):
        solver = MPMSolver(cfg)
        solver.keep_grid, solver.split_p2g = keep, split
        ins = [torch.cat([sa, sb]).clone().requires_grad_() for sa, sb in zip(a[:5], b[:5])]
        outs = solver.step(*ins, torch.cat([a[5], b[5]]), torch.cat([a[6], b[6]]), run=run, n_runs=2)
        results.append([o.detach() for o in outs] + list(torch.autograd.grad(outs, ins, [torch.ones_like(o) for o in outs])))
    for x, y in zip(*results):
        assert torch.equal(x, y)
