"""Cameras as capture tools write them, read into :class:`gca.render.camera.Camera` (OpenCV convention).

Every reader returns ``{image name: Camera}`` with intrinsics ``K`` [3, 3] in pixels (pixel centres
at i + 0.5, as COLMAP and nerfstudio also place them) and the world-to-camera pose ``w2c`` [4, 4] in
OpenCV axes (x right, y down, z forward), in the frame and units of the capture (the scan's frame
when the scan and the camera come from one reconstruction).

- COLMAP text model (``cameras.txt`` + ``images.txt``; ``colmap model_converter --output_type TXT``
  turns a binary model into it; :func:`read_colmap_binary` reads ``cameras.bin`` + ``images.bin``):
  ``images.txt`` stores the world-to-camera rotation as a quaternion (qw, qx, qy, qz) and the
  translation, already in OpenCV axes. Models SIMPLE_PINHOLE, PINHOLE and, with zero distortion,
  SIMPLE_RADIAL, RADIAL, OPENCV; frames with lens distortion must be undistorted first
  (``colmap image_undistorter`` writes PINHOLE cameras).
- nerfstudio / Blender ``transforms.json``: ``transform_matrix`` is camera-to-world in **OpenGL**
  axes (x right, y up, z backward); we flip y and z: ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``.
  Intrinsics ``fl_x, fl_y, cx, cy, w, h`` (top level or per frame) or Blender's ``camera_angle_x``
  (then ``w, h`` are needed and the principal point is the image centre).

:func:`transform_camera` moves a camera along a similarity of the world (the scan's
``object_from_scan`` import, then the particles' ``sim_from_world``); :func:`rescale` adapts the
intrinsics to frames of another resolution.
"""

from __future__ import annotations

import json
import math
import os
import struct
from pathlib import Path

import numpy as np

from gca.assets.ply import quats_to_rotmats
from gca.render.camera import Camera, CameraError

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips the camera's y and z axes
# COLMAP camera models: id -> (name, number of params); the distortion params follow fx fy cx cy
COLMAP_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12)}


class CaptureError(ValueError):
    """An unusable camera or capture file (one line naming the file and the problem)."""


def _K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _colmap_intrinsics(model: str, params: list[float], where: str) -> np.ndarray:
    """K [3, 3] of a COLMAP camera; refuses lens distortion (undistort the frames first)."""
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = params[:3]
        return _K(f, f, cx, cy)
    if model == "PINHOLE":
        return _K(*params[:4])
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy, *dist = params
        K = _K(f, f, cx, cy)
    elif model == "OPENCV":
        *fc, k1, k2, p1, p2 = params
        K, dist = _K(*fc), [k1, k2, p1, p2]
    else:
        raise CaptureError(f"{where}: COLMAP camera model {model} is not supported (PINHOLE, SIMPLE_PINHOLE, or "
                           f"undistort the frames with `colmap image_undistorter`)")
    if any(abs(d) > 1e-9 for d in dist):
        raise CaptureError(f"{where}: COLMAP camera model {model} has lens distortion {dist}: undistort the frames "
                           f"first (`colmap image_undistorter` writes PINHOLE cameras)")
    return K


