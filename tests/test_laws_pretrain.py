"""Law-level fitting of the neural laws to analytic ones, response error, wave-speed estimate."""

import math

import pytest
import torch

from gca.laws.elastic import CorotatedElasticity
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity
from gca.laws.plastic import VonMisesPlasticity
from gca.laws.pretrain import (DeformationSampling, PretrainConfig, fit_elasticity, fit_plasticity,
                               response_error, sample_deformations, sweep_deformations, sweep_response_error)
from gca.laws.svd import det3, polar_rotation, svd

SAMPLING = DeformationSampling(stretch=0.2, compression=0.2, rotation=math.pi)
FIT = PretrainConfig(sampling=SAMPLING, n_samples=2048, batch_size=256, steps=300, lr=1e-2, seed=0)


def held_out(n=512, sampling=SAMPLING):
    return sample_deformations(n, sampling, torch.Generator().manual_seed(99))


@pytest.fixture(scope="module")
def fitted_corotated():
    """Neural elasticity regressed onto corotated jelly (E = 1e5 Pa, nu = 0.2), CI-sized."""
    torch.manual_seed(0)
    reference = CorotatedElasticity(1e5, 0.2, learnable=False)
    law = NeuralElasticity(NeuralLawConfig(widths=(64, 64), stress_scale=1e4))
    history = fit_elasticity(law, reference, FIT)
    return law, reference, history


def test_sampling_respects_ranges_and_seed():
    cfg = DeformationSampling(stretch=0.3, compression=0.1, rotation=0.5)
    F = sample_deformations(400, cfg, torch.Generator().manual_seed(1), torch.float64)
    _, sigma, _ = svd(F)
    assert (det3(F) > 0).all()
    assert sigma.max() <= 1.3 + 1e-9 and sigma.min() >= 0.9 - 1e-9
    assert sigma.max() > 1.2 and sigma.min() < 0.95  # the ranges are actually used
    R = polar_rotation(F)
    angle = torch.arccos(((torch.diagonal(R, dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1))
    assert angle.max() <= 0.5 + 1e-6 and angle.max() > 0.4
    again = sample_deformations(400, cfg, torch.Generator().manual_seed(1), torch.float64)
    assert torch.equal(F, again)


def test_fit_elasticity_to_corotated(fitted_corotated):
    law, reference, history = fitted_corotated
    assert history[-1] < 0.01 * history[0]
    assert response_error(law, reference, held_out()) < 0.05
    sweeps = sweep_response_error(law, reference, max_strain=0.15, n=8)
    assert sweeps["mean"] < 0.05 and set(sweeps) == {"uniaxial", "shear", "mean"}
    eye = torch.eye(3).expand(3, 3, 3)
    assert torch.equal(law(eye), torch.zeros(3, 3, 3))  # still exactly stress-free at rest


def test_wave_speed_estimate(fitted_corotated):
    law, reference, _ = fitted_corotated
    rho = 1e3
    # probes give max |tau| / strain ~ lam + 2 mu (P-wave modulus) for a law close to corotated
    assert law.wave_speed(rho) == pytest.approx(reference.wave_speed(rho), rel=0.1)
    fresh = NeuralElasticity(NeuralLawConfig(stress_scale=1.0))
    stiffer = NeuralElasticity(NeuralLawConfig(stress_scale=4.0))
    stiffer.load_state_dict(fresh.state_dict())
    assert stiffer.wave_speed(rho) == pytest.approx(2 * fresh.wave_speed(rho), rel=1e-5)
    assert fresh.wave_speed(torch.tensor([4e3, 1e3])) == pytest.approx(fresh.wave_speed(1e3), rel=1e-6)


def test_fit_plasticity_to_von_mises():
    torch.manual_seed(1)
    reference = VonMisesPlasticity(3e5, 0.25, 5e3, learnable=False)
    sampling = DeformationSampling(stretch=0.1, compression=0.1, rotation=math.pi)
    law = NeuralPlasticity(NeuralLawConfig(alpha=0.01))
    cfg = PretrainConfig(sampling=sampling, n_samples=2048, batch_size=256, steps=300, lr=1e-2, seed=2)
    F = held_out(512, sampling)

    def correction_error():
        return response_error(lambda x: law(x) - x, lambda x: reference(x) - x, F)

    before = correction_error()
    history = fit_plasticity(law, reference, cfg)
    # the von Mises return map has a kink at the yield surface; 300 CI steps reach ~15-20 %
    assert history[-1] < 0.1 * history[0]
    assert correction_error() < 0.3 < before


def test_response_error_hand_values_and_errors():
    reference = CorotatedElasticity(1e5, 0.2, learnable=False)
    Fs = sweep_deformations(0.1, 5)["uniaxial"]
    assert Fs.shape == (10, 3, 3) and not (Fs == torch.eye(3)).all(dim=(1, 2)).any()  # rest excluded
    assert response_error(lambda F: 1.1 * reference(F), reference, Fs) == pytest.approx(0.1, rel=1e-5)
    assert response_error(reference, reference, Fs) == 0.0
    with pytest.raises(ValueError, match="reference response is zero"):
        response_error(reference, reference, torch.eye(3).expand(4, 3, 3))
    with pytest.raises(ValueError, match=r"\[N, 3, 3\]"):
        response_error(reference, reference, torch.eye(3))


def test_divergence_is_detected():
    law = NeuralElasticity(NeuralLawConfig(widths=(8,)))
    with torch.no_grad():
        law.mlp[0].weight[0, 0] = float("nan")
    cfg = PretrainConfig(sampling=SAMPLING, n_samples=64, batch_size=32, steps=3)
    with pytest.raises(RuntimeError, match="diverged at step 0"):
        fit_elasticity(law, CorotatedElasticity(1e5, 0.2, learnable=False), cfg)
    with pytest.raises(ValueError, match="non-finite"):
        fit_elasticity(NeuralElasticity(), lambda F: F * float("inf"), cfg)
