"""Initial velocity estimation recovers a known launch velocity from the monocular silhouettes."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import JELLY, ground_truth_views, tiny_body, tiny_solver  # noqa: E402

from gca.laws.presets import material_from_preset  # noqa: E402
from gca.train.config import VelocityConfig  # noqa: E402
from gca.train.velocity import estimate_velocity  # noqa: E402


@pytest.mark.parametrize("v_true", [(0.8, -1.2, 0.0), (0.5, -1.2, 0.6)], ids=["in_plane", "along_ray"])
def test_recovers_launch_velocity_within_10_percent(v_true):
    """Fitted through 8 video frames, a launch in the image plane and one with a component along the
    camera's ray (z: the camera looks along -z) are both recovered without a prior on that component."""
    torch.manual_seed(0)
    body = tiny_body()
    v_true = np.array(v_true)
    view, frames, _ = ground_truth_views(body, v_true, n_frames=16, frame_every=2)
    cfg = VelocityConfig(iterations=80, n_video_frames=8, lr=0.1, angular=False)
    v0, w0, history = estimate_velocity(tiny_solver(), material_from_preset(JELLY), body, view, frames, 2, cfg)
    error = np.linalg.norm(v0.numpy() - v_true) / np.linalg.norm(v_true)
    assert error < 0.10, f"v0={v0.tolist()} vs {v_true.tolist()} ({100 * error:.1f}% error)"
    assert history[-1] < history[0]  # (soft alpha vs a binary mask keeps a floor above 0)
    assert torch.equal(w0, torch.zeros(3))


def test_a_prior_on_the_view_axis_biases_a_launch_along_the_ray():
    """reg_view_axis pulls v0's along-ray component to zero: the session-5 default (1e-2) lost 40% of a
    0.6 m/s along-ray launch (the pipeline's six scenes lost 0.4-0.65 m/s the same way)."""
    torch.manual_seed(0)
    body = tiny_body()
    v_true = np.array([0.5, -1.2, 0.6])
    view, frames, _ = ground_truth_views(body, v_true, n_frames=16, frame_every=2)
    cfg = VelocityConfig(iterations=80, n_video_frames=8, lr=0.1, angular=False, reg_view_axis=1e-2)
    v0, _, _ = estimate_velocity(tiny_solver(), material_from_preset(JELLY), body, view, frames, 2, cfg)
    assert v0[2] < 0.8 * v_true[2], f"v0={v0.tolist()}: the prior should have shrunk the along-ray component"
