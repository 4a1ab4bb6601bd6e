"""Plastic return maps: identity at rest / inside yield, yield-surface landing, objectivity, gradchecks."""

import math

import pytest
import torch
from torch.autograd import gradcheck

from gca.laws.ood import viscoplastic_plastic
from gca.laws.plastic import (drucker_prager_alpha, drucker_prager_plastic, identity_plastic, sigma_plastic,
                              von_mises_plastic)
from gca.laws.svd import det3, polar_rotation, svd

f64 = torch.float64
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from fixtures3x3 import random_rotations  # noqa: E402
from fixtures3x3 import random_F  # noqa: E402
MU, LAM = 1.2e5, 1.2e5  # NCLaw plasticine moduli (E = 3e5, nu = 0.25) [Pa]
SIGMA_Y = 5e3  # [Pa]; yield strain sigma_y / (2 mu) = 0.0208
PHI = 25.0  # [deg]
ETA, N_FLOW, DT = 50.0, 0.7, 5e-4  # [Pa s^n], [1], [s]
LAWS = {
    "identity": lambda F: identity_plastic(F),
    "sigma": lambda F: sigma_plastic(F),
    "von_mises": lambda F: von_mises_plastic(F, MU, SIGMA_Y),
    "drucker_prager": lambda F: drucker_prager_plastic(F, MU, LAM, PHI),
    "viscoplastic": lambda F: viscoplastic_plastic(F, MU, SIGMA_Y, ETA, N_FLOW, DT),
}






def hencky(F):
    """(tr eps [N], dev eps [N,3]) of F's signed singular values."""
    eps = torch.log(svd(F)[1])
    tr = eps.sum(-1)
    return tr, eps - tr[:, None] / 3


@pytest.mark.parametrize("name", LAWS)
@pytest.mark.parametrize("dtype", [torch.float32, f64])
def test_rest_state_is_fixed(name, dtype):
    I = torch.eye(3, dtype=dtype).repeat(3, 1, 1)
    out = LAWS[name](I)
    assert out.dtype == dtype
    torch.testing.assert_close(out, I, atol=1e-6 if dtype == torch.float32 else 1e-12, rtol=0)


def test_identity_returns_F_itself():
    F = random_F(4, 0)
    assert identity_plastic(F) is F


@pytest.mark.parametrize("name", ["von_mises", "viscoplastic"])
def test_inside_yield_unchanged_exactly(name):
    Q, Q2 = random_rotations(8, 1), random_rotations(8, 2)
    stretch = torch.diag_embed(torch.tensor([1.01, 0.995, 1.0], dtype=f64).expand(8, 3))  # ||dev eps|| ~ 0.01
    F = Q @ stretch @ Q2
    assert torch.equal(LAWS[name](F), F)


def test_drucker_prager_inside_cone_unchanged_exactly():
    F = torch.diag_embed(torch.tensor([[0.9, 0.91, 0.9], [0.95, 0.95, 0.96]], dtype=f64))  # compressed, tiny shear
    assert torch.equal(drucker_prager_plastic(F, MU, LAM, PHI), F)


@pytest.mark.parametrize("name", LAWS)
def test_objectivity(name):
    F, Q = random_F(32, 3), random_rotations(32, 4)
    law = LAWS[name]
    expected = law(F) if name == "sigma" else Q @ law(F)  # the fluid projection forgets rotation: J^(1/3) I
    torch.testing.assert_close(law(Q @ F), expected, atol=1e-10, rtol=1e-10)


