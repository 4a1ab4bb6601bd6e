"""gca.align.cpr: parameter recovery, credibility weights, target removal, gradients, divergence."""

import dataclasses

import pytest
import torch

from gca.align.cpr import (CPR, ELASTIC_PARAMS, CPRConfig, elastic_tau, relative_variance,
                           solve_linear_groups)
from gca.config import ConfigError, build
from gca.laws.base import lame
from gca.laws.elastic import corotated_tau, sigma_tau, stvk_tau, volume_tau
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity
from gca.laws.plastic import drucker_prager_plastic, identity_plastic, von_mises_plastic

from test_laws_neural import scramble

N = 320
MU, LAM = lame(1e5, 0.2)  # NCLaw jelly: mu = 4.167e4 Pa, lam = 2.778e4 Pa
ELASTIC_ONLY = CPRConfig(plastic=())
LAWS = {"corotated": corotated_tau, "stvk": stvk_tau, "sigma": sigma_tau}


class FixedLaw(torch.nn.Module):
    """A 'neural' law that is an analytic law with fixed parameters (forward(F) -> law(F, *args))."""

    def __init__(self, law, *args, scale=None):
        super().__init__()
        self.law, self.args = law, args
        self.scale = None if scale is None else torch.nn.Parameter(torch.tensor(scale, dtype=torch.float64))

    def forward(self, F):
        out = self.law(F, *self.args)
        return out if self.scale is None else self.scale * out


def _deformations(seed=0, n=N, amplitude=0.06, dtype=torch.float32):
    """Random general deformation gradients near I (stretch, shear and rotation, det > 0)."""
    g = torch.Generator().manual_seed(seed)
    return (torch.eye(3, dtype=torch.float64) + amplitude * torch.randn(n, 3, 3, generator=g,
                                                                        dtype=torch.float64)).to(dtype)


# ---------------------------------------------------------------- config and subset
def test_config_validation_and_build():
    cfg = build(CPRConfig, {"subset_size": 64, "elastic": ["corotated", "sigma"], "plastic": []}, "align.cpr",
                partial=True)
    assert cfg.elastic == ("corotated", "sigma") and cfg.plastic == ()
    with pytest.raises(ValueError, match="unknown hypotheses"):
        CPRConfig(elastic=("neo_hookean",))
    with pytest.raises(ConfigError, match="unknown keys"):
        build(CPRConfig, {"subset": 3})
    with pytest.raises(ConfigError, match="^params: missing key align.cpr.n_groups "):  # params must give every key
        build(CPRConfig, {"subset_size": 64, "elastic": ["corotated", "sigma"], "plastic": []}, "align.cpr")


def test_subset_is_fixed_seeded_and_split_into_groups():
    a, b, c = CPR(CPRConfig(), 1000, seed=1), CPR(CPRConfig(), 1000, seed=1), CPR(CPRConfig(), 1000, seed=2)
    assert torch.equal(a.subset, b.subset) and not torch.equal(a.subset, c.subset)
    assert len(a.subset) == 256 and len(set(a.subset.tolist())) == 256 and int(a.subset.max()) < 1000
    assert torch.bincount(a.group_ids).tolist() == [32] * 8
    assert len(CPR(CPRConfig(), 100, seed=0).subset) == 100  # N < |S|: all particles


# ---------------------------------------------------------------- solvers
def test_hypotheses_are_linear_in_their_parameters():
    """CPR's closed-form fit assumes H(F; mu, lam) = mu H(F; 1, 0) + lam H(F; 0, 1)."""
    F = _deformations(dtype=torch.float64)[:32]
    for name, params in ELASTIC_PARAMS.items():
        theta = [MU, LAM][-len(params):]
        units = torch.eye(len(params), dtype=torch.float64)
        combo = sum(t * elastic_tau(name, F, u.tolist()) for t, u in zip(theta, units))
        torch.testing.assert_close(elastic_tau(name, F, theta), combo, rtol=1e-10, atol=1e-6)


def test_linear_solver_and_relative_variance_hand_values():
    basis = torch.randn(2, 8, 3, 3, dtype=torch.float64)
    target = 3.0 * basis[0] - 2.0 * basis[1]
    theta = solve_linear_groups(basis, target, torch.arange(8) % 2, 2)
    torch.testing.assert_close(theta, torch.tensor([[3.0, -2.0], [3.0, -2.0]], dtype=torch.float64))
    # groups (1, 0) and (3, 0): var = 1, mean^2 = 4 -> 0.25
    assert float(relative_variance(torch.tensor([[1.0, 0.0], [3.0, 0.0]]))) == pytest.approx(0.25)
    assert float(relative_variance(torch.zeros(4, 0))) == 0.0


