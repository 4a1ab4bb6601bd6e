"""gca.train.probe: non-finite gradients are traced to the stage whose backward made them."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import NaNBackward  # noqa: E402

from gca.train.probe import GradProbe  # noqa: E402


def _chain(broken: str):
    """theta -> particles -> gaussians -> render outputs -> loss, with one stage's backward broken."""
    theta = torch.ones(4, requires_grad=True)
    probe = GradProbe()
    x = theta * 2.0
    x = NaNBackward.apply(x) if broken == "law" else x
    probe.watch("particles", "x", -1, x)
    means = x * 3.0
    means = NaNBackward.apply(means) if broken == "map" else means
    probe.watch("gaussians", "means", 0, means)
    rgb = means.sin()
    rgb = NaNBackward.apply(rgb) if broken == "raster" else rgb
    probe.watch("render outputs", "train0/rgb", 0, rgb)
    loss = rgb.sum() if broken != "loss" else (rgb * torch.tensor([float("inf"), 1, 1, 1]) * 0).sum()
    loss.backward()
    assert not torch.isfinite(theta.grad).all()  # the probe is a diagnosis, never a repair
    return probe.report()


@pytest.mark.parametrize("broken, expected", [
    ("loss", "first broken at 'render outputs': made by the losses' backward"),
    ("raster", "first broken at 'gaussians': made by the rasterizer's backward"),
    ("map", "first broken at 'particles': made by the particles-to-Gaussians map's backward"),
    ("law", "every probed gradient finite: made by the simulator/law backward"),
])
def test_probe_names_the_broken_stage(broken, expected):
    assert expected in _chain(broken)


def test_probe_all_finite_and_unknown_stage():
    probe = GradProbe()
    t = torch.ones(3, requires_grad=True)
    probe.watch("particles", "x", -1, t * 1.0)
    assert "no probed tensor" in probe.report()
    with pytest.raises(ValueError, match="unknown stage"):
        probe.watch("nowhere", "x", 0, t)


def test_a_frame_batched_tensor_names_its_broken_frames():
    """watch_frames (session 40: a training iteration's frames rendered in one call) counts each frame of a [T, ...]
    tensor apart: the report names the frames whose gradient broke, not all of them; watch's one count for the
    whole tensor (the control) cannot."""
    frames = [3, 4, 5, 6]
    probe, whole = GradProbe(), GradProbe()
    means = (torch.ones(4, 5, 3, requires_grad=True) * 2.0)
    probe.watch_frames("gaussians", "means", frames, means)
    whole.watch("gaussians", "means", -1, means)
    weight = torch.ones(4, 5, 3)
    weight[2, 1, 0] = float("nan")  # only frame 5's gradient
    (means * weight).sum().backward()
    assert "gaussians: non-finite (means at frames [5])" in probe.report()
    assert "means at frames [-1]" in whole.report()
    with pytest.raises(ValueError, match="unknown stage"):
        probe.watch_frames("nowhere", "x", frames, means)
