"""Scene and video configuration: which object, which ground-truth material, camera, lighting, timing.

A *scene* is an object with a ground-truth material, an initial velocity, a camera rig (one
monocular training camera, extra training cameras for the multi-view reference rows, held-out
evaluation cameras), lighting interference and timing. All positions are in the simulation frame
(unit cube, metres, y up); the camera orbits ``target`` at ``distance``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping, Sequence

import numpy as np

from gca.config import OPTIONAL, ConfigError, build


@dataclasses.dataclass(frozen=True)
class OrbitCamera:
    """A camera on a sphere around ``target`` (sim frame), looking at it, y up.

    Attributes:
        azimuth_deg: rotation about +y from the +z axis [deg].
        elevation_deg: angle above the horizontal plane [deg].
        distance: distance from ``target`` [m, sim units].
        fov_deg: vertical field of view [deg].
        target: look-at point [m, sim frame].
    """

    azimuth_deg: float = 0.0
    elevation_deg: float = 15.0
    distance: float = 1.6
    fov_deg: float = 40.0
    target: tuple[float, float, float] = (0.5, 0.3, 0.5)

    def __post_init__(self):
        object.__setattr__(self, "target", tuple(float(t) for t in self.target))

    def eye(self) -> np.ndarray:
        """Camera centre [3] in the sim frame."""
        az, el = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
        offset = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        return np.asarray(self.target, dtype=np.float64) + self.distance * offset


@dataclasses.dataclass(frozen=True)
class VideoConfig:
    """Timing and image settings shared by all scenes.

    Attributes:
        n_frames: simulated frames (each is ``substeps`` MPM steps).
        substeps: MPM steps per simulated frame.
        frame_every: the video keeps every k-th simulated frame (reduced frame rate).
        resolution: square image size [pixels].
        background: RGB background in [0, 1].
        mask_threshold: alpha above which a pixel belongs to the object mask.
    """

    n_frames: int = 200
    substeps: int = 2
    frame_every: int = 4
    resolution: int = 256
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    mask_threshold: float = 0.5

    def video_frames(self) -> list[int]:
        """Simulated-frame indices (1-based, after each frame's steps) kept in the video."""
        return list(range(self.frame_every, self.n_frames + 1, self.frame_every))


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """One scene of the benchmark.

    Attributes:
        object: object name (``objects.<name>`` in params).
        material: ground-truth material preset name (``materials.<name>``).
        prior: neural prior family the learned law starts from (``jelly``, ``plasticine``, ``sand``, ``fluid``).
        kind: ``synthetic``, ``real_to_sim`` or ``composite``.
        dt: MPM time step [s].
        v0: initial linear velocity [m/s], sim frame.
        w0: initial angular velocity about the centre of mass [rad/s].
        camera: the monocular training camera.
        extra_train_cameras: two more training cameras (multi-view reference rows).
        eval_cameras: held-out cameras for rendering metrics.
        light_seed: seed of the per-frame lighting interference.
        methods: the methods (table rows) trained on this scene.
        cpr_target: (elastic, plastic) CPR hypotheses closest to the true law; the
            ``cpr_target_removed`` method drops them from CPR's library.
        law_level: evaluate the law-level response error against the analytic ground truth.
    """

    object: str
    material: str
    prior: str
    kind: str = "synthetic"
    dt: float = 5e-4
    v0: tuple[float, float, float] = (0.0, -1.0, 0.0)
    w0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    camera: OrbitCamera = OrbitCamera()
    extra_train_cameras: tuple[OrbitCamera, ...] = dataclasses.field(default=(), metadata=OPTIONAL)
    eval_cameras: tuple[OrbitCamera, ...] = ()
    light_seed: int = 0
    methods: tuple[str, ...] = ("gca", "neuma", "nclaw")
    cpr_target: tuple[str, str] = ("corotated", "identity")
    law_level: bool = dataclasses.field(default=False, metadata=OPTIONAL)


def _cameras(items: Sequence[Mapping] | None, where: str) -> tuple[OrbitCamera, ...]:
    return tuple(build(OrbitCamera, c, f"{where}[{i}]", partial=True) for i, c in enumerate(items or ()))


def scene_config(params: Mapping, scene: str) -> SceneConfig:
    """Build the :class:`SceneConfig` of ``scene`` from resolved params (``scenes.<scene>``)."""
    scenes = params.get("scenes", {})
    if scene not in scenes:
        raise ConfigError(f"params: unknown scene {scene!r}; known scenes: {sorted(scenes)}")
    raw = dict(scenes[scene])
    where = f"scenes.{scene}"
    raw["camera"] = build(OrbitCamera, raw.get("camera", {}), f"{where}.camera", partial=True)
    raw["extra_train_cameras"] = _cameras(raw.get("extra_train_cameras"), f"{where}.extra_train_cameras")
    raw["eval_cameras"] = _cameras(raw.get("eval_cameras"), f"{where}.eval_cameras")
    return build(SceneConfig, raw, where)


def video_config(params: Mapping) -> VideoConfig:
    raw = dict(params.get("video", {}))
    if "background" in raw:
        raw["background"] = tuple(raw["background"])
    return build(VideoConfig, raw, "video")