# ---------------------------------------------------------------- elastic recovery and weights
@pytest.mark.parametrize("name", ["corotated", "stvk", "sigma"])
def test_recovers_lame_and_gives_true_law_the_largest_weight(name):
    cpr = CPR(ELASTIC_ONLY, N, seed=0)
    F = _deformations()
    R_e, R_p, info = cpr.residuals(FixedLaw(LAWS[name], MU, LAM), identity_plastic, F, F)
    mu, lam = info["elastic"][name].theta.tolist()
    assert mu == pytest.approx(MU, rel=1e-2) and lam == pytest.approx(LAM, rel=1e-2)
    weights = {k: float(f.weight) for k, f in info["elastic"].items()}
    assert CPR.best(info["elastic"]) == name, weights
    assert weights[name] > 3 * max(w for k, w in weights.items() if k != name), weights
    assert weights[name] == pytest.approx(1 / ELASTIC_ONLY.eps, rel=1e-3)  # exact fit: Var = 0
    assert torch.isfinite(R_e) and float(R_p) == 0.0


def test_volume_law_weight_is_maximal():
    """A pure-pressure law is also exactly corotated/sigma with mu = 0: those tie, nothing beats it."""
    cpr = CPR(ELASTIC_ONLY, N, seed=0)
    F = _deformations()
    _, _, info = cpr.residuals(FixedLaw(volume_tau, LAM), identity_plastic, F, F)
    assert info["elastic"]["volume"].theta.item() == pytest.approx(LAM, rel=1e-2)
    assert float(info["elastic"]["volume"].weight) == pytest.approx(max(float(f.weight) for f in info["elastic"].values()))
    assert info["elastic"]["stvk"].weight < 0.5 / ELASTIC_ONLY.eps


def test_log_dict_reports_E_nu_and_weights():
    cpr = CPR(ELASTIC_ONLY, N, seed=0)
    F = _deformations()
    _, _, info = cpr.residuals(FixedLaw(corotated_tau, MU, LAM), identity_plastic, F, F)
    logged = CPR.log_dict(info)
    assert logged["cpr/e/corotated/E"] == pytest.approx(1e5, rel=1e-2)
    assert logged["cpr/e/corotated/nu"] == pytest.approx(0.2, rel=1e-2)
    assert {"cpr/e/volume/lam", "cpr/e/sigma/weight", "cpr/R_e", "cpr/R_p"} <= set(logged)
    assert all(isinstance(v, float) for v in logged.values())


def test_target_removed_changes_the_most_credible_law():
    F = _deformations()
    law = FixedLaw(corotated_tau, MU, LAM)
    R_full, _, full = CPR(ELASTIC_ONLY, N, seed=0).residuals(law, identity_plastic, F, F)
    removed_cfg = dataclasses.replace(ELASTIC_ONLY, elastic=("stvk", "volume", "sigma"))
    R_e, _, removed = CPR(removed_cfg, N, seed=0).residuals(law, identity_plastic, F, F)
    assert CPR.best(full["elastic"]) == "corotated"
    assert "corotated" not in removed["elastic"] and CPR.best(removed["elastic"]) in ("stvk", "sigma")
    assert max(f.weight for f in removed["elastic"].values()) < 0.5 / ELASTIC_ONLY.eps  # no exact fit left
    assert float(R_e) > 2 * float(R_full)  # the credible exact fit was what kept the residual small


def test_normalized_weights_stop_wrong_hypotheses_pulling_an_exact_law():
    """A law that is exactly corotated: with omega as written every wrong hypothesis pulls it away
    (grad of omega_k * misfit_k ~ grad log misfit_k); the credibility distribution omega / sum omega
    leaves it almost alone (the pull shrinks by sum_k omega_k, here > 50x)."""
    F = _deformations(dtype=torch.float64)
    grads = {}
    for weighting in ("raw", "normalized"):
        law = FixedLaw(corotated_tau, MU, LAM, scale=1.0)
        R_e, _, info = CPR(dataclasses.replace(ELASTIC_ONLY, weighting=weighting), N, 0).residuals(
            law, identity_plastic, F, F)
        (grads[weighting],) = torch.autograd.grad(R_e, law.scale)
        total_weight = sum(float(f.weight) for f in info["elastic"].values())
    assert float(grads["raw"].abs()) > 50 * float(grads["normalized"].abs()) > 0
    assert float(grads["raw"] / grads["normalized"]) == pytest.approx(total_weight, rel=1e-6)