def _w2c(qvec, tvec) -> np.ndarray:
    q = np.asarray(qvec, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = quats_to_rotmats((q / np.linalg.norm(q))[None])[0]
    T[:3, 3] = tvec
    return T


def _camera(K, w2c, width, height, where: str) -> Camera:
    try:
        return Camera(K=K, w2c=w2c, width=int(width), height=int(height))
    except CameraError as exc:
        raise CaptureError(f"{where}: {str(exc).split(': ', 1)[-1]}") from None


def _lines(path: Path) -> list[tuple[int, list[str]]]:
    if not path.is_file():
        raise CaptureError(f"{path}: file not found")
    return [(n, line.split()) for n, line in enumerate(path.read_text().splitlines(), 1)
            if line.strip() and not line.lstrip().startswith("#")]


def read_colmap_text(folder: str | os.PathLike) -> dict[str, Camera]:
    """``{image name: Camera}`` from ``<folder>/cameras.txt`` and ``<folder>/images.txt``.

    ``images.txt`` holds two lines per image (pose, then 2D points, possibly empty); both are read.
    """
    folder = Path(folder)
    intr: dict[int, tuple] = {}
    for n, f in _lines(folder / "cameras.txt"):
        where = f"{folder / 'cameras.txt'}:{n}"
        try:
            intr[int(f[0])] = (_colmap_intrinsics(f[1], [float(v) for v in f[4:]], where), int(f[2]), int(f[3]))
        except (IndexError, ValueError) as exc:
            if isinstance(exc, CaptureError):
                raise
            raise CaptureError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {' '.join(f)!r}") from None
    path = folder / "images.txt"
    text = path.read_text().splitlines() if path.is_file() else None
    if text is None:
        raise CaptureError(f"{path}: file not found")
    cams, expect_points = {}, False
    for n, line in enumerate(text, 1):
        if line.lstrip().startswith("#"):
            continue
        if expect_points:  # the 2D points line (may be empty)
            expect_points = False
            continue
        f = line.split()
        if not f:
            continue
        where = f"{path}:{n}"
        try:
            qvec, tvec, cam_id, name = [float(v) for v in f[1:5]], [float(v) for v in f[5:8]], int(f[8]), f[9]
        except (IndexError, ValueError):
            raise CaptureError(f"{where}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {line!r}") from None
        if cam_id not in intr:
            raise CaptureError(f"{where}: camera {cam_id} is not in cameras.txt")
        K, w, h = intr[cam_id]
        cams[name] = _camera(K, _w2c(qvec, tvec), w, h, where)
        expect_points = True
    if not cams:
        raise CaptureError(f"{path}: no image")
    return cams


def read_colmap_binary(folder: str | os.PathLike) -> dict[str, Camera]:
    """``{image name: Camera}`` from ``<folder>/cameras.bin`` and ``<folder>/images.bin`` (COLMAP's
    binary model, little-endian; layout of COLMAP's ``WriteCamerasBinary`` / ``WriteImagesBinary``)."""
    folder = Path(folder)
    intr = {}
    path = folder / "cameras.bin"
    if not path.is_file():
        raise CaptureError(f"{path}: file not found")
    try:
        with open(path, "rb") as fh:
            for _ in range(struct.unpack("<Q", fh.read(8))[0]):
                cam_id, model_id, w, h = struct.unpack("<iiQQ", fh.read(24))
                if model_id not in COLMAP_MODELS:
                    raise CaptureError(f"{path}: camera {cam_id}: unknown COLMAP model id {model_id}")
                name, n_params = COLMAP_MODELS[model_id]
                params = list(struct.unpack(f"<{n_params}d", fh.read(8 * n_params)))
                intr[cam_id] = (_colmap_intrinsics(name, params, f"{path} (camera {cam_id})"), w, h)
        path = folder / "images.bin"
        if not path.is_file():
            raise CaptureError(f"{path}: file not found")
        cams = {}
        with open(path, "rb") as fh:
            for _ in range(struct.unpack("<Q", fh.read(8))[0]):
                values = struct.unpack("<idddddddi", fh.read(64))
                name = b""
                while (c := fh.read(1)) not in (b"\x00", b""):
                    name += c
                n_points = struct.unpack("<Q", fh.read(8))[0]
                fh.seek(24 * n_points, os.SEEK_CUR)
                if values[8] not in intr:
                    raise CaptureError(f"{path}: image {name.decode()!r}: camera {values[8]} is not in cameras.bin")
                K, w, h = intr[values[8]]
                cams[name.decode()] = _camera(K, _w2c(values[1:5], values[5:8]), w, h, f"{path} ({name.decode()})")
    except struct.error:
        raise CaptureError(f"{path}: truncated or not a COLMAP binary model") from None
    return cams


def read_transforms_json(path: str | os.PathLike) -> dict[str, Camera]:
    """``{file_path: Camera}`` from a nerfstudio / Blender ``transforms.json`` (OpenGL c2w converted)."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CaptureError(f"{path}: malformed JSON ({exc})") from None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not frames:
        raise CaptureError(f"{path}: no 'frames' list")
    cams = {}
    for i, frame in enumerate(frames):
        where = f"{path} (frames[{i}])"
        get = lambda k, default=None: frame.get(k, data.get(k, default))  # noqa: E731
        w, h = get("w"), get("h")
        if w is None or h is None:
            raise CaptureError(f"{where}: needs the image size 'w' and 'h'")
        if get("fl_x") is not None:
            fx = float(get("fl_x"))
            fy = float(get("fl_y", fx))
            K = _K(fx, fy, float(get("cx", w / 2)), float(get("cy", h / 2)))
        elif get("camera_angle_x") is not None:
            fx = 0.5 * w / math.tan(0.5 * float(get("camera_angle_x")))
            fy = 0.5 * h / math.tan(0.5 * float(get("camera_angle_y"))) if get("camera_angle_y") is not None else fx
            K = _K(fx, fy, w / 2, h / 2)
        else:
            raise CaptureError(f"{where}: no intrinsics ('fl_x' or 'camera_angle_x')")
        if any(abs(float(get(k, 0.0))) > 1e-9 for k in ("k1", "k2", "k3", "k4", "p1", "p2")):
            raise CaptureError(f"{where}: lens distortion (k1.. p2) is not supported: undistort the frames first")
        try:
            c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
            name = str(frame["file_path"])
        except KeyError as exc:
            raise CaptureError(f"{where}: missing {exc.args[0]!r}") from None
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0, 0, 0, 1]])
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise CaptureError(f"{where}: transform_matrix must be a finite 4x4 (or 3x4) matrix")
        cams[name] = _camera(K, np.linalg.inv(c2w @ OPENGL_TO_OPENCV), w, h, where)
    return cams


def write_transforms_json(path: str | os.PathLike, cameras: dict[str, Camera], extra: dict | None = None) -> Path:
    """Write ``{file_path: Camera}`` as a nerfstudio ``transforms.json`` (per-frame intrinsics; atomic)."""
    from gca import io

    frames = [{"file_path": name, "w": c.width, "h": c.height, "fl_x": c.K[0, 0], "fl_y": c.K[1, 1],
               "cx": c.K[0, 2], "cy": c.K[1, 2], "transform_matrix": (c.c2w @ OPENGL_TO_OPENCV).tolist()}
              for name, c in cameras.items()]
    return io.write_json(path, {**(extra or {}), "camera_model": "OPENCV", "frames": frames})


def transform_camera(camera: Camera, A: np.ndarray) -> Camera:
    """The same camera in the frame x' = A x of a similarity A [4, 4] (A[:3, :3] = s Q, s > 0).

    A point and its image stay put: camera coordinates scale by s (depth in the new units),
    ``w2c' = [R Q^T, s t - R Q^T a]`` for ``w2c = [R, t]`` and ``A = [s Q, a]``.
    """
    A = np.asarray(A, dtype=np.float64)
    s = float(np.cbrt(np.linalg.det(A[:3, :3])))
    if not s > 0:
        raise CaptureError(f"transform_camera: not a similarity with positive scale (det {np.linalg.det(A[:3, :3])})")
    Q = A[:3, :3] / s
    R, t = camera.w2c[:3, :3], camera.w2c[:3, 3]
    w2c = np.eye(4)
    w2c[:3, :3] = R @ Q.T
    w2c[:3, 3] = s * t - R @ Q.T @ A[:3, 3]
    return Camera(K=camera.K, w2c=w2c, width=camera.width, height=camera.height)


def rescale(camera: Camera, width: int, height: int) -> Camera:
    """The camera for frames resized to ``width`` x ``height`` pixels (K scaled per axis, pixel centres kept)."""
    sx, sy = width / camera.width, height / camera.height
    K = camera.K.copy()
    K[0] *= sx
    K[1] *= sy
    return Camera(K=K, w2c=camera.w2c, width=width, height=height)
