"""Monocular preprocessing of a scene's training video (the ``preprocess`` stage's library side).

From the monocular view ``train0`` only: estimated relative depth per frame, object masks, and
cached SIFT keypoints of the ground-truth frames. Also a measured match precision on a synthetic
pair with a known correspondence (frame 0 against a homography-warped copy of itself).

    data/prep/<scene>/depth.npy       estimated relative depth [T, H, W] (float32; larger = farther)
    data/prep/<scene>/masks.npy       masks [T, H, W] (bool)
    data/prep/<scene>/keypoints.npz   SIFT keypoints + descriptors per frame (pack_keypoints layout)
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from gca.io import load_array, load_arrays, reading
from gca.scenes.store import TRAIN_VIEW, SceneDataError, ViewData
from gca.vision import (VisionConfig, compute_masks, detect_keypoints, estimate_depth, match_features,
                        match_precision, pack_keypoints, unpack_keypoints)


def known_warp(size: int, seed: int = 0) -> np.ndarray:
    """A mild random homography [3, 3] for a ``size`` x ``size`` image (rotation, scale, shear, shift)."""
    rng = np.random.default_rng(seed)
    angle, scale = rng.uniform(-10, 10), rng.uniform(0.9, 1.1)
    Hm = np.vstack([cv2.getRotationMatrix2D((size / 2, size / 2), angle, scale), [0, 0, 1]])
    Hm[:2, 2] += rng.uniform(-0.05, 0.05, 2) * size
    Hm[2, :2] = rng.uniform(-2e-4, 2e-4, 2) * 64 / size
    return Hm


def synthetic_pair_precision(frame: np.ndarray, cfg: VisionConfig, seed: int = 0, tol_px: float = 2.0) -> dict:
    """Match a frame [H, W, 3] against its own homography warp; precision = fraction of correct matches."""
    img = (np.clip(frame, 0, 1) * 255).astype(np.uint8) if frame.dtype != np.uint8 else frame
    Hm = known_warp(img.shape[0], seed)
    warped = cv2.warpPerspective(img, Hm, (img.shape[1], img.shape[0]), borderValue=(255, 255, 255))
    p, q = match_features(img, warped, cfg.matching)
    return {"match_pairs": int(len(p)), "match_precision": float(match_precision(p, q, Hm, tol_px))}


def preprocess_view(view: ViewData, cfg: VisionConfig, seed: int = 0) -> dict[str, np.ndarray]:
    """Depth, masks and keypoints of the monocular view.

    The ``simulated`` depth backend models an estimator from the ground-truth depth (synthetic scenes
    only); the ``transformers`` backend reads only the frames.
    """
    if view.name != TRAIN_VIEW:
        raise SceneDataError(f"preprocess works on the monocular view {TRAIN_VIEW!r}, got {view.name!r}")
    frames = (view.rgb * 255 + 0.5).astype(np.uint8)
    alpha = view.mask.astype(np.float32)
    masks = compute_masks(cfg.masks, frames=frames, alpha=alpha)
    depth = estimate_depth(frames, cfg.depth, gt_depth=view.depth, masks=masks, seed=seed).astype(np.float32)
    if not np.all(np.isfinite(depth)):
        raise FloatingPointError("preprocess: the depth estimator returned NaN/inf")
    keypoints = pack_keypoints([detect_keypoints(f, cfg.matching) for f in frames])
    return {"depth": depth, "masks": masks, "keypoints": keypoints}


def write_prep(out_dir: Path, prep: dict) -> None:
    np.save(out_dir / "depth.npy", prep["depth"])
    np.save(out_dir / "masks.npy", prep["masks"])
    np.savez(out_dir / "keypoints.npz", **prep["keypoints"])


def load_prep(prep_dir: str | Path, n_frames: int) -> tuple[np.ndarray, np.ndarray, list]:
    """(depth [T,H,W], masks [T,H,W], keypoints per frame), validated against the video length."""
    prep_dir = Path(prep_dir)
    for name in ("depth.npy", "masks.npy", "keypoints.npz"):
        if not (prep_dir / name).is_file():
            raise SceneDataError(f"{prep_dir / name}: missing (run the preprocess stage)")
    depth, masks = load_array(prep_dir / "depth.npy", "depth"), load_array(prep_dir / "masks.npy", "masks")
    with reading(prep_dir / "keypoints.npz", "keypoints"):
        keypoints = unpack_keypoints(load_arrays(prep_dir / "keypoints.npz", "keypoints"))
    for name, n in (("depth.npy", len(depth)), ("masks.npy", len(masks)), ("keypoints.npz", len(keypoints))):
        if n != n_frames:
            raise SceneDataError(f"{prep_dir / name}: has {n} frames, the video has {n_frames}")
    if not np.all(np.isfinite(depth)):
        raise SceneDataError(f"{prep_dir / 'depth.npy'}: contains NaN/inf")
    return depth, masks, keypoints
