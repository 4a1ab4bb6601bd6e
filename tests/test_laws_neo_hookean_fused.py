"""gca.laws.fused.neo_hookean_tau: the neo-Hookean law in one warp kernel each way with a hand-written adjoint,
against the torch reference ``gca.laws.ood.neo_hookean_tau`` (values, gradients in F, mu and lam; crushed and
inverted rows below the J clamp included) and float64 gradchecks with a negative control."""

import pytest
import torch
from torch.autograd import gradcheck

from gca.laws import fused
from gca.laws.ood import J_MIN, NeoHookeanElasticity, neo_hookean_tau
from gca.train.law import CATEGORY_LAWS

from test_laws_corotated_fused import _moduli, compare_laws
from test_laws_neural_fused import hard_F

f64 = torch.float64


def _with_crushed(F):
    """``hard_F`` plus a row crushed below the clamp (0 < J < J_MIN) and one just above it (J = 1.02 J_MIN)."""
    crushed = torch.diag(torch.tensor([0.05, 0.1, 0.1], dtype=F.dtype))  # J = 5e-4
    above = torch.diag(torch.tensor([0.1, 0.1, 0.102], dtype=F.dtype))  # J = 1.02e-3
    return torch.cat([F, crushed[None], above[None]]).contiguous()


@pytest.mark.parametrize("per_particle", [False, True])
@pytest.mark.parametrize("dtype,rtol", [(f64, 1e-10), (torch.float32, 2e-5)])
def test_fused_neo_hookean_equals_the_torch_law_in_values_and_gradients(per_particle, dtype, rtol):
    F = _with_crushed(hard_F(40, seed=3, dtype=dtype))
    mu, lam = _moduli(F.shape[0], per_particle, dtype)
    results, cot = compare_laws(lambda F, mu, lam: fused.neo_hookean_tau(F, mu, lam, J_MIN), neo_hookean_tau,
                                F, mu, lam, rtol)
    assert float(results[0][0][:4].abs().max()) == 0.0  # F = I: exactly no stress
    # inverted and crushed rows (J < J_MIN): the pressure is the clamp's, and no volumetric gradient reaches F there
    tau, v_F = results[0][0], results[0][1]
    for row in (5, F.shape[0] - 2):
        m = mu if mu.dim() == 0 else mu[row]
        l = lam if lam.dim() == 0 else lam[row]
        f = F[row]
        expect = m * (f @ f.T - torch.eye(3, dtype=dtype)) + l * torch.log(torch.tensor(J_MIN, dtype=dtype)) * \
            torch.eye(3, dtype=dtype)
        torch.testing.assert_close(tau[row].detach(), expect, rtol=rtol * 10, atol=0)
        G = cot[row]
        torch.testing.assert_close(v_F[row], m * (G + G.T) @ f, rtol=rtol * 10, atol=rtol * float(v_F.abs().max()))


@pytest.mark.grad
@pytest.mark.parametrize("per_particle", [False, True])
def test_fused_neo_hookean_gradcheck_float64(per_particle):
    F = hard_F(12, seed=5)[:8].contiguous()  # F = I, a tie, inverted rows (below the clamp)
    mu, lam = _moduli(F.shape[0], per_particle, f64, seed=2)
    scale = 1e-4  # stresses of O(1) for gradcheck's absolute tolerance
    ins = [F.requires_grad_(), (mu * scale).requires_grad_(), (lam * scale).requires_grad_()]
    assert gradcheck(lambda F, mu, lam: fused.neo_hookean_tau(F, mu, lam, J_MIN), ins, eps=1e-6, atol=1e-8, rtol=1e-6)


@pytest.mark.grad
@pytest.mark.parametrize("wrong_at", ["F", "mu", "lam"])
def test_gradcheck_catches_a_wrong_neo_hookean_adjoint(monkeypatch, wrong_at):
    # negative control: the same check rejects a 1 % error in each of the adjoint's outputs
    F = hard_F(12, seed=5)[:8].contiguous()
    mu, lam = _moduli(F.shape[0], True, f64, seed=2)
    ins = [F.requires_grad_(), (mu * 1e-4).requires_grad_(), (lam * 1e-4).requires_grad_()]
    backward = fused._NeoHookean.backward
    at = ("F", "mu", "lam").index(wrong_at)

    def wrong(ctx, v_tau):
        grads = list(backward(ctx, v_tau))
        grads[at] = 1.01 * grads[at]
        return tuple(grads)

    monkeypatch.setattr(fused._NeoHookean, "backward", staticmethod(wrong))
    assert not gradcheck(lambda F, mu, lam: fused.neo_hookean_tau(F, mu, lam, J_MIN), ins, eps=1e-6, atol=1e-8,
                         rtol=1e-6, raise_exception=False)


def test_neo_hookean_refuses_mismatched_moduli():
    F = hard_F(12, seed=1)
    with pytest.raises(ValueError, match="neo_hookean_tau: mu and lam"):
        fused.neo_hookean_tau(F, torch.ones(12, dtype=f64), torch.ones((), dtype=f64), J_MIN)


def test_neo_hookean_elasticity_takes_the_fused_path_and_learns_E_and_nu_through_it(monkeypatch):
    """The PAC-NeRF-style elastic row's law (learnable E and nu) and the elastomer's ground truth go through the
    fused kernels by default; the torch reference gives the same gradients of log E and nu."""
    assert CATEGORY_LAWS["elastic"]["elasticity"] == "neo_hookean"
    F = hard_F(30, seed=8)
    law = NeoHookeanElasticity(E=1e5, nu=0.3, learnable=True).double()
    params = [p for p in law.parameters() if p.requires_grad]
    assert params
    grads = []
    for fast in (True, False):
        law.fast_path = fast
        law.zero_grad()
        (law(F) ** 2).sum().backward()
        grads.append([p.grad.clone() for p in params])
    for a, b in zip(*grads):
        assert float(b.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-10, atol=0)
    calls, apply = [], fused._NeoHookean.apply
    monkeypatch.setattr(fused._NeoHookean, "apply", lambda *a: calls.append(1) or apply(*a))
    for fast in (True, False):  # the fused Function runs on the fast path only
        law.fast_path = fast
        law(F)
    assert calls == [1]


@pytest.mark.parametrize("fn", [lambda F, mu, lam: fused.neo_hookean_tau(F, mu, lam, J_MIN), fused.corotated_tau],
                         ids=["neo_hookean", "corotated"])
@pytest.mark.parametrize("shape", [(), (0,)])
def test_fused_laws_take_an_empty_batch(fn, shape):
    """No particle (a composite part left empty): an empty stress, and gradients of the moduli's own shape (review:
    per-particle moduli of shape [0] were summed to [1])."""
    F = torch.zeros(0, 3, 3, dtype=f64, requires_grad=True)
    mu, lam = (torch.ones(shape, dtype=f64, requires_grad=True) for _ in range(2))
    tau = fn(F, mu, lam)
    assert tau.shape == (0, 3, 3)
    v_F, v_mu, v_lam = torch.autograd.grad(tau.sum(), [F, mu, lam], allow_unused=True)
    assert v_F.shape == (0, 3, 3) and v_mu.shape == shape and v_lam.shape == shape
    assert float(v_mu.abs().sum()) == 0.0 and float(v_lam.abs().sum()) == 0.0