def test_residual_is_scale_free():
    """Stresses x1000 (kPa -> MPa range) leave R_e and the weights unchanged (normalised residuals)."""
    F = _deformations()
    _, _, a = CPR(ELASTIC_ONLY, N, 0).residuals(FixedLaw(sigma_tau, MU, LAM), identity_plastic, F, F)
    _, _, b = CPR(ELASTIC_ONLY, N, 0).residuals(FixedLaw(sigma_tau, 1e3 * MU, 1e3 * LAM), identity_plastic, F, F)
    assert float(a["R_e"]) == pytest.approx(float(b["R_e"]), rel=1e-4)
    for k in a["elastic"]:
        assert float(a["elastic"][k].weight) == pytest.approx(float(b["elastic"][k].weight), rel=1e-4)


def test_a_frame_at_rest_does_not_dominate():
    """A free-flight frame (|F - I| ~ 1e-7, stresses ~0.01 Pa) beside a deformed one: with the stress floor
    its misfit counts in Pa, not relative to its own vanishing stress (which gave R_e ~ 2e3 on the paper
    bottle's prior). R_e of [rest, deformed] ~ R_e of the deformed frame alone; without the floor the rest
    frame weighs as much as a deformed one (a relative misfit of order 1 of pure round-off)."""
    torch.manual_seed(0)
    law = NeuralElasticity(NeuralLawConfig(widths=(16, 16), stress_scale=1e4))
    rest, moved = _deformations(seed=5, amplitude=1e-7), _deformations(seed=6, amplitude=0.05)

    def R_e(cfg, *frames):
        F = torch.stack(frames)
        return float(CPR(cfg, N, 0).residuals_frames(law, identity_plastic, F, F)[0].detach())

    floored, bare = ELASTIC_ONLY, dataclasses.replace(ELASTIC_ONLY, stress_floor=1e-12, strain_floor=1e-12)
    assert R_e(floored, rest, moved) == pytest.approx(R_e(floored, moved), rel=1e-3)
    assert R_e(bare, rest) > 0.5 * R_e(bare, moved) > 0


# ---------------------------------------------------------------- plastic recovery
def test_von_mises_yield_strain_recovered():
    mu_p, sigma_y = lame(3e5, 0.25)[0], 5e3  # NCLaw plasticine: sigma_y / (2 mu) = 0.0208
    F_e = _deformations(seed=1)
    F_trial = _deformations(seed=2, amplitude=0.08)
    cpr = CPR(CPRConfig(plastic=("identity", "sigma", "von_mises")), N, seed=0)
    _, R_p, info = cpr.residuals(FixedLaw(sigma_tau, MU, LAM), FixedLaw(von_mises_plastic, mu_p, sigma_y),
                                 F_e, F_trial)
    k = info["plastic"]["von_mises"].theta.item()
    assert k == pytest.approx(sigma_y / (2 * mu_p), rel=3e-2)
    assert CPR.best(info["plastic"]) == "von_mises"
    assert info["plastic"]["identity"].weight < 0.2 * info["plastic"]["von_mises"].weight
    assert torch.isfinite(R_p)


def test_drucker_prager_friction_angle_recovered():
    mu, lam = lame(1e6, 0.2)  # NCLaw sand
    F_trial = _deformations(seed=3, amplitude=0.08)
    cpr = CPR(CPRConfig(plastic=("identity", "von_mises", "drucker_prager")), N, seed=0)
    _, _, info = cpr.residuals(FixedLaw(sigma_tau, mu, lam), FixedLaw(drucker_prager_plastic, mu, lam, 25.0),
                               F_trial, F_trial)
    assert float(info["lam_over_mu"]) == pytest.approx(lam / mu, rel=1e-2)  # from the elastic fit
    assert info["plastic"]["drucker_prager"].theta.item() == pytest.approx(25.0, abs=1.0)
    assert CPR.best(info["plastic"]) == "drucker_prager"


# ---------------------------------------------------------------- gradients
def test_gradient_reaches_every_neural_parameter():
    torch.manual_seed(0)
    ncfg = NeuralLawConfig(widths=(16, 16))
    elasticity, plasticity = NeuralElasticity(ncfg), NeuralPlasticity(ncfg)
    F_e, F_trial = _deformations(seed=4), _deformations(seed=5)
    R_e, R_p, _ = CPR(CPRConfig(grid_size=6, refine_rounds=1), N, 0).residuals(elasticity, plasticity, F_e, F_trial)
    (R_e + R_p).backward()
    for module in (elasticity, plasticity):
        for name, p in module.named_parameters():
            assert p.grad is not None and torch.isfinite(p.grad).all(), name
            assert p.grad.abs().max() > 0, name


