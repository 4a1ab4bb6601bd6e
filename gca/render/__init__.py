"""gca.render: differentiable Gaussian rasterizer (tiled torch; optional gsplat), cameras,
Gaussians following particles, lighting for the benchmark videos.

Public API::

    Camera, look_at, intrinsics                      (camera.py)
    RasterConfig, render, render_ref                 (rasterize.py)
    project_gaussians                                (project.py)
    Binding, follow, covariance_from_scale_rot,
    quat_to_rotmat, smallest_axis_normal             (follow.py)
    LightingConfig, Light, sample_lights, shade      (shading.py)
"""

from gca.render.camera import Camera, CameraError, intrinsics, look_at
from gca.render.follow import (Binding, BindingError, covariance_from_scale_rot, follow, quat_to_rotmat,
                               smallest_axis_normal)
from gca.render.project import Projected, project_gaussians
from gca.render.rasterize import RasterConfig, RenderError, render, render_ref
from gca.render.shading import Light, LightingConfig, sample_lights, shade

__all__ = [
    "Camera", "CameraError", "intrinsics", "look_at",
    "Binding", "BindingError", "covariance_from_scale_rot", "follow", "quat_to_rotmat", "smallest_axis_normal",
    "Projected", "project_gaussians",
    "RasterConfig", "RenderError", "render", "render_ref",
    "Light", "LightingConfig", "sample_lights", "shade",
]
