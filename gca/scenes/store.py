"""On-disk layout of a scene (the ``ground_truth`` stage's output) and its validated loader.

    data/scenes/<scene>/
      meta.json            scene/timing facts: dt, substeps, frame_every, video_frames, times [s], views
      cameras.json         {view: Camera.to_dict()}; "train0" is the monocular camera,
                           "train1", "train2" the extra multi-view cameras, "eval*" held out
      views/<view>/rgb/00000.png ...     the lit RGB frames (uint8): what a camera recorded
      views/<view>/plate.png             the empty scene filmed before the throw (a clean plate, uint8)
      views/train0/depth_sim.npy         the simulated monocular depth estimator's output [T, H, W] (float32,
                                         relative; ``vision.depth.backend: simulated``): an observation made in
                                         the ground_truth stage, because the estimator model needs the true depth
      preview.gif          the monocular video
      seed<k>/             training seed k's own nuisance draw (k in ``train.seeds``, k > 0; synthetic scenes):
                           meta.json, cameras.json and the training views (``views/train*/``: lit frames, plate,
                           ``depth_sim.npy``) rendered from the same true trajectory under seed k's lighting,
                           exposure and white-balance drift, with seed k's depth-estimator noise
                           (:func:`seed_dir`, :func:`nuisance_seed`); the top level is seed 0's draw

Only what a monocular method observes is here: no masks, no true depth, no trajectory. Those are
ground-truth-only and live in ``data/gt/<scene>/`` (:mod:`gca.scenes.truth`); :func:`load_view`
cannot return them (``ViewData.mask`` and ``.depth`` are None until preprocessing's own masks are
set), and :func:`load_trajectory` works only where evaluation bound the ground truth.

Every problem found while loading names the file and the problem (missing frames, a camera that
does not match the images, NaN in data).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Iterable

import imageio.v3 as iio
import numpy as np

from gca.io import load_array, read_json, reading
from gca.render.camera import Camera

TRAIN_VIEW = "train0"


def seed_dir(root: str | Path, seed: int) -> Path:
    """Training seed ``seed``'s observations under a per-scene directory ``root`` (``data/scenes/<scene>`` or
    ``data/prep/<scene>``): ``root`` itself for seed 0 (the layout before seeds drew their own nuisances, so
    its data are unchanged), ``root/seed<k>`` for seed k > 0."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"a training seed is an integer >= 0, got {seed!r}")
    return Path(root) if seed == 0 else Path(root) / f"seed{seed}"


def nuisance_seed(base: int, seed: int) -> int:
    """The generator seed of one nuisance stream (lighting: ``scenes.<name>.light_seed``; depth-estimator noise:
    the global ``seed``) for training seed ``seed``: ``base`` itself for seed 0 (the benchmark's draw as made
    before the seeds covered the nuisances), else a 63-bit integer of numpy's ``SeedSequence([base, seed])``
    (a stream independent of seed 0's and of every other seed's). Only the draw changes with the seed, never
    the distribution it is drawn from (the ``render.lighting`` and ``vision.depth`` conditions)."""
    seed_dir(".", seed)  # validates the seed
    if seed == 0:
        return int(base)
    return int(np.random.SeedSequence([int(base), int(seed)]).generate_state(1, np.uint64)[0] >> np.uint64(1))


class SceneDataError(ValueError):
    """A scene directory is incomplete or inconsistent (names the file and the problem)."""


@dataclasses.dataclass
class ViewData:
    """One camera's video. rgb [T, H, W, 3] float32 in [0,1]; mask [T, H, W] bool (None from the scene
    loader: training sets the preprocess stage's masks); depth [T, H, W] (None from the scene loader;
    tests building synthetic views may fill it)."""

    name: str
    camera: Camera
    rgb: np.ndarray
    mask: np.ndarray | None = None
    depth: np.ndarray | None = None


def frame_name(i: int) -> str:
    return f"{i:05d}.png"


def view_dir(scene_dir: Path, view: str) -> Path:
    return Path(scene_dir) / "views" / view


