"""Depth backends (gca/vision/depth.py): the simulated estimator model and the offline Depth Anything checks."""

import dataclasses

import cv2
import numpy as np
import pytest
import scipy.stats

from gca.vision.depth import (DepthConfig, DepthError, SimulatedDepth, SimulatedDepthConfig, TransformersDepthConfig,
                              disparity_to_depth, estimate_depth, make_depth_estimator)

T, H, W, R = 3, 48, 48, 16


def _scene():
    """A ball-like object: hemisphere depth inside a disk that moves a little per frame."""
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    depths, masks = [], []
    for t in range(T):
        rho2 = (rows - 23.5) ** 2 + (cols - 20.0 - 2 * t) ** 2
        mask = rho2 <= R**2
        depths.append(np.where(mask, 3.0 - 0.05 * np.sqrt(np.clip(R**2 - rho2, 0, None)), 0.0))
        masks.append(mask)
    frames = np.zeros((T, H, W, 3), np.uint8)
    return frames, np.stack(depths), np.stack(masks)


def _interior(mask, margin):
    return cv2.erode(mask.astype(np.uint8), np.ones((2 * margin + 1,) * 2, np.uint8)).astype(bool)


def _interior_stats(est, z, masks):
    """Per frame: Spearman(z, est) and the max affine-fit residual (relative) in the interior."""
    rhos, residuals = [], []
    for t in range(T):
        inner = _interior(masks[t], 4)
        rhos.append(scipy.stats.spearmanr(z[t][inner], est[t][inner]).statistic)
        A = np.stack([z[t][inner], np.ones(inner.sum())], -1)
        coef, *_ = np.linalg.lstsq(A, est[t][inner], rcond=None)
        residuals.append(np.abs(A @ coef - est[t][inner]).max() / np.ptp(est[t][inner]))
    return np.array(rhos), np.array(residuals)


def test_simulated_depth_is_monotone_in_the_interior_but_not_affine():
    frames, z, masks = _scene()
    exact = SimulatedDepthConfig(noise_std=0.0, lowfreq_std=0.0)  # warp + bleed + scale/shift only
    est = SimulatedDepth(exact, seed=3).estimate(frames, z, masks)
    assert est.shape == (T, H, W) and est.dtype == np.float32
    rhos, residuals = _interior_stats(est, z, masks)
    np.testing.assert_allclose(rhos, 1.0, atol=1e-9)  # monotone away from the edge band
    assert residuals.max() > 0.02, residuals  # the per-frame warp makes it non-affine
    rhos, _ = _interior_stats(SimulatedDepth(SimulatedDepthConfig(), seed=3).estimate(frames, z, masks), z, masks)
    assert rhos.min() > 0.95, rhos  # with the default noise the local order is still nearly kept


def test_simulated_depth_errors_concentrate_at_the_edge():
    frames, z, masks = _scene()
    cfg = SimulatedDepthConfig(gamma_max=1.0, noise_std=0.0, lowfreq_std=0.0, edge_band_px=3.0,
                               scale_range=(1.0, 1.0), shift_range=(0.0, 0.0))
    est = SimulatedDepth(cfg).estimate(frames, z, masks)
    for t in range(T):
        zo = z[t][masks[t]]
        truth = np.where(masks[t], (z[t] - zo.min()) / np.ptp(zo), cfg.background)
        err = np.abs(est[t] - truth)
        far = _interior(masks[t], 4) | ~cv2.dilate(masks[t].astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        assert err[far].max() < 1e-6
        assert err[~far].max() > 0.1  # foreground/background bleed inside the band


def test_simulated_depth_is_deterministic_per_seed():
    frames, z, masks = _scene()
    a = estimate_depth(frames, DepthConfig(), z, masks, seed=7)
    b = estimate_depth(frames, DepthConfig(), z, masks, seed=7)
    c = estimate_depth(frames, DepthConfig(), z, masks, seed=8)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_simulated_depth_needs_gt_and_checks_shapes():
    frames, z, masks = _scene()
    with pytest.raises(ValueError, match="needs gt_depth and masks"):
        SimulatedDepth(SimulatedDepthConfig()).estimate(frames)
    with pytest.raises(ValueError, match="depth.py"):
        SimulatedDepth(SimulatedDepthConfig()).estimate(frames, z[:, :-1], masks)
    bad = z.copy()
    bad[0, 24, 20] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        SimulatedDepth(SimulatedDepthConfig()).estimate(frames, bad, masks)


def test_transformers_backend_with_absent_weights_says_how_to_get_them(tmp_path):
    cfg = DepthConfig(backend="transformers", transformers=TransformersDepthConfig(weights_dir=str(tmp_path / "none")))
    with pytest.raises(DepthError) as info:
        make_depth_estimator(cfg)
    message = str(info.value)
    assert "depth.py" in message and "huggingface-cli download" in message and "weights_dir" in message
    try:
        import transformers  # noqa: F401
    except ImportError:
        assert "pip install 'gca[depth]'" in message


def test_disparity_to_depth_reverses_the_order_per_frame():
    disp = np.random.default_rng(0).random((2, 8, 8)) * 5 + 1
    depth = disparity_to_depth(disp, 0.05)
    for t in range(2):
        assert scipy.stats.spearmanr(disp[t].ravel(), depth[t].ravel()).statistic == pytest.approx(-1.0)
    assert depth.max() == pytest.approx(1 / 0.05) and depth.min() == pytest.approx(1 / 1.05)


def test_bad_configs_raise():
    with pytest.raises(ValueError, match="backend"):
        DepthConfig(backend="midas")
    with pytest.raises(ValueError, match="gamma_max"):
        dataclasses.replace(SimulatedDepthConfig(), gamma_max=0.5)
