"""Ground-truth-only data of a scene: written by ``ground_truth``, read by evaluation only (issue 21, item 6).

    data/gt/<scene>/
      trajectory.npz                 x [T+1, P, 3]: particles at frame 0 and at each video frame [m, sim]
      law.json                       the true material preset, v0 [m/s], w0 [rad/s], light seed
      views/<view>/alpha.npy         rendered alpha [T, H, W] (float32, [0, 1]): the true silhouette
      views/<view>/depth.npy         true camera-space depth [T, H, W] (float32, m; the render's alpha-normalised
                                     depth; 0 where alpha <= threshold)
      views/train0/unlit.npy         the monocular view rendered with the base colours, no lighting,
                                     exposure or shadow [T, H, W, 3] (uint8): the lighting statistic's reference

Nothing a method trains on is here, and nothing here is reachable from the scene directory: the
training-side loader (:mod:`gca.scenes.store`) returns frames and cameras only. The evaluation code
reads this directory in one of two ways:

- explicitly, with the functions below taking ``gt_dir``;
- through :func:`bind` (a context manager the ``evaluate`` stage enters), which lets
  :func:`gca.scenes.store.load_trajectory` (``scene_dir``) find the trajectory of a scene directory.
  In a process that never bound it (``preprocess``, ``train``), asking for it raises
  :class:`GroundTruthUnavailable`; ``dvc.yaml`` gives only ``evaluate``, ``nuisance`` and ``report``
  the ``data/gt/<scene>`` dependency.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

import numpy as np

from gca.io import read_json, write_json

_BOUND: dict[Path, Path] = {}


class GroundTruthUnavailable(RuntimeError):
    """Ground-truth-only data was asked for where it is not available (training side, or a missing file)."""


def _key(scene_dir: str | Path) -> Path:
    return Path(scene_dir).resolve()


@contextlib.contextmanager
def bind(scene_dir: str | Path, gt_dir: str | Path) -> Iterator[Path]:
    """Within the block, the ground truth of ``scene_dir`` is ``gt_dir`` (evaluation stages only)."""
    gt_dir = Path(gt_dir)
    if not gt_dir.is_dir():
        raise GroundTruthUnavailable(f"{gt_dir}: ground-truth directory not found (run the ground_truth stage)")
    key = _key(scene_dir)
    previous = _BOUND.get(key)
    _BOUND[key] = gt_dir
    try:
        yield gt_dir
    finally:
        if previous is None:
            _BOUND.pop(key, None)
        else:
            _BOUND[key] = previous


def bound_dir(scene_dir: str | Path) -> Path:
    """The ground-truth directory bound to ``scene_dir`` by :func:`bind`; raises when none is."""
    gt = _BOUND.get(_key(scene_dir))
    if gt is None:
        raise GroundTruthUnavailable(
            f"{scene_dir}: ground truth is evaluation-only and not bound in this process (the evaluate stage "
            "binds data/gt/<scene> with gca.scenes.truth.bind; preprocessing and training never read it)")
    return gt


def _require(path: Path) -> Path:
    if not path.is_file():
        raise GroundTruthUnavailable(f"{path}: missing ground-truth file (run the ground_truth stage)")
    return path


def view_truth_dir(gt_dir: str | Path, view: str) -> Path:
    return Path(gt_dir) / "views" / view


def write_view_truth(gt_dir: Path, view: str, alpha: np.ndarray, depth: np.ndarray, mask_threshold: float,
                     unlit: np.ndarray | None = None) -> None:
    """Write one view's true alpha [T,H,W], depth [T,H,W] (zeroed outside alpha > threshold), unlit RGB."""
    folder = view_truth_dir(gt_dir, view)
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "alpha.npy", np.clip(alpha, 0, 1).astype(np.float32))
    np.save(folder / "depth.npy", np.where(alpha > mask_threshold, depth, 0.0).astype(np.float32))
    if unlit is not None:
        np.save(folder / "unlit.npy", (np.clip(unlit, 0, 1) * 255 + 0.5).astype(np.uint8))


def write_truth(gt_dir: Path, trajectory: np.ndarray, law: dict) -> None:
    """Write the trajectory [T+1, P, 3] and the true law record."""
    gt_dir.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(gt_dir / "trajectory.npz", x=trajectory.astype(np.float32))
    write_json(gt_dir / "law.json", law)


def _load_checked(path: Path) -> np.ndarray:
    arr = np.load(_require(path))
    if not np.all(np.isfinite(arr)):
        raise GroundTruthUnavailable(f"{path}: contains NaN/inf")
    return arr


def load_trajectory(gt_dir: str | Path) -> np.ndarray:
    """True particle positions [T+1, P, 3] (m)."""
    path = _require(Path(gt_dir) / "trajectory.npz")
    x = np.load(path)["x"]
    if x.ndim != 3 or x.shape[-1] != 3 or not np.all(np.isfinite(x)):
        raise GroundTruthUnavailable(f"{path}: trajectory must be finite [T+1, P, 3], got shape {x.shape}")
    return x


def load_alpha(gt_dir: str | Path, view: str) -> np.ndarray:
    """True alpha [T, H, W] float32 in [0, 1]."""
    return _load_checked(view_truth_dir(gt_dir, view) / "alpha.npy").astype(np.float32)


def load_true_depth(gt_dir: str | Path, view: str) -> np.ndarray:
    """True camera-space depth [T, H, W] (m; 0 = background)."""
    return _load_checked(view_truth_dir(gt_dir, view) / "depth.npy")


def load_unlit(gt_dir: str | Path, view: str = "train0") -> np.ndarray:
    """The unlit render [T, H, W, 3] float32 in [0, 1]."""
    return _load_checked(view_truth_dir(gt_dir, view) / "unlit.npy").astype(np.float32) / 255.0


def load_law(gt_dir: str | Path) -> dict:
    """The true law record (material preset, v0, w0)."""
    return read_json(_require(Path(gt_dir) / "law.json"))