def read_meta(scene_dir: str | Path) -> dict:
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise SceneDataError(f"{scene_dir}: scene directory not found (run the ground_truth stage)")
    return read_json(scene_dir / "meta.json")


def frame_substeps(meta: dict, dt: float, scene_dir: str | Path) -> int:
    """MPM steps per video frame of a scene (``meta["substeps"]``), for a simulation at time step ``dt`` [s].

    The video's frame interval is ``substeps * meta["dt"]``; simulated at another ``dt`` the same substeps would
    cover another interval and every frame would be compared with the wrong instant, silently. So a scene made at
    another ``dt`` than the one asked is refused with one line (a stale scene after ``scenes.<scene>.dt`` changed,
    or data reused by hand across a change).

    Raises:
        SceneDataError: ``meta["dt"]`` differs from ``dt`` (relative 1e-6).
    """
    substeps = int(meta["substeps"])
    made = meta.get("dt")
    if made is not None and abs(float(made) - float(dt)) > 1e-6 * float(dt):
        raise SceneDataError(f"{Path(scene_dir) / 'meta.json'}: the video was made at dt={float(made):g} s ({substeps} "
                             f"MPM steps per frame) but the simulation runs at dt={float(dt):g} s, so each frame would "
                             f"cover {float(dt) / float(made):g}x its interval; remake the scene (its ground_truth "
                             f"stage) or set scenes.<scene>.dt back")
    return substeps


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
    """Load and validate one view's frames (mask and depth are None: the scene directory holds neither)."""
    scene_dir = Path(scene_dir)
    meta = meta or read_meta(scene_dir)
    cameras = cameras or read_cameras(scene_dir)
    if view not in cameras:
        raise SceneDataError(f"{scene_dir / 'cameras.json'}: no camera for view {view!r} (have {sorted(cameras)})")
    camera, n = cameras[view], len(meta["video_frames"])
    rgb = _read_frames(view_dir(scene_dir, view) / "rgb", n, camera, 3).astype(np.float32) / 255.0
    return ViewData(view, camera, rgb)


def load_views(scene_dir: str | Path, views: Iterable[str]) -> dict[str, ViewData]:
    meta, cameras = read_meta(scene_dir), read_cameras(scene_dir)
    return {v: load_view(scene_dir, v, meta, cameras) for v in views}


def load_plate(scene_dir: str | Path, view: str = TRAIN_VIEW) -> np.ndarray | None:
    """The view's clean plate [H, W, 3] float32 in [0, 1], or None when the scene has none."""
    path = view_dir(scene_dir, view) / "plate.png"
    if not path.is_file():
        return None
    img = iio.imread(path)
    if img.ndim != 3 or img.shape[-1] < 3:
        raise SceneDataError(f"{path}: a plate must be an RGB image, got shape {img.shape}")
    return img[..., :3].astype(np.float32) / 255.0


def load_simulated_depth(scene_dir: str | Path, n_frames: int, view: str = TRAIN_VIEW) -> np.ndarray:
    """The simulated estimator's relative depth [T, H, W] written by the ground_truth stage."""
    path = view_dir(scene_dir, view) / "depth_sim.npy"
    if not path.is_file():
        raise SceneDataError(f"{path}: missing (the ground_truth stage writes it for vision.depth.backend: simulated)")
    depth = load_array(path, "simulated depth")
    if depth.ndim != 3 or len(depth) != n_frames:
        raise SceneDataError(f"{path}: shape {depth.shape}, expected [{n_frames}, H, W]")
    if not np.all(np.isfinite(depth)):
        raise SceneDataError(f"{path}: contains NaN/inf")
    return depth


def load_trajectory(scene_dir: str | Path) -> np.ndarray:
    """Ground-truth particle positions [T+1, P, 3] (evaluation only): read from the ground-truth directory
    bound to ``scene_dir`` (:func:`gca.scenes.truth.bind`); raises
    :class:`gca.scenes.truth.GroundTruthUnavailable` in a process that did not bind one."""
    from gca.scenes import truth

    return truth.load_trajectory(truth.bound_dir(scene_dir))
