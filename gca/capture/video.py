"""The capture scene kind: a user's video of the object (frames, camera, frame rate) as it comes.

params.yaml::

    scenes:
      myscene:
        object: donut                 # a capture object (objects.<name> with a scan)
        kind: capture
        material: none                # no ground-truth law (materials.none is the empty placeholder)
        prior: jelly                  # the neural prior family the learned law starts from
        dt: 1.0e-3                    # MPM time step [s]; substeps per frame = round(1 / (fps dt))
        methods: [gca]
        capture:
          video: captures/donut/frames        # folder of frames (.png/.jpg, sorted by name), any resolution
          camera: captures/donut/transforms.json   # COLMAP model folder | transforms.json | {K, w2c, width, height}
          frame: ""                   # which entry of a multi-camera file ("" = the only or first one)
          fps: 30.0                   # the video's frame rate [1/s]
          plate: ""                   # optional image of the empty scene ("" = median of the frames)
          heldout_fraction: 0.25      # the last quarter of the frames is held out for evaluation
          depth: transformers         # transformers (Depth Anything, local weights) | silhouette (fallback)

The camera is calibrated in the *scan's* frame (the frame of ``objects.<name>.scan``); the ground_truth
stage brings it to the simulation frame through ``object_from_scan`` and ``sim_from_world``
(:func:`gca.capture.cameras.transform_camera`). Every problem names the file and the problem in one line
(:class:`gca.capture.cameras.CaptureError`).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from PIL import Image

from gca.capture.cameras import CaptureError, read_colmap_binary, read_colmap_text, read_transforms_json
from gca.render.camera import Camera

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_CHOICES = ("transformers", "silhouette")


@dataclasses.dataclass(frozen=True)
class CaptureVideoConfig:
    """``scenes.<name>.capture`` (module docstring)."""

    video: str  # folder of frames
    camera: Any  # COLMAP folder | transforms.json | {K: 3x3 [px], w2c: 4x4 (OpenCV), width, height}
    fps: float  # frame rate [1/s]
    frame: str = ""  # entry of a multi-camera file ("" = the only or first)
    plate: str = ""  # empty-scene image ("" = median of the frames)
    heldout_fraction: float = 0.25  # last share of the frames held out for evaluation [1]
    depth: str = "transformers"  # transformers | silhouette

    def __post_init__(self):
        bad = []
        if not self.fps > 0:
            bad.append(f"fps={self.fps} (> 0 frames/s)")
        if not 0.0 <= self.heldout_fraction < 1.0:
            bad.append(f"heldout_fraction={self.heldout_fraction} (in [0, 1))")
        if self.depth not in DEPTH_CHOICES:
            bad.append(f"depth={self.depth!r} (one of {DEPTH_CHOICES})")
        if bad:
            raise CaptureError(f"params capture: invalid {'; '.join(bad)}")


def split_heldout(n_frames: int, fraction: float) -> int:
    """Training frames of an ``n_frames`` video whose last ``fraction`` is held out (>= 2 kept for training)."""
    n_train = n_frames - int(round(fraction * n_frames))
    if n_train < 2:
        raise CaptureError(f"capture: {n_frames} frames leave {n_train} for training after holding out "
                           f"{fraction:.0%}; need >= 2 (more frames or a smaller heldout_fraction)")
    return n_train


def frame_files(folder: str | os.PathLike) -> list[Path]:
    """The frame images of ``folder`` sorted by name; one-line errors for a missing or empty folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder}: video folder not found (scenes.<name>.capture.video)")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(files) < 2:
        raise CaptureError(f"{folder}: {len(files)} frame images ({'/'.join(IMAGE_SUFFIXES)}); a video needs >= 2")
    return files


def read_image(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """RGB uint8 [H, W, 3] of one image, resized to ``size`` = (W, H) when given."""
    try:
        with Image.open(path) as img:
            img = img.convert("RGB")
            if size is not None and img.size != size:
                img = img.resize(size, Image.BILINEAR)
            return np.asarray(img, dtype=np.uint8)
    except (OSError, ValueError) as exc:
        raise CaptureError(f"{path}: not a readable image ({exc})") from None


def read_frames(folder: str | os.PathLike, max_side: int = 0) -> tuple[list[str], np.ndarray, tuple[int, int]]:
    """(file names, frames uint8 [T, H, W, 3], native (W, H)) of a video folder; frames downscaled so the
    longer side is at most ``max_side`` pixels (0: native). All frames must share one size."""
    files = frame_files(folder)
    with Image.open(files[0]) as first:
        native = first.size
    w, h = native
    if max_side and max(w, h) > max_side:
        k = max_side / max(w, h)
        w, h = max(1, int(round(w * k))), max(1, int(round(h * k)))
    frames = []
    for path in files:
        with Image.open(path) as img:
            if img.size != native:
                raise CaptureError(f"{path}: frame is {img.size[0]}x{img.size[1]}, the first frame "
                                   f"({files[0].name}) is {native[0]}x{native[1]}; frames must share one size")
        frames.append(read_image(path, (w, h)))
    return [p.name for p in files], np.stack(frames), native


def _pick(cams: dict[str, Camera], frame: str, where: str) -> Camera:
    if not cams:
        raise CaptureError(f"{where}: no camera in the file")
    if not frame:
        return cams[sorted(cams)[0]]
    hits = [k for k in cams if k == frame or Path(k).name == frame or Path(k).stem == frame]
    if not hits:
        raise CaptureError(f"{where}: no camera named {frame!r} (have {sorted(cams)[:5]}...)")
    return cams[hits[0]]


def read_camera(spec: Any, frame: str = "", root: str | os.PathLike = ".") -> Camera:
    """The video's camera (OpenCV convention, in the scan's frame) from ``capture.camera``: a COLMAP model
    folder (``cameras.txt``/``images.txt`` or ``.bin``), a ``transforms.json``, or a mapping
    ``{K: [3x3] px, w2c: [4x4], width, height}``."""
    if isinstance(spec, Mapping):
        try:
            return Camera(K=np.asarray(spec["K"], dtype=np.float64), w2c=np.asarray(spec["w2c"], dtype=np.float64),
                          width=int(spec["width"]), height=int(spec["height"]))
        except KeyError as exc:
            raise CaptureError(f"params capture.camera: missing {exc.args[0]!r} (K, w2c, width, height)") from None
        except ValueError as exc:
            raise CaptureError(f"params capture.camera: {exc}") from None
    path = Path(root) / str(spec)
    if path.is_dir():
        if (path / "cameras.txt").is_file():
            return _pick(read_colmap_text(path), frame, str(path))
        if (path / "cameras.bin").is_file():
            return _pick(read_colmap_binary(path), frame, str(path))
        raise CaptureError(f"{path}: a camera folder must hold a COLMAP model (cameras.txt/images.txt or .bin)")
    if path.suffix == ".json":
        return _pick(read_transforms_json(path), frame, str(path))
    raise CaptureError(f"{path}: camera file not found (a COLMAP folder or a transforms.json)")


def median_plate(frames: np.ndarray) -> np.ndarray:
    """Estimated empty-scene image [H, W, 3] uint8: the per-pixel median of the frames [T, H, W, 3] (the
    object moves, so each pixel shows the background in most frames)."""
    return np.median(frames, axis=0).round().astype(np.uint8)