def _frozen_residual(info, F, s, law):
    """R_e recomputed from the solved targets (theta, omega, scale held fixed), float64."""
    tau = s * law(F)
    total_weight = sum(f.weight for f in info["elastic"].values())  # weighting="normalized"
    return sum(f.weight / total_weight * (tau - elastic_tau(k, F, f.theta.tolist())).square().sum((-2, -1)).mean()
               for k, f in info["elastic"].items()) / info["scale_e"]


def test_gradient_is_the_frozen_target_gradient_fd_check():
    """dR_e/ds (autograd, targets detached) equals a float64 central difference of the frozen residual;
    negative control: the same tolerance rejects a 1 % wrong gradient."""
    F = _deformations(seed=6, dtype=torch.float64)
    base = lambda F: corotated_tau(F, MU, LAM) + sigma_tau(F, 0.3 * MU, 0.0)  # no hypothesis is exact
    law = FixedLaw(base, scale=1.3)
    R_e, _, info = CPR(ELASTIC_ONLY, N, 0).residuals(law, identity_plastic, F, F)
    (grad,) = torch.autograd.grad(R_e, law.scale)
    h = 1e-6
    fd = (_frozen_residual(info, F, 1.3 + h, base) - _frozen_residual(info, F, 1.3 - h, base)) / (2 * h)
    assert float(grad) != 0.0
    torch.testing.assert_close(grad, fd, rtol=1e-6, atol=0.0)
    with pytest.raises(AssertionError):
        torch.testing.assert_close(1.01 * grad, fd, rtol=1e-6, atol=0.0)


def test_refit_every_reuses_targets():
    F = _deformations()
    cpr = CPR(dataclasses.replace(ELASTIC_ONLY, refit_every=2), N, 0)
    _, _, first = cpr.residuals(FixedLaw(sigma_tau, MU, LAM), identity_plastic, F, F)
    weights = {k: float(f.weight) for k, f in first["elastic"].items()}
    _, _, second = cpr.residuals(FixedLaw(sigma_tau, 2 * MU, LAM), identity_plastic, F, F)
    assert first["refit"] and not second["refit"]
    assert {k: float(f.weight) for k, f in second["elastic"].items()} == weights
    _, _, third = cpr.residuals(FixedLaw(sigma_tau, 2 * MU, LAM), identity_plastic, F, F)
    assert third["refit"] and third["elastic"]["sigma"].theta[0].item() == pytest.approx(2 * MU, rel=1e-3)


# ---------------------------------------------------------------- divergence and bad input
def test_divergence_and_bad_input_raise():
    cpr = CPR(ELASTIC_ONLY, N, 0)
    F = _deformations()
    law = FixedLaw(corotated_tau, MU, LAM)
    F_bad = F.clone()
    F_bad[7, 1, 1] = float("nan")
    with pytest.raises(FloatingPointError, match="F_e has 1 of"):
        cpr.residuals(law, identity_plastic, F_bad, F)
    with pytest.raises(FloatingPointError, match="neural stress"):
        cpr.residuals(lambda F: law(F) * float("inf"), identity_plastic, F, F)
    with pytest.raises(ValueError, match="built for"):
        cpr.residuals(law, identity_plastic, F[:10], F[:10])
    with pytest.raises(ValueError, match=r"\[N, 3, 3\]"):
        cpr.residuals(law, identity_plastic, F[:, :2], F)


