"""Measured nuisance statistics of a scene's monocular observations (issue 21): how far what a method sees
is from the truth. Evaluation-side: it reads the ground-truth directory (:mod:`gca.scenes.truth`).

Per scene, on the monocular view ``train0``:

- ``mask_iou``: per-frame IoU of the preprocess stage's masks (segmented from the lit frames) against the
  true alpha > ``mask_threshold``;
- ``depth_spearman``: per-frame Spearman rank correlation of the preprocess stage's relative depth against
  the true camera-space depth, over the pixels inside the true object;
- ``lighting_unexplained_share``: the share of the lit video's in-object colour variance that the best
  per-frame affine colour map of the unlit render cannot explain
  (:func:`gca.scenes.ground_truth.unexplained_colour_share`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.stats

from gca.scenes import TRAIN_VIEW, load_view, truth
from gca.scenes.ground_truth import unexplained_colour_share
from gca.scenes.preprocess import load_prep
from gca.vision.segment import iou


def depth_spearman(est: np.ndarray, true: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Per-frame Spearman correlation [T] of estimated vs true depth over ``inside`` [T, H, W] (NaN: < 3 pixels)."""
    out = []
    for e, z, m in zip(est, true, inside):
        out.append(float(scipy.stats.spearmanr(e[m], z[m]).statistic) if m.sum() >= 3 else float("nan"))
    return np.array(out)


def _summary(values: np.ndarray, name: str) -> dict:
    finite = values[np.isfinite(values)]
    return {f"{name}_per_frame": [round(float(v), 5) for v in values],
            f"{name}_mean": float(finite.mean()) if len(finite) else float("nan"),
            f"{name}_min": float(finite.min()) if len(finite) else float("nan")}


def scene_nuisance(scene_dir: str | Path, gt_dir: str | Path, prep_dir: str | Path, mask_threshold: float = 0.5) -> dict:
    """The three statistics of one scene (module docstring) as a JSON-ready dict."""
    view = load_view(scene_dir, TRAIN_VIEW)
    depth, masks, _ = load_prep(prep_dir, len(view.rgb))
    alpha = truth.load_alpha(gt_dir, TRAIN_VIEW)
    true_depth = truth.load_true_depth(gt_dir, TRAIN_VIEW)
    inside = alpha > mask_threshold
    out = {**_summary(iou(masks, inside), "mask_iou"), **_summary(depth_spearman(depth, true_depth, inside), "depth_spearman")}
    out["mask_false_positive_share"] = float((masks & ~inside).sum() / max(masks.sum(), 1))
    out["mask_false_negative_share"] = float((~masks & inside).sum() / max(inside.sum(), 1))
    out["lighting_unexplained_share"] = unexplained_colour_share(view.rgb, truth.load_unlit(gt_dir, TRAIN_VIEW), inside)
    out["image_mean_per_frame"] = [round(float(v), 5) for v in view.rgb.mean(axis=(1, 2, 3))]
    return out
