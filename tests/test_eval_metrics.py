"""gca.eval: Chamfer (hand-computed, symmetric, chunked vs KD-tree reference), PSNR/SSIM closed forms,
LPIPS availability, law response error, efficiency probe."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from gca.config import build
from gca.eval import (CHAMFER_DEFINITION, MetricsConfig, chamfer, chamfer_over_time, count_parameters,
                      deformation_sweep, law_response_curve, law_response_error, lpips_or_reason,
                      lpips_unavailable_reason, measure, psnr, ssim)


def _chamfer_ref(a: np.ndarray, b: np.ndarray) -> float:
    """KD-tree reference of the documented definition (mean of the two directed means)."""
    return 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


# ---------------------------------------------------------------- Chamfer
def test_chamfer_hand_computed():
    a = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = torch.tensor([[0.0, 0.0, 0.0]])
    # a->b: (0 + 1)/2 = 0.5; b->a: 0; CD = (0.5 + 0)/2
    assert chamfer(a, b).item() == pytest.approx(0.25)
    a, b = torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[0.0, 3.0, 4.0]])
    assert chamfer(a, b).item() == pytest.approx(5.0)
    assert chamfer(a, b, squared=True).item() == pytest.approx(25.0)
    assert "mean" in CHAMFER_DEFINITION


def test_chamfer_zero_identical_and_symmetric():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(500, 3, generator=g), torch.rand(300, 3, generator=g)
    assert chamfer(a, a.clone()).item() == 0.0
    assert chamfer(a, b).item() == pytest.approx(chamfer(b, a).item(), rel=1e-6)
    assert chamfer(a, b).item() > 0.0


def test_chamfer_chunked_matches_kdtree():
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(700, 3, generator=g), torch.rand(450, 3, generator=g) + 0.1
    ref = _chamfer_ref(a.numpy().astype(np.float64), b.numpy().astype(np.float64))
    assert chamfer(a, b).item() == pytest.approx(ref, rel=1e-5)  # CPU default: KD-tree
    for chunk in (64, 1 << 23):  # brute force (the GPU path): many tiny blocks and a single block
        assert chamfer(a, b, chunk_elements=chunk, backend="brute").item() == pytest.approx(ref, rel=1e-5)


def test_chamfer_gradient_and_over_time():
    a = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], requires_grad=True)
    b = torch.tensor([[0.0, 0.0, 0.0]])
    chamfer(a, b, squared=True).backward()
    # only the far point moves: d/dx [ (1/2)(x^2/2) ] = x/2 = 0.5
    assert torch.allclose(a.grad, torch.tensor([[0.0, 0, 0], [0.5, 0, 0]]))
    traj_a = torch.stack([a.detach(), a.detach() * 2])
    traj_b = torch.stack([b, b])
    assert torch.allclose(chamfer_over_time(traj_a, traj_b), torch.tensor([0.25, 0.5]))


def test_chamfer_rejects_bad_input():
    with pytest.raises(ValueError, match="geometry.py"):
        chamfer(torch.rand(4, 2), torch.rand(4, 3))
    with pytest.raises(ValueError, match="non-finite"):
        chamfer(torch.tensor([[float("nan"), 0, 0]]), torch.rand(4, 3))


# ---------------------------------------------------------------- images
def _image(seed=0, shape=(2, 3, 32, 40)):
    g = torch.Generator().manual_seed(seed)
    return 0.2 + 0.6 * torch.rand(*shape, generator=g)


def test_psnr_closed_forms():
    ref = _image()
    assert torch.allclose(psnr(ref + 0.1, ref), torch.full((2,), 20.0), atol=1e-4)  # MSE = 0.01
    signs = torch.randint(0, 2, ref.shape, generator=torch.Generator().manual_seed(3)) * 2 - 1
    a = 0.05
    assert torch.allclose(psnr(ref + a * signs, ref), torch.full((2,), -20 * math.log10(a)), atol=1e-4)
    assert psnr(ref[0] + 0.1, ref[0]).ndim == 0
    assert torch.isinf(psnr(ref, ref)).all()


def test_psnr_mask_ignores_background():
    ref = _image()
    mask = torch.zeros(32, 40, dtype=torch.bool)
    mask[8:24, 10:30] = True
    img = torch.where(mask, ref + 0.1, ref - 0.15)
    assert torch.allclose(psnr(img, ref, mask=mask), torch.full((2,), 20.0), atol=1e-4)
    assert (psnr(img, ref) < 19.0).all()  # unmasked sees the background error


def test_ssim_identity_and_degradation():
    ref = _image()
    assert torch.allclose(ssim(ref, ref), torch.ones(2), atol=1e-5)
    noisy = ref + 0.2 * (torch.rand(ref.shape, generator=torch.Generator().manual_seed(5)) - 0.5)
    assert (ssim(noisy, ref) < 0.95).all()


def test_image_metrics_reject_channels_last():
    with pytest.raises(ValueError, match="channels first"):
        psnr(torch.rand(32, 40, 3), torch.rand(32, 40, 3))


def test_lpips_reports_reason_or_value():
    value, reason = lpips_or_reason(_image(), _image(1))
    if lpips_unavailable_reason() is None:
        assert reason is None and torch.isfinite(value).all()
    else:
        assert value is None and reason.startswith("lpips:")


# ---------------------------------------------------------------- law response
class _LinearLaw(torch.nn.Module):
    """tau = 2 mu eps + lam tr(eps) I with small strain eps = (F + F^T)/2 - I (a toy reference law)."""

    def __init__(self, mu=1e4, lam=5e3, scale=1.0):
        super().__init__()
        self.mu, self.lam, self.scale = mu, lam, scale

    def forward(self, F):
        eps = 0.5 * (F + F.transpose(-1, -2)) - torch.eye(3, dtype=F.dtype)
        tr = eps.diagonal(dim1=-2, dim2=-1).sum(-1)
        return self.scale * (2 * self.mu * eps + self.lam * tr[:, None, None] * torch.eye(3, dtype=F.dtype))


@pytest.mark.parametrize("kind", ["uniaxial", "shear"])
def test_law_response_error_zero_and_ten_percent(kind):
    ref = _LinearLaw()
    assert law_response_error(_LinearLaw(), ref, kind=kind, n=21) == pytest.approx(0.0, abs=1e-9)
    assert law_response_error(_LinearLaw(scale=1.1), ref, kind=kind, n=21) == pytest.approx(10.0, rel=1e-5)
    assert law_response_error(_LinearLaw(mu=2e4), ref, kind=kind, n=21) > 1.0


def test_law_response_curve_values():
    s, F = deformation_sweep("uniaxial", 5)
    assert torch.allclose(s, torch.tensor([0.8, 0.9, 1.0, 1.1, 1.2])) and torch.allclose(F[:, 0, 0], s)
    curve = law_response_curve(_LinearLaw(mu=1.0, lam=0.0), "shear", 4)
    # shear gamma: eps_xy = gamma/2, tau_xy = 2 mu eps_xy = gamma
    assert torch.allclose(curve["component"], curve["strain"])


# ---------------------------------------------------------------- efficiency
def test_measure_sees_allocation_and_counts_parameters():
    with measure("cpu") as usage:
        big = torch.ones(16 * 2 ** 20)  # 64 MiB, alive until the block exits
        big.add_(1.0)
    assert usage.wall_s > 0 and usage.delta_bytes >= 32 * 2 ** 20, usage
    assert set(usage.as_dict("train/")) == {"train/wall_s", "train/peak_mib", "train/delta_mib"}
    lin = torch.nn.Linear(3, 4)
    lin.bias.requires_grad_(False)
    assert count_parameters(lin) == 12 and count_parameters(lin, trainable_only=False) == 16
    del big


def test_best_time_us_leaves_the_warm_up_round_out():
    import time
    from gca.efficiency import best_time_us
    calls = []

    def fn():  # instant in the warm-up round (2 calls), then 2 ms a call: counting the warm-up would give ~0
        calls.append(1)
        if len(calls) > 2:
            time.sleep(2e-3)
    assert best_time_us(fn, "cpu", iters=2, repeats=2) >= 2000.0
    assert len(calls) == 6  # 2 calls x (warm-up + 2 rounds)
    assert best_time_us(lambda: None, "cpu", iters=1, repeats=0) < 2000.0  # repeats 0 still times one round


def test_metrics_config_builds_and_validates():
    cfg = build(MetricsConfig, {"ssim_window": 7, "response_sweeps": ["shear"]}, "eval.metrics", partial=True)
    assert cfg.response_sweeps == ("shear",) and cfg.ssim_window == 7
    with pytest.raises(ValueError, match="eval/config.py"):
        MetricsConfig(response_sweeps=("torsion",))


def test_a_stop_while_an_evaluation_image_is_written_leaves_no_half_written_file(tmp_path, monkeypatch):
    """Issue 24 item 7 (found by tests/test_fault_injection.py): SIGTERM (``gca.stop.Terminated``) in the middle
    of writing the strip, the rollout GIF or the CD plot leaves neither a half-written file nor a temporary."""
    import matplotlib.figure

    from gca import stop
    from gca.eval import evaluate

    def cut(path, *args, **kwargs):  # half of a file, then the signal
        open(path, "wb").write(b"\x89PNG\r\n\x1a\n half")
        raise stop.Terminated()

    monkeypatch.setattr(evaluate.iio, "imwrite", cut)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda self, path, **kwargs: cut(path))
    frames = np.zeros((2, 4, 4, 3))
    for write in (lambda: evaluate.write_strip(tmp_path / "strip.png", frames, frames),
                  lambda: evaluate.plot_chamfer(tmp_path / "cd_time.png", [0.0, 0.01], [0.1, 0.2])):
        with pytest.raises(stop.Terminated):
            write()
        assert sorted(p.name for p in tmp_path.iterdir()) == []
