"""Neural elasticity/plasticity: zero at rest, objectivity, gradients, input checks."""

import pytest
import torch

from gca.laws.base import Elasticity, Plasticity
from gca.laws.lora import apply_lora
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity, invariant_features
from gca.laws.svd import svd


def random_F(n, seed, dtype=torch.float64, spread=0.2):
    """Deformation gradients I + spread * noise (det > 0 for spread <= 0.2)."""
    g = torch.Generator().manual_seed(seed)
    return torch.eye(3, dtype=dtype) + spread * (2 * torch.rand(n, 3, 3, generator=g, dtype=dtype) - 1)


def random_rotations(n, seed, dtype=torch.float64):
    """Uniform rotations from QR of Gaussian matrices, det fixed to +1."""
    g = torch.Generator().manual_seed(seed)
    Q, R = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=dtype))
    Q = Q * torch.sign(torch.diagonal(R, dim1=1, dim2=2))[:, None, :]
    Q[torch.det(Q) < 0, :, 0] *= -1
    return Q


def eye(n, dtype=torch.float64):
    return torch.eye(3, dtype=dtype).expand(n, 3, 3).clone()


def scramble(law, seed, steps=5):
    """A few Adam steps on a random regression target, so the weights are no longer the init."""
    g = torch.Generator().manual_seed(seed)
    params = [p for p in law.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=0.05)
    F = random_F(32, seed + 1)
    target = torch.randn(32, 3, 3, generator=g, dtype=torch.float64)
    for _ in range(steps):
        opt.zero_grad()
        ((law(F) - target) ** 2).mean().backward()
        opt.step()
    return law


def test_interface_and_shapes():
    E, P = NeuralElasticity(), NeuralPlasticity()
    assert isinstance(E, Elasticity) and isinstance(P, Plasticity)
    F = random_F(7, 0, torch.float32)
    assert E(F).shape == (7, 3, 3) and P(F).shape == (7, 3, 3)
    assert sum(p.numel() for p in E.parameters()) == 13 * 64 + 64 * 64 + 64 * 9  # 5,504 as NCLaw


def test_features_zero_at_rest_and_hand_values():
    F = torch.diag(torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64))[None]
    _, sigma, _ = svd(F)
    z = invariant_features(F, sigma)
    # hand values: sigma - 1 = (1, 0, -0.5) (sorted desc), F^T F - I = diag(3, 0, -0.75), det - 1 = 0
    expected = torch.tensor([1, 0, -0.5, 3, 0, 0, 0, 0, 0, 0, 0, -0.75, 0], dtype=torch.float64)
    torch.testing.assert_close(z[0], expected)
    _, sigma_I, _ = svd(eye(2))
    assert torch.equal(invariant_features(eye(2), sigma_I), torch.zeros(2, 13, dtype=torch.float64))


@pytest.mark.parametrize("lora", [False, True])
def test_zero_at_rest_after_training(lora):
    torch.manual_seed(0)
    E, P = NeuralElasticity().double(), NeuralPlasticity().double()
    if lora:
        E, P = apply_lora(E, 4, 4.0), apply_lora(P, 4, 4.0)
    E, P = scramble(E, 1), scramble(P, 2)
    assert E(random_F(4, 3)).abs().max() > 0  # the networks are not trivially zero
    assert torch.equal(E(eye(5)), torch.zeros(5, 3, 3, dtype=torch.float64))
    assert torch.equal(P(eye(5)), eye(5))


def test_objectivity_float64():
    torch.manual_seed(1)
    E, P = scramble(NeuralElasticity().double(), 3), scramble(NeuralPlasticity().double(), 4)
    F, Q = random_F(64, 5), random_rotations(64, 6)
    tau, tau_rot = E(F), E(Q @ F)
    torch.testing.assert_close(tau_rot, Q @ tau @ Q.transpose(1, 2), rtol=1e-10, atol=1e-8)
    torch.testing.assert_close(P(Q @ F), Q @ P(F), rtol=1e-10, atol=1e-12)
    # negative control: a stress that is not rotated (tau(QF) vs tau(F)) must differ
    assert (tau_rot - tau).abs().max() > 1e-3 * tau.abs().max()


