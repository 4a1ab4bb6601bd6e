"""Monocular preprocessing of a scene's training video (the ``preprocess`` stage's library side).

From the monocular view ``train0``'s frames only (the scene directory; never the ground-truth
directory): estimated relative depth per frame, object masks segmented from the lit frames, and
cached SIFT keypoints. Also a measured match precision on a synthetic
pair with a known correspondence (frame 0 against a homography-warped copy of itself).

    data/prep/<scene>/depth.npy       estimated relative depth [T, H, W] (float32; larger = farther)
    data/prep/<scene>/masks.npy       masks [T, H, W] (bool)
    data/prep/<scene>/keypoints.npz   SIFT keypoints + descriptors per frame (pack_keypoints layout)
    data/prep/<scene>/heldout_masks.npy   a capture's held-out frames' masks [T_h, H, W] (evaluation only)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from gca.io import load_array, load_arrays, reading
from gca.scenes.store import TRAIN_VIEW, SceneDataError, ViewData
from gca.vision.depth import silhouette_depth
from gca.vision.segment import segment_frames
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


def preprocess_view(view: ViewData, cfg: VisionConfig, seed: int = 0,
                    simulated_depth: np.ndarray | None = None, plate: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Depth, masks and keypoints of the monocular view, from its frames.

    Args:
        view: the scene loader's ``train0`` (frames and camera; no mask, no depth).
        cfg: the ``vision`` section.
        simulated_depth: [T, H, W] the simulated estimator's output the ground_truth stage stored
            (:func:`gca.scenes.store.load_simulated_depth`), used by ``vision.depth.backend: simulated``;
            the ``transformers`` backend reads only the frames.
        plate: the view's clean plate [H, W, 3] (:func:`gca.scenes.store.load_plate`) for the segmenter's
            ``background: plate``; None: ``plate_color``.
    """
    if view.name != TRAIN_VIEW:
        raise SceneDataError(f"preprocess works on the monocular view {TRAIN_VIEW!r}, got {view.name!r}")
    frames = (view.rgb * 255 + 0.5).astype(np.uint8)
    if cfg.masks.method == "segment":
        masks = segment_frames(frames, cfg.masks.segment, plate)
    else:
        masks = compute_masks(cfg.masks, frames=frames)
    if cfg.depth.backend == "simulated":
        if simulated_depth is None:
            raise SceneDataError("preprocess: vision.depth.backend 'simulated' needs the scene's views/train0/depth_sim.npy")
        depth = np.asarray(simulated_depth, dtype=np.float32)
    else:
        depth = estimate_depth(frames, cfg.depth, seed=seed).astype(np.float32)
    if not np.all(np.isfinite(depth)):
        raise FloatingPointError("preprocess: the depth estimator returned NaN/inf")
    keypoints = pack_keypoints([detect_keypoints(f, cfg.matching) for f in frames])
    return {"depth": depth, "masks": masks, "keypoints": keypoints}


def preprocess_capture(view: ViewData, heldout: np.ndarray, cfg: VisionConfig, depth: str, seed: int = 0,
                       plate: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """:func:`preprocess_view` of a capture's training frames, needing the frames only, plus the held-out
    frames' masks (``heldout_masks`` [T_h, H, W] bool, for evaluation; segmented with the same background).

    Args:
        view: ``train0`` (frames, camera); heldout: the held-out frames [T_h, H, W, 3] float in [0, 1].
        depth: ``scenes.<name>.capture.depth``: ``transformers`` (Depth Anything from
            ``vision.depth.transformers.weights_dir``; a missing model is a one-line :class:`SceneDataError`
            saying how to get it) or ``silhouette`` (:func:`gca.vision.depth.silhouette_depth`, the fallback).
    """
    frames = (np.concatenate([view.rgb, heldout]) * 255 + 0.5).astype(np.uint8) if len(heldout) else \
        (view.rgb * 255 + 0.5).astype(np.uint8)
    if cfg.masks.method == "segment":
        masks = segment_frames(frames, cfg.masks.segment, plate)
    else:
        masks = compute_masks(cfg.masks, frames=frames)
    n = len(view.rgb)
    train = frames[:n]
    if depth == "silhouette":
        est = silhouette_depth(masks[:n], cfg.depth.simulated.background)
    else:
        tcfg = cfg.depth.transformers
        if not (Path(tcfg.weights_dir) / "config.json").is_file():
            raise SceneDataError(f"{tcfg.weights_dir}: no Depth Anything model (config.json) for this capture's depth: "
                                 "download it (README, 'Your own object') and set vision.depth.transformers.weights_dir, "
                                 "or set scenes.<name>.capture.depth: silhouette (a fallback without a model)")
        est = estimate_depth(train, dataclasses.replace(cfg.depth, backend="transformers"), seed=seed)
    est = np.asarray(est, dtype=np.float32)
    if not np.all(np.isfinite(est)):
        raise FloatingPointError("preprocess: the depth estimator returned NaN/inf")
    keypoints = pack_keypoints([detect_keypoints(f, cfg.matching) for f in train])
    return {"depth": est, "masks": masks[:n], "keypoints": keypoints, "heldout_masks": masks[n:]}


def write_prep(out_dir: Path, prep: dict) -> None:
    np.save(out_dir / "depth.npy", prep["depth"])
    np.save(out_dir / "masks.npy", prep["masks"])
    np.savez(out_dir / "keypoints.npz", **prep["keypoints"])
    if "heldout_masks" in prep:  # captures: the held-out frames' masks, read by evaluation only
        np.save(out_dir / "heldout_masks.npy", prep["heldout_masks"])


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
