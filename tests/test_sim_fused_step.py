"""gca.sim.fused_step / MPMSolver.step_fused: the analytic law's stress inside P2G and the grid zeroed by its
update (three kernels a step), against the generic step (law, then transfers) on the CPU: frames of several
steps, both analytic laws, one modulus or one per particle, inverted and crushed rows, a plastic law after the
step, runs sharing a launch; with negative controls (a missing zeroing, a wrong law) and the frame's choice of
path (fused only where no gradient is asked for)."""

import pytest
import torch
import warp as wp

from gca.laws import fused
from gca.laws.base import Material
from gca.laws.elastic import CorotatedElasticity
from gca.laws.ood import NeoHookeanElasticity
from gca.laws.plastic import IdentityPlasticity, VonMisesPlasticity
from gca.sim import fused_step
from gca.sim import rollout
from gca.sim.frame import fused_law, simulate_frame
from gca.sim.kernels import KERNELS
from gca.sim.solver import MPMSolver, SimConfig

LAWS = {"corotated": lambda: CorotatedElasticity(1e5, 0.3, learnable=False),
        "neo_hookean": lambda: NeoHookeanElasticity(2e5, 0.4, learnable=False)}


def _state(n: int, dtype, seed: int = 0):
    """A moving, strained blob: (x, v, C, F, vol, mass), two rows of F inverted and one crushed (J < 1e-3); a
    quarter of the particles in the floor's and a side wall's regions, thrown into them with a tangential
    velocity (the walls and their friction act), three of them on the position clamp moving out (it acts)."""
    g = torch.Generator().manual_seed(seed)
    x = 0.3 + 0.4 * torch.rand(n, 3, generator=g, dtype=dtype)
    v = 0.3 * torch.randn(n, 3, generator=g, dtype=dtype)
    q = n // 4
    x[-q:, :2] = 0.04 + 0.08 * torch.rand(q, 2, generator=g, dtype=dtype)  # within 2 cells of x = 0 and y = 0
    v[-q:] = torch.tensor([-2.0, -3.0, 1.5], dtype=dtype)
    x[-3:, 1] = 0.5 / 16  # on the clamp of a 16-cell grid (clip 0.5 cells), moving down
    C = 0.5 * torch.randn(n, 3, 3, generator=g, dtype=dtype)
    F = torch.eye(3, dtype=dtype) + 0.15 * torch.randn(n, 3, 3, generator=g, dtype=dtype)
    F[0] = torch.diag(torch.tensor([1.1, 0.9, -0.8], dtype=dtype))
    F[1] = -F[1]
    F[2] = torch.diag(torch.tensor([0.05, 0.1, 0.1], dtype=dtype))
    vol = torch.full((n,), 1e-5, dtype=dtype)
    return x, v, C, F, vol, 1000.0 * vol


def _material(law: str, dtype, per_particle: bool = False, plastic: bool = False, n: int = 0) -> Material:
    e = LAWS[law]()
    if per_particle:  # one Young's modulus per particle, 0.5-2x
        g = torch.Generator().manual_seed(1)
        e.log_E = torch.nn.Parameter(e.log_E.detach() + torch.log(0.5 + 1.5 * torch.rand(n, generator=g)),
                                     requires_grad=False)
    p = VonMisesPlasticity(3e5, 0.25, 2e3, learnable=False) if plastic else IdentityPlasticity()
    return Material(e, p, 1000.0).to(dtype)


def _frames(solver, material, n_steps, state):
    """(fused, generic) outputs of one frame of ``n_steps`` steps from ``state`` under no_grad."""
    with torch.no_grad():
        fast = simulate_frame(solver, material, n_steps, *state[:4], *state[4:])
        solver.fuse_analytic = False
        try:
            slow = simulate_frame(solver, material, n_steps, *state[:4], *state[4:])
        finally:
            solver.fuse_analytic = True
    return fast, slow


def _assert_close(fast, slow, rtol):
    for name, a, b in zip("xvCF", fast, slow):
        scale = float(b.abs().max())
        assert torch.isfinite(a).all(), name
        assert float((a - b).abs().max()) <= rtol * scale, (name, float((a - b).abs().max()), scale)