def test_stress_scale_is_linear_and_alpha_residual():
    cfg_a, cfg_b = NeuralLawConfig(stress_scale=1.0), NeuralLawConfig(stress_scale=250.0, alpha=0.5)
    torch.manual_seed(2)
    E_a = NeuralElasticity(cfg_a).double()
    E_b = NeuralElasticity(cfg_b).double()
    E_b.load_state_dict(E_a.state_dict())
    F = random_F(8, 7)
    torch.testing.assert_close(E_b(F), 250.0 * E_a(F), rtol=1e-12, atol=0)
    P_a, P_b = NeuralPlasticity(NeuralLawConfig(alpha=1.0)).double(), NeuralPlasticity(cfg_b).double()
    P_b.load_state_dict(P_a.state_dict())
    torch.testing.assert_close(P_b(F) - F, 0.5 * (P_a(F) - F), rtol=1e-12, atol=1e-15)


def test_first_piola_has_polar_form():
    # tau = P F^T with P = s R S: R^T tau F^{-T} / s must be symmetric (the symmetrised network output).
    E = scramble(NeuralElasticity().double(), 8)
    F = random_F(16, 9)
    U, _, Vh = svd(F)
    R = U @ Vh
    S = R.transpose(1, 2) @ E(F) @ torch.linalg.inv(F.transpose(1, 2)) / E.cfg.stress_scale
    torch.testing.assert_close(S, S.transpose(1, 2), rtol=1e-9, atol=1e-12)


class _WrongGrad(torch.autograd.Function):
    """Identity forward, gradient scaled by 1.01: a deliberately wrong backward (negative control)."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, v_x):
        return 1.01 * v_x


@pytest.mark.grad
def test_gradcheck_float64_with_negative_control():
    cfg = NeuralLawConfig(widths=(16, 16), stress_scale=1.0)
    E, P = scramble(NeuralElasticity(cfg).double(), 10), NeuralPlasticity(cfg).double()
    F = random_F(2, 11).requires_grad_(True)
    check = dict(eps=1e-6, atol=1e-6, fast_mode=True)
    assert torch.autograd.gradcheck(E, (F,), **check)
    assert torch.autograd.gradcheck(P, (F,), **check)
    assert not torch.autograd.gradcheck(lambda x: E(_WrongGrad.apply(x)), (F,), raise_exception=False, **check)


def test_gradients_finite_at_rest():
    E, P = scramble(NeuralElasticity().double(), 12), scramble(NeuralPlasticity().double(), 13)
    F = eye(4).requires_grad_(True)
    g = torch.Generator().manual_seed(14)
    v_tau = torch.randn(4, 3, 3, generator=g, dtype=torch.float64)
    ((E(F) * v_tau).sum() + (P(F) * v_tau).sum()).backward()
    assert torch.isfinite(F.grad).all() and F.grad.abs().max() > 0
    for p in list(E.parameters()) + list(P.parameters()):
        assert p.grad is None or torch.isfinite(p.grad).all()


def test_bad_input_errors():
    E = NeuralElasticity()
    with pytest.raises(ValueError, match="NeuralElasticity.*\\[N, 3, 3\\]"):
        E(torch.zeros(3, 3))
    with pytest.raises(TypeError, match="float64"):
        E(eye(2))  # network is float32
    with pytest.raises(ValueError, match="activation"):
        NeuralLawConfig(activation="softplus")  # softplus(0) != 0 would break zero-at-rest
    with pytest.raises(ValueError, match="widths"):
        NeuralLawConfig(widths=(64, 0))
    assert NeuralLawConfig(widths=[32, 16]).widths == (32, 16)  # YAML lists become tuples
