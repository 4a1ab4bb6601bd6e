"""gca.sim rollout driver: gradients through checkpointed frames, CFL refusal, divergence detection."""

import pytest
import torch
import warp as wp

from gca.laws.base import Material
from gca.laws.elastic import CorotatedElasticity, corotated_tau
from gca.laws.plastic import IdentityPlasticity
from gca.sim import CFLError, MPMSolver, SimConfig, SimulationDiverged, check_cfl, rollout

wp.config.quiet = True
F64 = torch.float64


class _Corotated:
    """Corotated material (gca.laws.corotated_tau) with mu = 1 kPa * k, k a tensor input, for gradcheck."""

    def __init__(self, k, nu_ratio=0.5):
        self.mu, self.lam = 1e3 * k, 1e3 * k * nu_ratio

    def stress(self, F):
        return corotated_tau(F, self.mu, self.lam)

    def project(self, F_trial):
        return F_trial

    def wave_speed(self):
        return float(((self.lam + 2 * self.mu) / 1e3).detach().sqrt())


class _NaNMaterial(_Corotated):
    """Returns NaN stress: the simulation must stop with a diagnostic."""

    def stress(self, F):
        return torch.full_like(F, float("nan"))


def _blob(n, seed, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    x = 0.4 + 0.2 * torch.rand(n, 3, generator=g, dtype=dtype)
    v = 0.5 * torch.randn(n, 3, generator=g, dtype=dtype)
    vol = torch.full((n,), (0.2 / n ** (1 / 3)) ** 3, dtype=dtype)
    return x, v, vol, vol * 1e3


@pytest.mark.grad
def test_rollout_gradcheck_to_initial_velocity_and_law_parameter():
    # float64 gradcheck through 2 checkpointed frames of 2 steps: d x_final / d (v0, mu).
    cfg = SimConfig(n_grid=8, dt=2e-3, bound=2, boundary="slip", dtype="float64", friction=0.0, max_refine=1)
    solver = MPMSolver(cfg)
    x0, v0, vol, mass = _blob(6, seed=0)
    k = torch.tensor(1.0, dtype=F64)

    def final_positions(v0, k):
        return rollout(solver, _Corotated(k), x0, v0, vol, mass, n_steps=4, steps_per_frame=2).x[-1]

    inputs = (v0.requires_grad_(), k.requires_grad_())
    assert torch.autograd.gradcheck(final_positions, inputs, eps=1e-6, atol=1e-8, rtol=1e-5)


def test_checkpointing_does_not_change_values_or_gradients():
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=3, dtype="float64", boundary="sticky", friction=0.0, max_refine=1)
    solver = MPMSolver(cfg)
    x0, v0, vol, mass = _blob(60, seed=1)
    material = Material(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    results = []
    for checkpoint in (True, False):
        v0_ = v0.clone().requires_grad_()
        out = rollout(solver, material, x0, v0_, vol, mass, n_steps=12, steps_per_frame=4, checkpoint=checkpoint)
        loss = (out.x[1:] * torch.linspace(0, 1, 3 * 60, dtype=F64).reshape(60, 3)).sum() + out.F[-1].sum()
        grads = torch.autograd.grad(loss, [v0_, material.elasticity.log_E])
        results.append((out.x, *grads))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    assert results[0][2].abs() > 0  # the law parameter does receive a gradient


def test_cfl_bound_hand_computed():
    # dx = 0.1 m, c = 9 m/s, |v|max = 1 m/s, cfl = 0.5 -> dt_max = 0.5 * 0.1 / 10 = 5e-3 s.
    assert check_cfl(5e-3, 0.1, 9.0, max_velocity=1.0, cfl=0.5) == pytest.approx(5e-3)
    with pytest.raises(CFLError, match="dt=0.0051 s exceeds the CFL bound 0.005 s"):
        check_cfl(5.1e-3, 0.1, 9.0, max_velocity=1.0, cfl=0.5)


def test_rollout_refuses_too_large_dt_before_stepping():
    # E = 1e7 Pa, rho = 1e3: c ~ 116 m/s; dx = 1/16 m -> dt_max ~ 2.7e-4 s < 1e-3 s.
    solver = MPMSolver(SimConfig(n_grid=16, dt=1e-3, dtype="float64", bound=3, boundary="sticky", friction=0.0,
                                 max_refine=1))
    x0, v0, vol, mass = _blob(10, seed=2)
    material = Material(CorotatedElasticity(1e7, 0.3), IdentityPlasticity(), 1e3).double()
    with pytest.raises(CFLError, match="exceeds the CFL bound"):
        rollout(solver, material, x0, v0, vol, mass, n_steps=2, steps_per_frame=1)


def test_divergence_raises_with_step_count_and_law():
    solver = MPMSolver(SimConfig(n_grid=8, dt=1e-3, dtype="float64", bound=3, boundary="sticky", friction=0.0,
                                 max_refine=1))
    x0, v0, vol, mass = _blob(10, seed=3)
    with pytest.raises(SimulationDiverged, match=r"after step 3, law _NaNMaterial \(CFL: wave speed estimate 1.581 m/s, "
                                                 r"1 sub-step\(s\) per step\): 10 of 10 particles have non-finite"):
        rollout(solver, _NaNMaterial(torch.tensor(1.0, dtype=F64)), x0, v0, vol, mass, n_steps=6, steps_per_frame=3)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_particles_leaving_the_domain_are_detected(dtype):
    # Walls off (bound = 0) and a fast sideways throw: the blob piles up on the clamp at x = 1 - clip dx.
    solver = MPMSolver(SimConfig(n_grid=16, dt=1e-3, bound=0, gravity=(0, 0, 0), dtype=str(dtype)[6:],
                                 boundary="sticky", friction=0.0, max_refine=1))
    x0, _, vol, mass = _blob(20, seed=4, dtype=dtype)
    v0 = torch.zeros_like(x0)
    v0[:, 0] = 20.0
    with pytest.raises(SimulationDiverged, match="of 20 particles sit on the domain clamp"):
        rollout(solver, _Corotated(torch.tensor(0.01, dtype=dtype)), x0, v0, vol, mass, n_steps=40,
                steps_per_frame=4)


def test_rollout_input_errors():
    solver = MPMSolver(SimConfig(n_grid=8, dtype="float64", dt=1e-3, bound=3, boundary="sticky", friction=0.0,
                                 max_refine=1))
    x0, v0, vol, mass = _blob(5, seed=5)
    material = _Corotated(torch.tensor(1.0, dtype=F64))
    with pytest.raises(ValueError, match="multiple of steps_per_frame"):
        rollout(solver, material, x0, v0, vol, mass, n_steps=5, steps_per_frame=2)
    with pytest.raises(ValueError, match="v0 must have shape"):
        rollout(solver, material, x0, v0[:4], vol, mass, n_steps=2, steps_per_frame=1)


def test_cfl_refinement_takes_smaller_steps_with_the_same_frames():
    """dt = 1e-3 s against a bound of ~2.7e-4 s: with max_refine = 4 each step becomes 4 steps of 2.5e-4 s,
    frame for frame the rollout of a solver built with that dt; with max_refine = 3 it is refused."""
    x0, v0, vol, mass = _blob(10, seed=2)
    material = Material(CorotatedElasticity(1e7, 0.3), IdentityPlasticity(), 1e3).double()
    refined = rollout(MPMSolver(SimConfig(n_grid=16, dt=1e-3, dtype="float64", max_refine=4, bound=3,
                                          boundary="sticky", friction=0.0)), material,
                      x0, v0, vol, mass, n_steps=4, steps_per_frame=2)
    direct = rollout(MPMSolver(SimConfig(n_grid=16, dt=2.5e-4, dtype="float64", bound=3, boundary="sticky",
                                         friction=0.0, max_refine=1)), material,
                     x0, v0, vol, mass, n_steps=16, steps_per_frame=8)
    assert refined.refine == 4 and direct.refine == 1 and refined.x.shape == (3, 10, 3)
    torch.testing.assert_close(refined.x, direct.x, rtol=0, atol=0)
    torch.testing.assert_close(refined.F, direct.F, rtol=0, atol=0)
    with pytest.raises(CFLError, match="max_refine=3 sub-steps allow \\(needs 4\\)"):
        rollout(MPMSolver(SimConfig(n_grid=16, dt=1e-3, dtype="float64", max_refine=3, bound=3, boundary="sticky", friction=0.0)), material,
                x0, v0, vol, mass, n_steps=4, steps_per_frame=2)


def _swept_gradients(solver, material, x0, v0, vol, mass, frames, loss_at, skip=()):
    """(launch scale's, log E's) gradients of sum_f loss_at(f, x_f, F_f) over ``frames`` through the reverse sweep:
    each frame's loss differentiated to its own (x_f, F_f) leaves, last frame first (``skip``: frames left out)."""
    a = torch.tensor(1.0, dtype=F64, requires_grad=True)
    log_E = material.elasticity.log_E
    log_E.grad = None
    out = rollout(solver, material, x0, a * v0, vol, mass, n_steps=12, steps_per_frame=4, sweep=True)
    assert not out.x.requires_grad and not out.F.requires_grad
    for f in sorted(frames, reverse=True):
        if f in skip:
            continue
        x, F = (t[f].detach().requires_grad_() for t in (out.x, out.F))
        out.sweep.add(f, *torch.autograd.grad(loss_at(f, x, F), [x, F]))
    out.sweep.finish()
    return out, a.grad, log_E.grad.clone()


def test_reverse_sweep_equals_autograd_through_the_rollout():
    """rollout(..., sweep=True) + ReverseSweep (the losses' cotangents handed in frame by frame, last first) gives
    autograd's gradients through the rollout, to the law's parameter and through a launch parameter (v0 = a v),
    in float64; the frames are the same. Negative control: a frame's cotangent left out changes both."""
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=3, dtype="float64", boundary="sticky", friction=0.0, max_refine=1)
    solver = MPMSolver(cfg)
    x0, v0, vol, mass = _blob(60, seed=1)
    material = Material(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    g = torch.Generator().manual_seed(3)
    wx, wF = torch.randn(4, 60, 3, generator=g, dtype=F64), torch.randn(4, 60, 3, 3, generator=g, dtype=F64)
    frames = [0, 1, 3]  # frame 2 unsupervised, frame 0 the launch

    def loss_at(f, x, F):  # nonlinear in both, as an image loss is
        return (wx[f] * x).square().sum() + (wF[f] * F).sin().sum()

    a = torch.tensor(1.0, dtype=F64, requires_grad=True)
    ref = rollout(solver, material, x0, a * v0, vol, mass, n_steps=12, steps_per_frame=4)
    g_ref = torch.autograd.grad(sum(loss_at(f, ref.x[f], ref.F[f]) for f in frames), [a, material.elasticity.log_E])
    out, g_a, g_E = _swept_gradients(solver, material, x0, v0, vol, mass, frames, loss_at)
    torch.testing.assert_close(out.x, ref.x.detach(), rtol=0, atol=0)
    torch.testing.assert_close(out.F, ref.F.detach(), rtol=0, atol=0)
    assert abs(float(g_ref[0])) > 0 and abs(float(g_ref[1])) > 0
    torch.testing.assert_close(g_a, g_ref[0], rtol=1e-10, atol=0)
    torch.testing.assert_close(g_E, g_ref[1], rtol=1e-10, atol=0)
    _, g_a3, g_E3 = _swept_gradients(solver, material, x0, v0, vol, mass, frames, loss_at, skip=(3,))
    assert not torch.allclose(g_a3, g_ref[0], rtol=1e-3) and not torch.allclose(g_E3, g_ref[1], rtol=1e-3)


def test_reverse_sweep_refuses_frames_out_of_order():
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=3, dtype="float64", boundary="sticky", friction=0.0, max_refine=1)
    x0, v0, vol, mass = _blob(20, seed=2)
    material = Material(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    out = rollout(MPMSolver(cfg), material, x0, v0, vol, mass, n_steps=8, steps_per_frame=4, sweep=True)
    sweep = out.sweep
    with pytest.raises(ValueError, match="frame 3"):
        sweep.add(3, None, None)  # only frames 0..2 exist
    sweep.add(1, None, None)
    for again in (2, 1):  # later, or the same frame twice
        with pytest.raises(ValueError, match="last first"):
            sweep.add(again, None, None)
    sweep.finish()
    with pytest.raises(ValueError, match="twice"):
        sweep.finish()
    with pytest.raises(ValueError, match="finish"):
        sweep.add(0, None, None)


class _NaNLaw(Material):
    """A corotated Material whose stress turns NaN: a swept rollout must still stop with the diagnostic."""

    def stress(self, F):
        return torch.full_like(F, float("nan"))


def test_swept_rollout_judges_its_frames_once_and_names_the_step():
    """rollout(..., sweep=True) returns before reading its health checks (the host goes on while the GPU
    simulates); ReverseSweep.judge reads them once and raises SimulationDiverged at the first broken frame's step,
    as the per-frame checks do; add() and finish() judge first when the caller has not."""
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=3, dtype="float64", boundary="sticky", friction=0.0, max_refine=1)
    x0, v0, vol, mass = _blob(20, seed=2)
    bad = _NaNLaw(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    with pytest.raises(SimulationDiverged, match="after step 4, law") as per_frame:
        rollout(MPMSolver(cfg), bad, x0, v0, vol, mass, n_steps=12, steps_per_frame=4, graph=True)
    out = rollout(MPMSolver(cfg), bad, x0, v0, vol, mass, n_steps=12, steps_per_frame=4, sweep=True)
    assert out.clamped == []
    with pytest.raises(SimulationDiverged) as swept:
        out.sweep.judge()
    assert str(swept.value) == str(per_frame.value)
    out = rollout(MPMSolver(cfg), bad, x0, v0, vol, mass, n_steps=12, steps_per_frame=4, sweep=True)
    with pytest.raises(SimulationDiverged, match="after step 4"):
        out.sweep.add(3, None, None)
    good = Material(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    out = rollout(MPMSolver(cfg), good, x0, v0, vol, mass, n_steps=12, steps_per_frame=4, sweep=True)
    out.sweep.finish()
    ref = rollout(MPMSolver(cfg), good, x0, v0, vol, mass, n_steps=12, steps_per_frame=4)
    assert out.clamped == ref.clamped and len(out.clamped) == 4


def test_a_swept_rollout_is_freed_without_the_garbage_collector():
    """The sweep holds the frames, not the Rollout: with the cyclic collector off, a swept rollout's frames are freed
    as soon as the caller drops it (a Rollout <-> sweep cycle kept every iteration's frames until a collection:
    9.4 GiB at the peak of a 200-iteration ball run on the H100, session 31)."""
    import gc
    import weakref

    cfg = SimConfig(n_grid=16, dt=1e-3, bound=3, dtype="float64", boundary="sticky", friction=0.0, max_refine=1)
    x0, v0, vol, mass = _blob(20, seed=2)
    material = Material(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    enabled = gc.isenabled()
    gc.disable()
    try:
        out = rollout(MPMSolver(cfg), material, x0, v0, vol, mass, n_steps=8, steps_per_frame=4, sweep=True)
        out.sweep.finish()
        frames = weakref.ref(out.x)
        del out
        assert frames() is None
    finally:
        if enabled:
            gc.enable()


def test_a_sweep_without_cotangents_or_abandoned_adds_no_gradient():
    """finish() with no cotangent added (a method without image terms) sweeps nothing and leaves .grad None, as
    autograd would not have run; abandon() (the caller's error mid-sweep) adds nothing and ends the sweep."""
    cfg = SimConfig(n_grid=16, dt=1e-3, bound=3, dtype="float64", boundary="sticky", friction=0.0, max_refine=1)
    x0, v0, vol, mass = _blob(20, seed=2)
    material = Material(CorotatedElasticity(3e4, 0.3), IdentityPlasticity(), 1e3).double()
    log_E = material.elasticity.log_E
    log_E.grad = None
    out = rollout(MPMSolver(cfg), material, x0, v0, vol, mass, n_steps=12, steps_per_frame=4, sweep=True)
    calls = []
    backward = out.sweep.runner.backward
    out.sweep.runner.backward = lambda *a: (calls.append(1), backward(*a))[1]
    out.sweep.finish()
    assert calls == [] and log_E.grad is None
    out = rollout(MPMSolver(cfg), material, x0, v0, vol, mass, n_steps=12, steps_per_frame=4, sweep=True)
    x = out.x[2].detach().requires_grad_()
    out.sweep.add(2, *torch.autograd.grad(x.square().sum(), [x]), None)
    out.sweep.abandon()
    assert log_E.grad is None
    with pytest.raises(ValueError, match="after finish"):
        out.sweep.add(1, None, None)
    out = rollout(MPMSolver(cfg), material, x0, v0, vol, mass, n_steps=12, steps_per_frame=4, sweep=True)
    out.sweep.add(2, torch.ones_like(out.x[2]), None)
    out.sweep.finish()
    assert log_E.grad is not None and abs(float(log_E.grad)) > 0  # the positive control: an added cotangent sweeps