@pytest.mark.parametrize("plastic", [False, True])
@pytest.mark.parametrize("per_particle", [False, True])
@pytest.mark.parametrize("law", sorted(LAWS))
@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_a_fused_frame_equals_the_generic_frame(law, per_particle, plastic, dtype, rtol, monkeypatch):
    cfg = SimConfig(n_grid=16, dtype="float64" if dtype == torch.float64 else "float32")
    solver = MPMSolver(cfg)
    assert not solver.frames_fused  # on a CPU by default the frame goes step by step (measured faster there)
    solver.fuse_frames = True
    n = 400
    state = _state(n, dtype)
    material = _material(law, dtype, per_particle, plastic, n)
    calls = []
    monkeypatch.setattr(MPMSolver, "frame_fused", lambda self, *a, **k: calls.append(a[7]) or
                        _ORIGINAL_FRAME_FUSED(self, *a, **k))
    fast, slow = _frames(solver, material, 6, state)
    # a plastic material: the fused step, every step; a purely elastic one: the whole frame in one fused call
    assert calls == ([1] * 6 if plastic else [6])
    _assert_close(fast, slow, rtol)
    assert float((fast[0] - state[0]).abs().max()) > 1e-4  # the particles moved: the comparison is not vacuous


_ORIGINAL_FRAME_FUSED = MPMSolver.frame_fused


@pytest.mark.parametrize("n_steps", [1, 2, 5])
def test_a_fused_elastic_frame_equals_its_fused_steps_bitwise_on_the_cpu(n_steps):
    # frame_fused (G2P of each step and P2G of the next in one pass) against step_fused n times: the same operations
    dtype = torch.float32
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float32"))
    x, v, C, F, vol, mass = _state(300, dtype, seed=5)
    law = _material("neo_hookean", dtype, per_particle=True, n=300).elasticity.analytic_stress(F)
    with torch.no_grad():
        frame = solver.frame_fused(x, v, C, F, law, vol, mass, n_steps)
        state = (x, v, C, F)
        for _ in range(n_steps):
            state = solver.step_fused(*state, law, vol, mass)
    for a, b in zip(frame, state):
        assert torch.equal(a, b)
    assert torch.equal(x, _state(300, dtype, seed=5)[0])  # the inputs are left alone


@pytest.mark.parametrize("boundary,bound", [("sticky", 2), ("slip", 2), ("friction", 2), ("friction", 0)])
def test_the_walls_and_the_clamp_act_alike_in_both_paths(boundary, bound):
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64", boundary=boundary, bound=bound, friction=0.5))
    solver.fuse_frames = True
    state = _state(400, dtype, seed=7)
    for plastic in (False, True):
        fast, slow = _frames(solver, _material("corotated", dtype, plastic=plastic), 4, state)
        _assert_close(fast, slow, 1e-12)
    if bound:  # the thrown quarter: stopped (sticky) or turned along the walls, not still falling at 3 m/s
        assert float(fast[1][-100:, 1].min()) > -3.0 + 0.5
    else:  # no walls: the clamp holds the particles thrown out of the domain
        assert float(fast[0][-3:, 1].max()) == pytest.approx(solver.cfg.clamp_range[0])


def test_a_frame_stopped_between_scatter_and_zeroing_leaves_the_grid_clean(monkeypatch):
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64"))
    solver.fuse_frames = True
    material = _material("neo_hookean", dtype)
    a, b = _state(200, dtype, seed=8), _state(200, dtype, seed=9)
    real_launch = wp.launch

    def interrupted(kernel, *args, **kwargs):
        if "grid_update_zero" in kernel.key:
            raise KeyboardInterrupt
        return real_launch(kernel, *args, **kwargs)
    monkeypatch.setattr(wp, "launch", interrupted)
    with pytest.raises(KeyboardInterrupt), torch.no_grad():
        simulate_frame(solver, material, 3, *a[:4], *a[4:])
    monkeypatch.setattr(wp, "launch", real_launch)
    mv, m, _ = (t.numpy() for t in solver._zeroed_grid(1))
    assert not mv.any() and not m.any()
    fast, slow = _frames(solver, material, 3, b)  # another state: a dirty grid would have shown here
    _assert_close(fast, slow, 1e-12)


