"""On-disk layout of a scene (the ``ground_truth`` stage's output) and its validated loader.

    data/scenes/<scene>/
      meta.json            scene/timing facts: dt, substeps, frame_every, video_frames, times [s], views
      cameras.json         {view: Camera.to_dict()}; "train0" is the monocular camera,
                           "train1", "train2" the extra multi-view cameras, "eval*" held out
      views/<view>/rgb/00000.png ...     RGB frames (uint8)
      views/<view>/mask/00000.png ...    object masks (0/255)
      views/<view>/depth.npy             ground-truth camera-space depth [T, H, W] (m; 0 = background)
      trajectory.npz       x [T+1, P, 3]: particles at frame 0 and at each video frame (evaluation only:
                           training code never reads it)
      preview.gif          the monocular video

Every problem found while loading names the file and the problem (missing frames, a camera that
does not match the images, NaN in data).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Iterable

import imageio.v3 as iio
import numpy as np

from gca.io import load_array, load_arrays, read_json, reading
from gca.render.camera import Camera

TRAIN_VIEW = "train0"


class SceneDataError(ValueError):
    """A scene directory is incomplete or inconsistent (names the file and the problem)."""


@dataclasses.dataclass
class ViewData:
    """One camera's video. rgb [T, H, W, 3] float32 in [0,1]; mask [T, H, W] bool; depth [T, H, W] (m)."""

    name: str
    camera: Camera
    rgb: np.ndarray
    mask: np.ndarray
    depth: np.ndarray


def frame_name(i: int) -> str:
    return f"{i:05d}.png"


def view_dir(scene_dir: Path, view: str) -> Path:
    return Path(scene_dir) / "views" / view


def read_meta(scene_dir: str | Path) -> dict:
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise SceneDataError(f"{scene_dir}: scene directory not found (run the ground_truth stage)")
    return read_json(scene_dir / "meta.json")


def read_cameras(scene_dir: str | Path) -> dict[str, Camera]:
    raw = read_json(Path(scene_dir) / "cameras.json")
    return {name: Camera.from_dict(c) for name, c in raw.items()}


def _read_frames(folder: Path, n: int, camera: Camera, channels: int) -> np.ndarray:
    frames = []
    for i in range(n):
        path = folder / frame_name(i)
        if not path.is_file():
            raise SceneDataError(f"{path}: missing frame {i} of {n}")
        with reading(path, "image"):
            img = iio.imread(path)
        if channels > 1 and (img.ndim != 3 or img.shape[2] < channels):
            raise SceneDataError(f"{path}: expected a colour image ({channels} channels), got shape {img.shape}")
        if img.shape[:2] != (camera.height, camera.width):
            raise SceneDataError(f"{path}: image is {img.shape[1]}x{img.shape[0]} but the camera is "
                                 f"{camera.width}x{camera.height} (mismatched camera)")
        frames.append(img[..., :channels] if channels > 1 else (img if img.ndim == 2 else img[..., 0]))
    return np.stack(frames)


def load_view(scene_dir: str | Path, view: str, meta: dict | None = None,
              cameras: dict[str, Camera] | None = None) -> ViewData:
    """Load and validate one view's frames, masks and depth."""
    scene_dir = Path(scene_dir)
    meta = meta or read_meta(scene_dir)
    cameras = cameras or read_cameras(scene_dir)
    if view not in cameras:
        raise SceneDataError(f"{scene_dir / 'cameras.json'}: no camera for view {view!r} (have {sorted(cameras)})")
    camera, n = cameras[view], len(meta["video_frames"])
    folder = view_dir(scene_dir, view)
    rgb = _read_frames(folder / "rgb", n, camera, 3).astype(np.float32) / 255.0
    mask = _read_frames(folder / "mask", n, camera, 1) > 127
    depth_path = folder / "depth.npy"
    if not depth_path.is_file():
        raise SceneDataError(f"{depth_path}: missing depth")
    depth = load_array(depth_path, "depth")
    if depth.shape != mask.shape:
        raise SceneDataError(f"{depth_path}: shape {depth.shape} does not match the frames {mask.shape}")
    if not np.all(np.isfinite(depth)):
        raise SceneDataError(f"{depth_path}: contains NaN/inf")
    return ViewData(view, camera, rgb, mask, depth)


def load_views(scene_dir: str | Path, views: Iterable[str]) -> dict[str, ViewData]:
    meta, cameras = read_meta(scene_dir), read_cameras(scene_dir)
    return {v: load_view(scene_dir, v, meta, cameras) for v in views}


def load_trajectory(scene_dir: str | Path) -> np.ndarray:
    """Ground-truth particle positions [T+1, P, 3] (evaluation only)."""
    path = Path(scene_dir) / "trajectory.npz"
    if not path.is_file():
        raise SceneDataError(f"{path}: missing ground-truth trajectory")
    arrays = load_arrays(path, "trajectory")
    if "x" not in arrays:
        raise SceneDataError(f"{path}: no array 'x' (have {sorted(arrays)})")
    x = arrays["x"]
    if not np.all(np.isfinite(x)):
        raise SceneDataError(f"{path}: trajectory contains NaN/inf")
    return x
