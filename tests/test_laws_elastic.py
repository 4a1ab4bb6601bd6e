"""Elastic laws: zero at rest, objectivity, hand-derived uniaxial/shear values, float64 gradchecks."""

import math

import pytest
import torch
from torch.autograd import gradcheck

from gca.laws.base import lame
from gca.laws.elastic import corotated_tau, sigma_tau, stvk_tau, volume_tau
from gca.laws.ood import neo_hookean_tau

f64 = torch.float64
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from fixtures3x3 import random_rotations  # noqa: E402
from fixtures3x3 import random_F as _random_F  # noqa: E402


def random_F(n, seed, spread=0.25, dtype=f64):
    return _random_F(n, seed, spread, dtype)
MU, LAM = 4.0e4, 3.0e4  # Pa (hand values below use these)
LAWS = {
    "corotated": lambda F, mu, lam: corotated_tau(F, mu, lam),
    "stvk": lambda F, mu, lam: stvk_tau(F, mu, lam),
    "volume": lambda F, mu, lam: volume_tau(F, lam),
    "sigma": lambda F, mu, lam: sigma_tau(F, mu, lam),
    "neo_hookean": lambda F, mu, lam: neo_hookean_tau(F, mu, lam),
}






def uniaxial(s):
    return torch.diag(torch.tensor([s, 1.0, 1.0], dtype=f64))[None]


def shear(g):
    F = torch.eye(3, dtype=f64)[None].clone()
    F[0, 0, 1] = g
    return F


def test_lame_hand_values():
    mu, lam = lame(1e5, 0.2)  # NCLaw jelly: mu = 4.167e4, lam = 2.778e4
    assert mu == pytest.approx(1e5 / 2.4) and lam == pytest.approx(2e4 / 0.72)
    with pytest.raises(ValueError, match="Poisson"):
        lame(1e5, 0.5)


@pytest.mark.parametrize("name", LAWS)
@pytest.mark.parametrize("dtype", [torch.float32, f64])
def test_zero_stress_at_rest(name, dtype):
    tau = LAWS[name](torch.eye(3, dtype=dtype).repeat(4, 1, 1), MU, LAM)
    assert tau.dtype == dtype
    assert tau.abs().max() <= (1e-2 if dtype == torch.float32 else 1e-9)  # Pa, moduli ~ 1e4


@pytest.mark.parametrize("name", LAWS)
def test_objectivity(name):
    F, Q = random_F(32, 0), random_rotations(32, 1)
    law = LAWS[name]
    torch.testing.assert_close(law(Q @ F, MU, LAM), Q @ law(F, MU, LAM) @ Q.transpose(1, 2), atol=1e-7, rtol=1e-9)


@pytest.mark.parametrize("name", LAWS)
def test_symmetric_stress(name):
    tau = LAWS[name](random_F(16, 2), MU, LAM)
    torch.testing.assert_close(tau, tau.transpose(1, 2), atol=1e-8, rtol=1e-10)


def _uniaxial_expected(name, s):
    """tau = diag(xx, yy, yy) of F = diag(s, 1, 1), derived by hand per law (J = s, R = I)."""
    log_s = math.log(s)
    return {
        "corotated": (2 * MU * (s - 1) * s + LAM * s * (s - 1), LAM * s * (s - 1)),
        "stvk": (s * s * (2 * MU + LAM) * (s * s - 1) / 2, LAM * (s * s - 1) / 2),
        "volume": (LAM * s * (s - 1), LAM * s * (s - 1)),
        "sigma": ((2 * MU + LAM) * log_s, LAM * log_s),
        "neo_hookean": (MU * (s * s - 1) + LAM * log_s, LAM * log_s),
    }[name]


@pytest.mark.parametrize("name", LAWS)
@pytest.mark.parametrize("s", [0.8, 1.3])
def test_uniaxial_stretch_closed_form(name, s):
    xx, yy = _uniaxial_expected(name, s)
    expected = torch.diag(torch.tensor([xx, yy, yy], dtype=f64))[None]
    torch.testing.assert_close(LAWS[name](uniaxial(s), MU, LAM), expected, atol=1e-8, rtol=1e-10)


