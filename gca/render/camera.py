"""Pinhole cameras in the OpenCV convention (x right, y down, z forward).

A :class:`Camera` holds the intrinsics ``K`` (pixels) and the world-to-camera pose ``w2c`` (4x4).
Pixel ``(i, j)`` (column, row) covers ``[i, i+1] x [j, j+1]`` in image coordinates and its centre
is ``(i + 0.5, j + 0.5)`` (the 3DGS / gsplat convention), so a centred camera has
``cx = width / 2``, ``cy = height / 2``. Depth is camera-space ``z`` in the units of the frame the
camera lives in (the renderer gets sim-frame Gaussians and a sim-frame camera).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np
import torch

_WHERE = "gca/render/camera.py"


class CameraError(ValueError):
    """An invalid camera (names the file and the problem)."""


def _as_matrix(value: Any, shape: tuple[int, int], name: str) -> np.ndarray:
    array = np.array(value, dtype=np.float64, copy=True)
    if array.shape != shape:
        raise CameraError(f"{_WHERE}: {name} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise CameraError(f"{_WHERE}: {name} has non-finite entries")
    array.setflags(write=False)
    return array


def _check_K(K: np.ndarray) -> None:
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CameraError(f"{_WHERE}: K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise CameraError(f"{_WHERE}: K must be upper triangular with last row (0, 0, 1), got\n{K}")


def _check_w2c(w2c: np.ndarray) -> None:
    if not np.allclose(w2c[3], [0.0, 0.0, 0.0, 1.0]):
        raise CameraError(f"{_WHERE}: w2c last row must be (0, 0, 0, 1), got {w2c[3]}")
    R = w2c[:3, :3]
    if abs(np.linalg.det(R)) < 1e-9:
        raise CameraError(f"{_WHERE}: w2c is not invertible (det of its 3x3 block = {np.linalg.det(R):.3g})")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise CameraError(f"{_WHERE}: w2c rotation block is not a proper rotation (R R^T != I or det < 0)")


def _indexed(device: torch.device | str) -> torch.device:
    """``device`` with its index: a bare "cuda" is the current CUDA device (a kept tensor must not follow another)."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", torch.cuda.current_device())
    return device


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera.

    Attributes:
        K: intrinsics [3, 3] in pixels (fx, fy > 0, pixel centres at i + 0.5).
        w2c: world-to-camera rigid transform [4, 4], OpenCV axes (x right, y down, z forward).
        width: image width [pixels].
        height: image height [pixels].
    """

    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    # ("K, w2c" | "center", dtype, device) -> the tensors, made once (:meth:`_kept`): a tensor made from host data on
    # CUDA is a copy that synchronises the stream, and a training renders every frame through this camera (NOTES s39)
    _tensors: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _as_matrix(self.K, (3, 3), "K"))
        object.__setattr__(self, "w2c", _as_matrix(self.w2c, (4, 4), "w2c"))
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or value <= 0:
                raise CameraError(f"{_WHERE}: {name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        _check_K(self.K)
        _check_w2c(self.w2c)

    def __getstate__(self) -> dict:
        """Pickled without the tensors kept by :meth:`tensors` (a CUDA tensor would not load where CUDA is absent)."""
        return {**self.__dict__, "_tensors": {}}

    @property
    def c2w(self) -> np.ndarray:
        """Camera-to-world transform [4, 4]."""
        return np.linalg.inv(self.w2c)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates [3]."""
        return self.c2w[:3, 3]

    def tensors(self, dtype: torch.dtype = torch.float32,
                device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """Return ``(K [3, 3], w2c [4, 4])`` as torch tensors of the given dtype/device, made on the first call for that
        dtype and device and the same tensors after (not to be written to): on CUDA each new one would be a host copy
        that waits for the GPU, four a rendered frame (NOTES session 39)."""
        return self._kept("K, w2c", dtype, device, lambda: (self.K, self.w2c))

    def center_tensor(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
        """The camera centre in world coordinates [3] as a tensor, made once per dtype and device (:meth:`tensors`)."""
        return self._kept("center", dtype, device, lambda: (self.center,))[0]

    def _kept(self, name: str, dtype: torch.dtype, device: torch.device | str, arrays) -> tuple[torch.Tensor, ...]:
        """The tensors of the arrays ``arrays()`` gives (a tuple) on ``device`` in ``dtype``, made on the first call for
        ``name`` there and kept: outside inference mode (made under it they could never enter a training graph), on
        an indexed device (a bare "cuda" kept must not follow another current device)."""
        key = (name, dtype, _indexed(device))
        if key not in self._tensors:
            with torch.inference_mode(False):
                self._tensors[key] = tuple(torch.tensor(a.tolist(), dtype=dtype, device=key[2]) for a in arrays())
        return self._tensors[key]

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points [..., N, 3] -> camera-frame points [..., N, 3] (OpenCV axes, z forward) [m]."""
        _, w2c = self.tensors(points.dtype, points.device)
        return points @ w2c[:3, :3].T + w2c[:3, 3]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project world points to pixel coordinates.

        Args:
            points: world positions [N, 3].

        Returns:
            ``(uv [N, 2] pixels, z [N] camera-space depth)``.
        """
        assert points.ndim == 2 and points.shape[1] == 3, f"points must be [N, 3], got {tuple(points.shape)}"
        K, _ = self.tensors(points.dtype, points.device)
        x_cam = self.to_camera(points)
        z = x_cam[:, 2]
        uv = (x_cam[:, :2] / z[:, None]) * K.diagonal()[:2] + K[:2, 2]
        return uv, z

    def to_dict(self) -> dict:
        """JSON-ready dict (lists of floats)."""
        return {"K": self.K.tolist(), "w2c": self.w2c.tolist(), "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, mapping: Mapping) -> "Camera":
        """Inverse of :meth:`to_dict`; unknown or missing keys are errors."""
        keys = {"K", "w2c", "width", "height"}
        if not isinstance(mapping, Mapping) or set(mapping) != keys:
            got = sorted(mapping) if isinstance(mapping, Mapping) else type(mapping).__name__
            raise CameraError(f"{_WHERE}: camera dict needs exactly keys {sorted(keys)}, got {got}")
        return cls(K=mapping["K"], w2c=mapping["w2c"], width=mapping["width"], height=mapping["height"])


def intrinsics(fov_deg: float, width: int, height: int) -> np.ndarray:
    """Centred pinhole intrinsics [3, 3] with horizontal field of view ``fov_deg`` and square pixels."""
    if not 0.0 < fov_deg < 180.0:
        raise CameraError(f"{_WHERE}: fov_deg must be in (0, 180), got {fov_deg}")
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def look_at(eye, target, up, fov_deg: float, width: int, height: int) -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image.

    Args:
        eye: camera centre [3] (world).
        target: point the optical axis passes through [3] (world).
        up: world up direction [3]; image y (down) is aligned with ``-up``.
        fov_deg: horizontal field of view [degrees].
        width: image width [pixels].
        height: image height [pixels].

    Returns:
        The :class:`Camera` (OpenCV axes: z = forward, x = right, y = down).
    """
    eye, target, up = (np.asarray(a, dtype=np.float64).reshape(3) for a in (eye, target, up))
    forward = target - eye
    if np.linalg.norm(forward) < 1e-12:
        raise CameraError(f"{_WHERE}: look_at eye and target coincide ({eye})")
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9 * max(np.linalg.norm(up), 1e-12):
        raise CameraError(f"{_WHERE}: look_at up {up} is parallel to the viewing direction {z}")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return Camera(K=intrinsics(fov_deg, width, height), w2c=w2c, width=width, height=height)