def test_weights_and_residual_follow_the_documented_formula():
    """On S (residual_on='subset'): omega = 1/(V_param + misfit + eps) and R_e = sum omega * misfit / sum
    omega (``weighting="raw"``: without the division); without the misfit term parameter-free
    hypotheses get the maximal weight 1/eps (the literal reading)."""
    F = _deformations()
    law = FixedLaw(lambda F: corotated_tau(F, MU, LAM) + sigma_tau(F, 0.3 * MU, 0.0))
    for weighting in ("normalized", "raw"):
        cfg = dataclasses.replace(ELASTIC_ONLY, residual_on="subset", weighting=weighting)
        R_e, _, info = CPR(cfg, N, 0).residuals(law, identity_plastic, F, F)
        fits = info["elastic"].values()
        for f in fits:
            assert float(f.weight) == pytest.approx(1.0 / (float(f.var_param) + float(f.fit_residual) + cfg.eps),
                                                    rel=1e-12)
        norm = sum(float(f.weight) for f in fits) if weighting == "normalized" else 1.0
        assert float(R_e) == pytest.approx(sum(float(f.weight * f.fit_residual) for f in fits) / norm, rel=1e-5)
    literal = CPRConfig(include_fit_residual=False, plastic=("identity", "sigma"), elastic=())
    _, _, info = CPR(literal, N, 0).residuals(law, FixedLaw(von_mises_plastic, MU, 1e3), F, _deformations(7))
    assert all(float(f.weight) == pytest.approx(1 / literal.eps) for f in info["plastic"].values())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_residuals_synchronise_with_the_host_once_on_cuda():
    """On a GPU a CPR call reads back one number set (the finiteness check): fits, weights and the
    plastic grid searches stay on the device (torch's sync debug mode counts the rest)."""
    import warnings

    F, Ftr = _deformations().cuda(), _deformations(7).cuda()
    elasticity = NeuralElasticity().cuda()
    plasticity = NeuralPlasticity().cuda()
    cpr = CPR(CPRConfig(), N, 0)
    cpr.residuals(elasticity, plasticity, F, Ftr)  # warm-up (warp module load, caches)
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            R_e, R_p, _ = cpr.residuals(elasticity, plasticity, F, Ftr)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    syncs = [w for w in caught if "called a synchronizing" in str(w.message).lower()]  # not the "prototype" note
    assert len(syncs) <= 1, [str(w.message) for w in syncs]
    assert torch.isfinite(R_e + R_p)


@pytest.mark.parametrize("refit_every, chunks", [(1, (7,)), (3, (4, 3)), (2, (1, 5, 1))])
def test_frames_in_one_call_equal_frame_by_frame(refit_every, chunks):
    """B frames in one batched call = B calls of ``residuals`` in order: the summed R_e, R_p, the
    gradients of the neural laws' parameters and the last frame's fits; split into several batched
    calls, the refit schedule (``refit_every``) carries over as in the frame-by-frame calls."""
    cfg = dataclasses.replace(CPRConfig(), refit_every=refit_every)
    torch.manual_seed(0)
    el = NeuralElasticity(NeuralLawConfig(widths=(16, 16), stress_scale=1e4)).double()
    pl = scramble(NeuralPlasticity(NeuralLawConfig(widths=(16, 16), alpha=0.3)).double(), seed=1)  # it yields
    params = [*el.parameters(), *pl.parameters()]
    F_e = torch.stack([_deformations(seed=s, dtype=torch.float64) for s in range(7)])
    # growing strain: each frame's grid search zooms to its own range
    F_tr = torch.stack([_deformations(seed=20 + s, amplitude=0.02 * (s + 1), dtype=torch.float64) for s in range(7)])

    serial = CPR(cfg, N, seed=3)
    R_e = R_p = 0.0
    for b in range(7):
        r_e, r_p, info_serial = serial.residuals(el, pl, F_e[b], F_tr[b])
        R_e, R_p = R_e + r_e, R_p + r_p
    g_serial = torch.autograd.grad(R_e + R_p, params)

    batched = CPR(cfg, N, seed=3)
    B_e = B_p = 0.0
    start = 0
    for size in chunks:
        r_e, r_p, info = batched.residuals_frames(el, pl, F_e[start:start + size], F_tr[start:start + size])
        B_e, B_p, start = B_e + r_e, B_p + r_p, start + size
    g_batched = torch.autograd.grad(B_e + B_p, params)

    torch.testing.assert_close(B_e, R_e, rtol=1e-10, atol=0)
    torch.testing.assert_close(B_p, R_p, rtol=1e-10, atol=0)
    assert float(R_e.detach()) > 0 and float(R_p.detach()) > 0
    yields = [float(info_serial['plastic']['von_mises'].theta[0]), float(info['plastic']['von_mises'].theta[0])]
    assert yields[0] < 0.5, yields  # a real yield strain was fitted, not the no-yield end of the range
    for a, b in zip(g_batched, g_serial):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-12 * float(b.abs().max()))
    assert info["refit"] == info_serial["refit"]
    for kind in ("elastic", "plastic"):
        for name, fit in info_serial[kind].items():
            for field in ("theta", "weight", "var_param", "fit_residual"):
                torch.testing.assert_close(getattr(info[kind][name], field), getattr(fit, field), rtol=1e-10, atol=1e-14)