def _shear_expected(name, g):
    """(xx, yy, zz, xy) of tau for simple shear F = I + g e_x e_y^T (J = 1), derived by hand."""
    if name == "corotated":  # R = rotation by theta about z, tan(theta) = g/2
        c = 1 / math.sqrt(1 + g * g / 4)
        s = g / 2 * c
        return 2 * MU * (1 - c + g * g - g * s), 2 * MU * (1 - c), 0.0, 2 * MU * (g - s)
    if name == "stvk":  # S = [[lam g^2/2, mu g], [mu g, mu g^2 + lam g^2/2]], tau = F S F^T
        h = LAM * g * g / 2
        return h + 2 * MU * g * g + MU * g ** 4 + LAM * g ** 4 / 2, MU * g * g + h, h, MU * g + MU * g ** 3 + LAM * g ** 3 / 2
    if name == "volume":
        return 0.0, 0.0, 0.0, 0.0
    if name == "sigma":  # tau = mu log(F F^T); 2x2 spectral projectors, log lambda_+ = 2 asinh(g/2)
        L, r = 2 * math.asinh(g / 2), math.sqrt(4 + g * g)
        return MU * L * g / r, -MU * L * g / r, 0.0, 2 * MU * L / r
    return MU * g * g, 0.0, 0.0, MU * g  # neo_hookean: mu (F F^T - I)


@pytest.mark.parametrize("name", LAWS)
@pytest.mark.parametrize("g", [0.1, 0.6])
def test_simple_shear_closed_form(name, g):
    xx, yy, zz, xy = _shear_expected(name, g)
    expected = torch.tensor([[xx, xy, 0], [xy, yy, 0], [0, 0, zz]], dtype=f64)[None]
    torch.testing.assert_close(LAWS[name](shear(g), MU, LAM), expected, atol=1e-7, rtol=1e-10)


def test_small_strain_limit_is_linear_elasticity():
    """All laws agree with Hooke's law 2 mu eps + lam tr(eps) I for a small symmetric strain."""
    g = torch.Generator().manual_seed(3)
    eps = 1e-6 * torch.randn(1, 3, 3, generator=g, dtype=f64)
    eps = 0.5 * (eps + eps.transpose(1, 2))
    hooke = 2 * MU * eps + LAM * torch.diagonal(eps, dim1=1, dim2=2).sum() * torch.eye(3, dtype=f64)
    for name in ("corotated", "stvk", "sigma", "neo_hookean"):
        tau = LAWS[name](torch.eye(3, dtype=f64) + eps, MU, LAM)
        torch.testing.assert_close(tau, hooke, atol=1e-4 * hooke.abs().max().item(), rtol=0)  # O(strain) relative


def test_per_particle_moduli_broadcast():
    F = random_F(5, 4)
    mus, lams = torch.linspace(1e4, 5e4, 5, dtype=f64), torch.linspace(2e4, 3e4, 5, dtype=f64)
    for name, law in LAWS.items():
        batched = law(F, mus, lams)
        single = torch.cat([law(F[i:i + 1], mus[i].item(), lams[i].item()) for i in range(5)])
        torch.testing.assert_close(batched, single, atol=1e-8, rtol=1e-10)
    with pytest.raises(ValueError, match=r"shape \[N=5\]"):
        corotated_tau(F, torch.ones(3), 1.0)


@pytest.mark.grad
@pytest.mark.parametrize("name", LAWS)
@pytest.mark.parametrize("where", ["generic", "rest", "uniaxial"])
def test_gradcheck_F_and_moduli(name, where):
    """Moduli of order 1 so gradcheck's absolute tolerance is meaningful; exact at F = I too."""
    F = {"generic": random_F(3, 5), "rest": torch.eye(3, dtype=f64).repeat(2, 1, 1), "uniaxial": uniaxial(1.2)}[where]
    F = F.clone().requires_grad_(True)
    mu = torch.tensor(1.3, dtype=f64, requires_grad=True)
    lam = torch.tensor(0.7, dtype=f64, requires_grad=True)
    assert gradcheck(LAWS[name], (F, mu, lam))


def test_guards_give_finite_stress_for_inverted_F():
    F = torch.diag(torch.tensor([1.0, 1.0, -0.5], dtype=f64))[None].requires_grad_(True)
    for name in ("sigma", "neo_hookean", "corotated"):
        tau = LAWS[name](F, MU, LAM)
        (v_F,) = torch.autograd.grad(tau.sum(), F)
        assert torch.isfinite(tau).all() and torch.isfinite(v_F).all(), name
    assert sigma_tau(F.detach(), MU, LAM)[0, 2, 2] < 0  # clamped log(0.05): restoring pressure