def test_von_mises_lands_on_yield_surface():
    F = random_F(64, 5, spread=0.5)
    F = F[det3(F) > 0.2]
    tr0, dev0 = hencky(F)
    tr1, dev1 = hencky(von_mises_plastic(F, MU, SIGMA_Y))
    k = SIGMA_Y / (2 * MU)
    assert bool((dev0.norm(dim=-1) > 3 * k).all())  # all far outside
    torch.testing.assert_close(dev1.norm(dim=-1), torch.full_like(tr0, k), atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(tr1, tr0, atol=1e-10, rtol=1e-10)  # volume-preserving flow
    torch.testing.assert_close(dev1 / k, dev0 / dev0.norm(dim=-1, keepdim=True), atol=1e-8, rtol=1e-8)  # radial


def test_von_mises_uniaxial_hand_value():
    """F = diag(1.5, 1, 1): eps = (log 1.5, 0, 0), tr = log 1.5, dev direction (2, -1, -1)/sqrt(6)."""
    k = SIGMA_Y / (2 * MU)
    t = math.log(1.5)
    d = torch.tensor([2.0, -1.0, -1.0], dtype=f64) / math.sqrt(6)
    expected = torch.diag(torch.exp(t / 3 + k * d))[None]
    F = torch.diag(torch.tensor([1.5, 1.0, 1.0], dtype=f64))[None]
    torch.testing.assert_close(von_mises_plastic(F, MU, SIGMA_Y), expected, atol=1e-12, rtol=1e-12)


def test_drucker_prager_alpha_hand_value():
    assert float(drucker_prager_alpha(25.0)) == pytest.approx(0.2678, abs=1e-4)  # NCLaw sand (reference notes)


def test_drucker_prager_projects_onto_cone():
    g = torch.Generator().manual_seed(6)
    F = 0.85 * torch.eye(3, dtype=f64) + 0.15 * torch.randn(64, 3, 3, generator=g, dtype=f64)
    tr0, dev0 = hencky(F)
    slope = float(drucker_prager_alpha(PHI)) * (3 * LAM + 2 * MU) / (2 * MU)
    outside = (tr0 < 0) & (dev0.norm(dim=-1) + slope * tr0 > 1e-3)
    assert int(outside.sum()) >= 8
    tr1, dev1 = hencky(drucker_prager_plastic(F[outside], MU, LAM, PHI))
    torch.testing.assert_close(dev1.norm(dim=-1), -slope * tr0[outside], atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(tr1, tr0[outside], atol=1e-10, rtol=1e-10)


def test_drucker_prager_tension_goes_to_apex():
    F = random_F(16, 7, spread=0.1) * 1.2  # expanded: tr eps > 0
    torch.testing.assert_close(drucker_prager_plastic(F, MU, LAM, PHI), polar_rotation(F), atol=1e-12, rtol=0)
    c = 0.01  # cohesion shifts the apex to exp(c) R
    torch.testing.assert_close(drucker_prager_plastic(F, MU, LAM, PHI, c), math.exp(c) * polar_rotation(F),
                               atol=1e-12, rtol=0)


def test_sigma_plastic_keeps_volume_drops_shear():
    F = random_F(16, 8, spread=0.2)
    F = F[det3(F) > 0]
    F_e = sigma_plastic(F)
    torch.testing.assert_close(det3(F_e), det3(F), atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(F_e, det3(F).pow(1 / 3)[:, None, None] * torch.eye(3, dtype=f64).expand_as(F))


def test_viscoplastic_between_elastic_and_von_mises():
    F = torch.diag(torch.tensor([1.3, 1.0, 0.9], dtype=f64))[None]
    k = SIGMA_Y / (2 * MU)
    n0 = hencky(F)[1].norm()
    norms = [hencky(viscoplastic_plastic(F, MU, SIGMA_Y, ETA, N_FLOW, dt))[1].norm() for dt in (1e-6, 1e-5, 1e-4)]
    assert n0 > norms[0] > norms[1] > norms[2] > k  # relaxes monotonically with dt, never past the surface
    torch.testing.assert_close(viscoplastic_plastic(F, MU, SIGMA_Y, ETA, N_FLOW, 1.0), von_mises_plastic(F, MU, SIGMA_Y))


def test_viscoplastic_bingham_hand_value():
    """n = 1: d_gamma = dt * 2 mu (||dev|| - k) / eta along the deviator."""
    F = torch.diag(torch.tensor([1.3, 1.0, 0.9], dtype=f64))[None]
    k, dt, eta = SIGMA_Y / (2 * MU), 1e-6, 10.0
    tr0, dev0 = hencky(F)
    n0 = dev0.norm()
    d_gamma = dt * 2 * MU * (n0 - k) / eta
    tr1, dev1 = hencky(viscoplastic_plastic(F, MU, SIGMA_Y, eta, 1.0, dt))
    torch.testing.assert_close(dev1.norm(), n0 - d_gamma, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(tr1, tr0, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="dt > 0"):
        viscoplastic_plastic(F, MU, SIGMA_Y, eta, 1.0, 0.0)


@pytest.mark.grad
@pytest.mark.parametrize("where", ["generic", "uniaxial"])
def test_gradcheck_plastic_laws(where):
    """Parameters scaled to order 1 (mu = 1: yield strain sigma_y / 2); uniaxial F repeats two singular values."""
    F = random_F(3, 9) if where == "generic" else torch.diag(torch.tensor([1.8, 1.0, 1.0], dtype=f64))[None]
    F = F.clone().requires_grad_(True)
    mu, lam, sy = (torch.tensor(v, dtype=f64, requires_grad=True) for v in (1.0, 0.8, 0.2))
    assert gradcheck(lambda F, mu, sy: von_mises_plastic(F, mu, sy), (F, mu, sy))
    assert gradcheck(sigma_plastic, (F,))
    eta, n = (torch.tensor(v, dtype=f64, requires_grad=True) for v in (3.0, 0.7))
    assert gradcheck(lambda F, mu, sy, eta, n: viscoplastic_plastic(F, mu, sy, eta, n, 0.02), (F, mu, sy, eta, n))
    phi = torch.tensor(30.0, dtype=f64, requires_grad=True)
    Fc = (0.7 * F).detach().requires_grad_(True)  # compressed: the cone branch
    assert gradcheck(lambda F, mu, lam, phi: drucker_prager_plastic(F, mu, lam, phi), (Fc, mu, lam, phi))


@pytest.mark.parametrize("name", LAWS)
def test_finite_gradients_at_rest(name):
    F = torch.eye(3, dtype=f64).repeat(2, 1, 1).requires_grad_(True)
    W = torch.randn(2, 3, 3, generator=torch.Generator().manual_seed(10), dtype=f64)
    out = LAWS[name](F)
    if not out.requires_grad:  # identity returns F itself
        out = out * 1.0
    (v_F,) = torch.autograd.grad((out * W).sum(), F)
    assert torch.isfinite(v_F).all()
    if name in ("identity", "von_mises", "viscoplastic"):  # inside yield at rest: exact identity gradient
        torch.testing.assert_close(v_F, W)