def test_a_trainable_analytic_law_graphed_equals_its_checkpointed_rollout():
    # the graph's forward replay takes the fused frame, its recompute-backward the generic step: values and
    # gradients (launch velocity, log E) equal to the checkpointed rollout's, which never fuses
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64", max_refine=1))
    solver.fuse_frames = True
    x, v, C, F, vol, mass = _state(150, dtype, seed=10)
    results = []
    for graph in (True, False):
        material = Material(NeoHookeanElasticity(2e5, 0.4, learnable=True), IdentityPlasticity(), 1000.0).to(dtype)
        v0 = v.clone().requires_grad_(True)
        out = rollout(solver, material, x, v0, vol, mass, 6, 2, checkpoint=True, graph=graph)
        loss = (out.x[-1] * torch.linspace(0.5, 1.5, x.shape[0], dtype=dtype)[:, None]).sum() + (out.F[-1] ** 2).sum()
        results.append((out.x, *torch.autograd.grad(loss, [v0, material.elasticity.log_E])))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    assert float(results[0][2].abs()) > 0


def test_runs_sharing_a_launch_and_a_refined_solver_match_the_generic_step():
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64"))
    n = 300
    state = _state(n, dtype, seed=4)
    run = (torch.arange(n) >= n // 2).to(torch.int32)
    solver.fuse_frames = True
    batched = solver.with_runs(run, 2).refined(2)
    assert batched.fuse_analytic and batched.frames_fused and batched._batch is not None
    fast, slow = _frames(batched, _material("corotated", dtype), 3, state)
    _assert_close(fast, slow, 1e-12)


def test_the_grid_is_zero_after_each_fused_step_and_a_missing_zeroing_is_caught(monkeypatch):
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64"))
    solver.fuse_frames = True
    state = _state(200, dtype, seed=2)
    material = _material("neo_hookean", dtype)
    fast, slow = _frames(solver, material, 3, state)
    _assert_close(fast, slow, 1e-12)
    mv, m, _ = (t.numpy() for t in solver._zeroed_grid(1))
    assert not mv.any() and not m.any()
    # negative control: the plain grid update (no zeroing) lets every step's P2G pile onto the last one's
    kernels = fused_step.make_fused_step_kernels(dtype)
    broken = type(kernels)(**{**vars(kernels), "grid_update_zero": KERNELS["float64"].grid_update})
    monkeypatch.setattr(fused_step, "make_fused_step_kernels", lambda dt: broken)
    monkeypatch.setattr("gca.sim.solver.make_fused_step_kernels", lambda dt: broken)
    fresh = MPMSolver(SimConfig(n_grid=16, dtype="float64"))
    fresh.fuse_frames = True
    fast, slow = _frames(fresh, material, 3, state)
    assert float((fast[1] - slow[1]).abs().max()) > 1e-3 * float(slow[1].abs().max())


def test_a_wrong_law_in_the_fused_step_is_caught():
    # negative control of the equality: the corotated material's state stepped with the neo-Hookean stress
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64"))
    x, v, C, F, vol, mass = _state(200, dtype, seed=3)
    material = _material("corotated", dtype)
    right = material.elasticity.analytic_stress(F)
    wrong = fused.AnalyticStress(fused.NEO_HOOKEAN, right.mu, right.lam, 1e-3)
    with torch.no_grad():
        a = solver.step_fused(x, v, C, F, right, vol, mass)
        b = solver.step_fused(x, v, C, F, wrong, vol, mass)
        ref = solver.step(x, v, C, F, material.stress(F), vol, mass)
    assert torch.allclose(a[1], ref[1], rtol=1e-12, atol=1e-12)
    assert float((b[1] - ref[1]).abs().max()) > 1e-3 * float(ref[1].abs().max())


def test_the_frame_fuses_only_where_no_gradient_is_asked_for():
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64"))
    x, v, C, F, vol, mass = _state(100, dtype)
    learnable = Material(CorotatedElasticity(1e5, 0.3, learnable=True), IdentityPlasticity(), 1000.0).to(dtype)
    fixed = _material("corotated", dtype)
    assert fused_law(solver, learnable, x, v, C, F) is None  # a parameter requires a gradient, autograd records
    assert fused_law(solver, fixed, x, v.requires_grad_(), C, F) is None  # the state requires one
    v = v.detach()
    assert isinstance(fused_law(solver, fixed, x, v, C, F), fused.AnalyticStress)
    with torch.no_grad():
        assert isinstance(fused_law(solver, learnable, x, v, C, F), fused.AnalyticStress)
    solver.fuse_analytic = False
    assert fused_law(solver, fixed, x, v, C, F) is None
    solver.fuse_analytic = True
    fixed.elasticity.fast_path = False
    assert fused_law(solver, fixed, x, v, C, F) is None

    class Damped(Material):  # a stress that is not the elasticity's alone: never fused
        def stress(self, F):
            return super().stress(F) * 0.5
    assert fused_law(solver, Damped(CorotatedElasticity(1e5, 0.3), IdentityPlasticity(), 1000.0).to(dtype),
                     x, v, C, F) is None

    class Stiffer(CorotatedElasticity):  # a subclass that changes the law but inherits its analytic form: not fused
        def forward(self, F):
            return 3.0 * super().forward(F)
    assert fused_law(solver, Material(Stiffer(1e5, 0.3, learnable=False), IdentityPlasticity(), 1000.0).to(dtype),
                     x, v, C, F) is None
    # a buffer the moduli come from requires a gradient: the generic step keeps it
    through_nu = _material("neo_hookean", dtype)
    through_nu.elasticity.nu.requires_grad_(True)
    assert fused_law(solver, through_nu, x, v, C, F) is None
    with torch.no_grad():
        assert fused_law(solver, through_nu, x, v, C, F) is not None
    # the gradient path still differentiates the law's modulus through the generic step
    out = simulate_frame(solver, learnable, 2, x, v.requires_grad_(), C, F, vol, mass)
    out[0].sum().backward()
    assert learnable.elasticity.log_E.grad is not None and float(learnable.elasticity.log_E.grad.abs()) > 0


def test_only_a_purely_elastic_material_is_fused_a_frame_at_a_time(monkeypatch):
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64"))
    solver.fuse_frames = True
    state = _state(100, dtype, seed=11)

    class Softening(IdentityPlasticity):  # looks like the identity, is not
        def forward(self, F_trial):
            return 0.99 * F_trial

    class Projecting(Material):  # the material's own projection between steps
        def project(self, F_trial):
            return 0.99 * F_trial
    for material in (Material(CorotatedElasticity(1e5, 0.3, learnable=False), Softening(), 1000.0).to(dtype),
                     Projecting(CorotatedElasticity(1e5, 0.3, learnable=False), IdentityPlasticity(),
                                1000.0).to(dtype)):
        calls = []
        monkeypatch.setattr(MPMSolver, "frame_fused", lambda self, *a, **k: calls.append(a[7]) or
                            _ORIGINAL_FRAME_FUSED(self, *a, **k))
        fast, slow = _frames(solver, material, 3, state)
        assert calls == [1, 1, 1]  # step by step, the projection between steps
        _assert_close(fast, slow, 1e-12)
    with torch.no_grad():  # no steps: the state as it was
        out = simulate_frame(solver, _material("corotated", dtype), 0, *state[:4], *state[4:])
    assert all(torch.equal(a, b) for a, b in zip(out, state[:4]))


def test_step_fused_refuses_a_gradient_and_bad_moduli_in_one_line():
    dtype = torch.float64
    solver = MPMSolver(SimConfig(n_grid=16, dtype="float64"))
    x, v, C, F, vol, mass = _state(50, dtype)
    law = _material("corotated", dtype).elasticity.analytic_stress(F)
    with pytest.raises(ValueError, match="gca/sim/solver.py: step_fused / frame_fused have no backward"):
        solver.step_fused(x.requires_grad_(), v, C, F, law, vol, mass)
    with pytest.raises(ValueError, match="gca/laws/fused.py: AnalyticStress: kind=7"):
        fused.AnalyticStress(7, law.mu, law.lam)
    bad = fused.AnalyticStress(law.kind, torch.ones(7, dtype=dtype), torch.ones(7, dtype=dtype))
    with pytest.raises(ValueError,
                       match=r"gca/sim/solver.py: step_fused / frame_fused: mu must be .* shape \[1\] or \[50\]"):
        with torch.no_grad():
            solver.step_fused(x, v, C, F, bad, vol, mass)
