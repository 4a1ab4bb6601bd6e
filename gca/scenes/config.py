"""Scene and video configuration: which object, which ground-truth material, camera, lighting, timing.

A *scene* is an object with a ground-truth material, an initial velocity, a camera rig (one
monocular training camera, extra training cameras for the multi-view reference rows, held-out
evaluation cameras), lighting interference and timing. All positions are in the simulation frame
(unit cube, metres, y up); the camera orbits ``target`` at ``distance``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from gca.capture.video import CaptureVideoConfig
from gca.config import OPTIONAL, ConfigError


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
        fps: > 0: the video's frame rate [1/s]; then each scene's frames are derived from its dt
            (:func:`scene_video`: one video frame per round(1 / (fps dt)) steps, for its duration) and
            ``n_frames``/``substeps``/``frame_every`` are ignored; 0: those three as given.
        duration_s: > 0: every scene's video duration [s]; 0: the scene's own ``duration_s``.
        max_duration_s: > 0: a cap on the duration (the CI profile's small size) [s].
        timing: the name of the ``video.timings`` variant these came from (recorded in meta.json).
    """

    n_frames: int = 200
    substeps: int = 2
    frame_every: int = 4
    resolution: int = 256
    background: tuple[float, float, float] = (0.75, 0.75, 0.75)
    mask_threshold: float = 0.5
    fps: float = 100.0
    duration_s: float = 0.0
    max_duration_s: float = 0.0
    timing: str = "real_100fps"

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
        duration_s: the video's duration when ``video.fps`` > 0 [s] (NeuMA's: 0.2 s pawn/cat/fish/bottle,
            0.4 s ball/duck; docs/benchmark.md states the others').
        calibration: a calibration scene (issue 21, item 5): for tuning only, in no table.
        capture: a capture scene (``kind: capture``, README "Your own object"): the user's video, camera and
            frame rate (:class:`gca.capture.video.CaptureVideoConfig`); its ``material`` is ``none`` (no
            ground-truth law) and its timing comes from the frame rate, not the ``video`` section.
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
    duration_s: float = dataclasses.field(default=0.0, metadata=OPTIONAL)  # 0: video.duration_s
    calibration: bool = dataclasses.field(default=False, metadata=OPTIONAL)
    capture: CaptureVideoConfig | None = dataclasses.field(default=None, metadata=OPTIONAL)

    @property
    def is_capture(self) -> bool:
        return self.capture is not None


def scene_video(video: VideoConfig, scene: SceneConfig) -> VideoConfig:
    """The video timing of one scene: with ``video.fps`` > 0, one video frame per ``round(1 / (fps dt))`` MPM
    steps of the scene's dt (the realised rate is ``1 / (steps dt)``), ``frame_every = 1``, for the scene's
    duration (``video.duration_s`` or ``scene.duration_s``, capped by ``video.max_duration_s``). Idempotent."""
    if video.fps <= 0:
        return video
    steps = max(1, int(round(1.0 / (video.fps * scene.dt))))
    duration = video.duration_s or scene.duration_s
    if duration <= 0:
        raise ConfigError(f"params: video.fps = {video.fps} needs a duration: set video.duration_s or the scene's "
                          f"duration_s (scene of object {scene.object!r})")
    if video.max_duration_s > 0:
        duration = min(duration, video.max_duration_s)
    n = max(1, int(round(duration / (steps * scene.dt))))
    return dataclasses.replace(video, fps=0.0, n_frames=n, substeps=steps, frame_every=1)
