"""Masks (gca/vision/masks.py): alpha threshold, background difference, colour key, user files."""

import cv2
import numpy as np
import pytest

from gca.vision.masks import MaskConfig, compute_masks, load_mask_files, mask_from_alpha, mask_from_background

T, H, W = 7, 40, 48


def _video(seed=0):
    """A textured static background with a red 10x12 block moving right; a few 1-px specks of noise."""
    rng = np.random.default_rng(seed)
    bg = (cv2.GaussianBlur(rng.random((H, W, 3)), (0, 0), 2.0) * 0.4 + 0.3).astype(np.float32)
    frames, truth = [], []
    for t in range(T):
        m = np.zeros((H, W), bool)
        m[14:24, 3 + 6 * t:15 + 6 * t] = True
        f = bg.copy()
        f[m] = (0.9, 0.1, 0.1)
        specks = rng.integers(0, [H, W], size=(3, 2))
        f[specks[:, 0], specks[:, 1]] += 0.5  # isolated pixel noise the opening must remove
        frames.append(np.clip(f, 0, 1))
        truth.append(m)
    return np.stack(frames), np.stack(truth), bg


def test_mask_from_alpha_thresholds():
    alpha = np.array([[0.0, 0.49], [0.51, 1.0]])
    np.testing.assert_array_equal(mask_from_alpha(alpha), [[False, False], [True, True]])
    np.testing.assert_array_equal(mask_from_alpha(alpha, 0.2), [[False, True], [True, True]])


def test_background_difference_recovers_moving_object_and_opening_removes_specks():
    frames, truth, bg = _video()
    masks = compute_masks(MaskConfig(method="background", diff_threshold=0.15, open_px=3), frames=frames)
    np.testing.assert_array_equal(masks, truth)
    raw = mask_from_background(frames, threshold=0.15, open_px=0)
    assert (raw & ~truth).sum() > 0  # without the opening the specks are there
    uint8 = mask_from_background((frames * 255 + 0.5).astype(np.uint8), threshold=0.15, open_px=3)
    np.testing.assert_array_equal(uint8, truth)


def test_colour_key_on_white_background():
    frames = np.ones((2, H, W, 3), np.float32)
    frames[:, 5:20, 10:30] = (0.2, 0.5, 0.3)
    masks = compute_masks(MaskConfig(method="background", background_color=(1.0, 1.0, 1.0)), frames=frames)
    assert masks.sum() == 2 * 15 * 20 and masks[:, 5:20, 10:30].all()


def test_mask_files_hook_and_its_errors(tmp_path):
    _, truth, _ = _video()
    for t, m in enumerate(truth):
        cv2.imwrite(str(tmp_path / f"{t:04d}.png"), m.astype(np.uint8) * 255)
    frames = np.zeros((T, H, W, 3), np.uint8)
    np.testing.assert_array_equal(compute_masks(MaskConfig(method="files", files_dir=str(tmp_path)), frames), truth)
    with pytest.raises(ValueError, match=f"holds {T} mask PNGs but the video has {T + 1}"):
        load_mask_files(tmp_path, T + 1, (H, W))
    with pytest.raises(ValueError, match="masks.py.*frames are"):
        load_mask_files(tmp_path, T, (H + 1, W))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_mask_files(tmp_path / "missing", T, (H, W))


def test_alpha_method_needs_alpha():
    with pytest.raises(ValueError, match="needs the rendered alpha"):
        compute_masks(MaskConfig(method="alpha"), frames=np.zeros((1, 4, 4, 3)))
