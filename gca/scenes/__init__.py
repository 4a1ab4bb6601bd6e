"""Scenes: configuration, the simulate-and-render world, ground-truth videos, on-disk layout.

``store`` is the training-visible scene directory (frames, cameras); ``truth`` the ground-truth-only
directory that evaluation alone reads."""

from gca.scenes.config import OrbitCamera, SceneConfig, VideoConfig, scene_video
from gca.scenes.store import (TRAIN_VIEW, SceneDataError, ViewData, load_simulated_depth, load_trajectory, load_view,
                              load_views, read_meta)

__all__ = ["OrbitCamera", "SceneConfig", "VideoConfig", "scene_video", "TRAIN_VIEW",
           "SceneDataError", "ViewData", "load_simulated_depth", "load_trajectory", "load_view", "load_views",
           "read_meta"]
