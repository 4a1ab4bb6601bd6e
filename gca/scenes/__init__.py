"""Scenes: configuration, the simulate-and-render world, ground-truth generation, on-disk layout."""

from gca.scenes.config import OrbitCamera, SceneConfig, VideoConfig
from gca.scenes.store import TRAIN_VIEW, SceneDataError, ViewData, load_trajectory, load_view, load_views, read_meta

__all__ = ["OrbitCamera", "SceneConfig", "VideoConfig", "TRAIN_VIEW",
           "SceneDataError", "ViewData", "load_trajectory", "load_view", "load_views", "read_meta"]
