"""The Spring-Gaus real-capture dataset's layout (Zhong et al., ECCV 2024), read one view for training.

GCA's real-world experiment uses this dataset with **one** of its three fixed video cameras for
training, as the paper does; the other two are returned only as held-out views for evaluation. The
layout (as its public loader, ``lib/datasets/real_capture.py`` of Colmar-zlicheng/Spring-Gaus, reads it)::

    <root>/static/colmap/<obj>/cameras.bin, images.bin   COLMAP model of the multi-view static photos
    <root>/static/images/<obj>/*.JPG, static/masks/<obj>/*.png
    <root>/dynamic/cameras_calib.json                   {camera: {"rvecs": [3], "tvecs": [3]}}: the video
                                                        cameras' world-to-camera pose, OpenCV Rodrigues
                                                        vector + translation, in the COLMAP frame
    <root>/dynamic/sync.json                            the cameras' synchronisation (not needed here)
    <root>/dynamic/sequences/<obj>/<seq>.json           {"hit_frame": int, "<camera>": [frame file names]}
    <root>/dynamic/videos_images/<camera>/<name>.jpg    the video frames
    <root>/dynamic/videos_masks/<camera>/<name>.png     their object masks

The video cameras' intrinsics are not stored: the static COLMAP camera's focal lengths are scaled
from the photo size (W_S x H_S, the COLMAP camera's) to the video size (W x H, read from the first
frame), with the principal point at the video frame's centre. The videos run at 120 frames/s
(``FREQ`` in its configs).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from gca.capture.cameras import CaptureError, read_colmap_binary
from gca.render.camera import Camera

VIDEO_CAMERAS = ("C0733", "C0787", "C0801")  # the dataset's three video cameras
FPS = 120.0  # video frame rate [frames/s]


@dataclasses.dataclass(frozen=True)
class ViewFrames:
    """One video camera of a sequence: its camera (COLMAP frame, OpenCV axes) and frame/mask paths."""

    name: str
    camera: Camera
    frames: list[Path]
    masks: list[Path]


@dataclasses.dataclass(frozen=True)
class SpringGausSequence:
    """One object's sequence: the training view, the held-out views, timing.

    Attributes:
        train: the one view training sees.
        held_out: the other views (evaluation only).
        hit_frame: the frame index where the object hits the ground (from the sequence file).
        fps: frame rate [frames/s].
    """

    train: ViewFrames
    held_out: list[ViewFrames]
    hit_frame: int
    fps: float


def _json(path: Path):
    if not path.is_file():
        raise CaptureError(f"{path}: file not found (not a Spring-Gaus real_capture folder?)")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CaptureError(f"{path}: malformed JSON ({exc})") from None


def load_sequence(root: str | os.PathLike, obj: str, seq: int | str = 0, train_view: str = VIDEO_CAMERAS[0],
                  fps: float = FPS) -> SpringGausSequence:
    """Read one sequence of the Spring-Gaus real-capture layout (module docstring).

    Args:
        root: the dataset folder (``DATA_ROOT``, holding ``static/`` and ``dynamic/``).
        obj: the object (``bun``, ``burger``, ``dog``, ``pig``, ``potato``).
        seq: the sequence number.
        train_view: the one camera used for training; the others are held out.
        fps: the videos' frame rate [frames/s].

    Raises:
        CaptureError: a missing file or camera, or a frame without its mask (named).
    """
    root = Path(root)
    static = read_colmap_binary(root / "static" / "colmap" / obj)
    photo = next(iter(static.values()))  # every static photo shares COLMAP camera 1
    calib = _json(root / "dynamic" / "cameras_calib.json")
    seq_path = root / "dynamic" / "sequences" / obj / f"{seq}.json"
    info = _json(seq_path)
    names = [c for c in VIDEO_CAMERAS if c in info]
    if train_view not in names:
        raise CaptureError(f"{seq_path}: no frame list for the training camera {train_view!r} (has {names})")
    views = {}
    for cam in names:
        if cam not in calib or not {"rvecs", "tvecs"} <= set(calib[cam]):
            raise CaptureError(f"{root / 'dynamic/cameras_calib.json'}: no 'rvecs'/'tvecs' for camera {cam!r}")
        frames = [root / "dynamic" / "videos_images" / cam / f for f in info[cam]]
        masks = [root / "dynamic" / "videos_masks" / cam / (Path(f).stem + ".png") for f in info[cam]]
        missing = [p for p in frames + masks if not p.is_file()]
        if missing:
            raise CaptureError(f"{missing[0]}: file not found ({len(missing)} frame/mask files missing for camera {cam})")
        with Image.open(frames[0]) as im:
            W, H = im.size
        K = np.array([[photo.K[0, 0] * W / photo.width, 0.0, W / 2], [0.0, photo.K[1, 1] * H / photo.height, H / 2],
                      [0.0, 0.0, 1.0]])
        w2c = np.eye(4)
        w2c[:3, :3] = Rotation.from_rotvec(np.asarray(calib[cam]["rvecs"], dtype=np.float64).reshape(3)).as_matrix()
        w2c[:3, 3] = np.asarray(calib[cam]["tvecs"], dtype=np.float64).reshape(3)
        views[cam] = ViewFrames(cam, Camera(K=K, w2c=w2c, width=W, height=H), frames, masks)
    return SpringGausSequence(train=views[train_view], held_out=[v for c, v in views.items() if c != train_view],
                              hit_frame=int(info.get("hit_frame", 0)), fps=float(fps))
