"""gca.laws.fused.corotated_tau: the corotated law in warp kernels with a hand-written adjoint, against the torch
reference ``gca.laws.elastic.corotated_tau`` (values, gradients in F, mu and lam) and float64 gradchecks."""

import pytest
import torch
from torch.autograd import gradcheck

from gca.laws import fused
from gca.laws.elastic import CorotatedElasticity, corotated_tau

from test_laws_neural_fused import hard_F

f64 = torch.float64


def _moduli(n, per_particle, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    shape = (n,) if per_particle else ()
    mu = (2e4 * (1 + torch.rand(shape, generator=g, dtype=f64))).to(dtype)
    lam = (3e4 * (1 + torch.rand(shape, generator=g, dtype=f64))).to(dtype)
    return mu, lam


def _well_posed(F):
    """Rows where the polar rotation is differentiable: sigma_i + sigma_j away from 0 (not at the inversion clamp)."""
    s = torch.linalg.svdvals(F.detach())
    sign = torch.sign(torch.linalg.det(F.detach()))
    s = torch.cat([s[:, :2], (s[:, 2] * sign)[:, None]], dim=1)  # the sign-fixed singular values
    pair = torch.stack([s[:, 0] + s[:, 1], s[:, 0] + s[:, 2], s[:, 1] + s[:, 2]], dim=1).abs().min(dim=1).values
    return pair > 1e-3


@pytest.mark.parametrize("per_particle", [False, True])
@pytest.mark.parametrize("dtype,rtol", [(f64, 1e-10), (torch.float32, 2e-4)])
def test_fused_corotated_equals_the_torch_law_in_values_and_gradients(per_particle, dtype, rtol):
    F = hard_F(40, seed=3, dtype=dtype)
    keep = _well_posed(F)
    F = F[keep].contiguous()
    mu, lam = _moduli(F.shape[0], per_particle, dtype)
    (results, _) = compare_laws(fused.corotated_tau, corotated_tau, F, mu, lam, rtol)
    assert float(results[0][0][:4].abs().max()) == 0.0  # F = I: exactly no stress


def compare_laws(fast, reference, F, mu, lam, rtol):
    """``fast`` against ``reference`` (tau = law(F, mu, lam)): tau and the gradients of F, mu and lam under one seeded
    cotangent agree to ``rtol`` of the reference's largest entry, each non-zero. Returns both [(tau, v_F, v_mu, v_lam)]."""
    g = torch.Generator().manual_seed(7)
    cot = torch.randn(F.shape, generator=g, dtype=f64).to(F.dtype)
    results = []
    for fn in (fast, reference):
        ins = [t.clone().requires_grad_() for t in (F, mu, lam)]
        tau = fn(*ins)
        results.append((tau.detach(), *torch.autograd.grad(tau, ins, cot)))
    for name, a, b in zip(("tau", "F", "mu", "lam"), *results):
        assert a.shape == b.shape, name
        assert float(b.abs().max()) > 0, name
        assert float((a - b).abs().max()) <= rtol * float(b.abs().max()), name
    return results, cot


@pytest.mark.grad
@pytest.mark.parametrize("per_particle", [False, True])
def test_fused_corotated_gradcheck_float64(per_particle):
    F = hard_F(12, seed=5)
    F = F[_well_posed(F)][:8].contiguous()
    mu, lam = _moduli(F.shape[0], per_particle, f64, seed=2)
    scale = 1e-4  # stresses of O(1) for gradcheck's absolute tolerance
    ins = [F.requires_grad_(), (mu * scale).requires_grad_(), (lam * scale).requires_grad_()]
    assert gradcheck(fused.corotated_tau, ins, eps=1e-6, atol=1e-8, rtol=1e-6)


@pytest.mark.grad
def test_gradcheck_catches_a_wrong_corotated_adjoint(monkeypatch):
    # negative control: the same check rejects a 1 % error in v_lam
    F = hard_F(12, seed=5)
    F = F[_well_posed(F)][:8].contiguous()
    mu, lam = _moduli(F.shape[0], True, f64, seed=2)
    ins = [F.requires_grad_(), (mu * 1e-4).requires_grad_(), (lam * 1e-4).requires_grad_()]
    backward = fused._Corotated.backward

    def wrong(ctx, v_tau):
        v_F, v_mu, v_lam = backward(ctx, v_tau)
        return v_F, v_mu, 1.01 * v_lam

    monkeypatch.setattr(fused._Corotated, "backward", staticmethod(wrong))
    assert not gradcheck(fused.corotated_tau, ins, eps=1e-6, atol=1e-8, rtol=1e-6, raise_exception=False)


def test_corotated_elasticity_takes_the_fused_path_and_learns_E_through_it():
    F = hard_F(30, seed=8)
    F = F[_well_posed(F)].contiguous()
    law = CorotatedElasticity(E=1e5, nu=0.3).double()
    grads = []
    for fast in (True, False):
        law.fast_path = fast
        law.zero_grad()
        (law(F) ** 2).sum().backward()
        grads.append(law.log_E.grad.clone())
    assert float(grads[1].abs()) > 0
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=0)
    calls = []
    apply = fused._Corotated.apply
    fused._Corotated.apply = lambda *a: calls.append(1) or apply(*a)
    try:
        law.fast_path = True
        law(F)
    finally:
        fused._Corotated.apply = apply
    assert calls == [1]
