"""Issue 22 item 3: the baselines as their authors run them, labelled honestly.

The L1 depth terms of the PAC-NeRF + depth rows (raw and aligned), ...
"""

import pytest
import torch

from gca.train.objective import depth_l1_aligned, depth_l1_raw


def _frame(seed=0, dtype=torch.float64, h=12, w=10):
    g = torch.Generator().manual_seed(seed)
    depth = 1.0 + 0.3 * torch.rand(h, w, generator=g, dtype=dtype)  # rendered metric depth [m]
    est = 2.0 - 0.5 * depth + 0.02 * torch.randn(h, w, generator=g, dtype=dtype)  # affine-ish estimate, noisy
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[2:10, 1:8] = True
    return depth, est, mask


@pytest.mark.parametrize("a, b", [(3.0, 0.7), (0.01, -5.0), (-2.0, 1.0)])
def test_aligned_depth_is_invariant_to_an_affine_change_of_the_estimate(a, b):
    depth, est, mask = _frame()
    ref = depth_l1_aligned(depth, est, mask)
    moved = depth_l1_aligned(depth, a * est + b, mask)
    torch.testing.assert_close(moved, ref, rtol=1e-9, atol=1e-12)
    assert float(ref) > 0  # the estimate is not exactly affine in the render: a real residual remains
    # negative control: the raw L1 is not invariant
    assert abs(float(depth_l1_raw(depth, a * est + b, mask)) - float(depth_l1_raw(depth, est, mask))) > 1e-2


def test_aligned_depth_is_zero_for_an_exactly_affine_estimate_and_sees_shape():
    depth, _, mask = _frame()
    assert float(depth_l1_aligned(depth, 4.0 * depth - 3.0, mask)) < 1e-12
    assert float(depth_l1_raw(depth, 4.0 * depth - 3.0, mask)) > 0.1  # raw: the units differ
    # a different shape (not affine in the render) is penalised
    assert float(depth_l1_aligned(depth, depth.square().flip(0), mask)) > 1e-3


def test_aligned_depth_ignores_pixels_outside_the_mask():
    depth, est, mask = _frame()
    other = est.clone()
    other[~mask] = 1e6
    torch.testing.assert_close(depth_l1_aligned(depth, other, mask), depth_l1_aligned(depth, est, mask))


@pytest.mark.parametrize("fn", [depth_l1_aligned, depth_l1_raw])
def test_a_zero_mask_frame_contributes_zero_with_a_finite_gradient(fn):
    depth, est, _ = _frame()
    depth.requires_grad_(True)
    value = fn(depth, est, torch.zeros_like(depth, dtype=torch.bool))
    assert float(value) == 0.0
    value.backward()
    assert torch.equal(depth.grad, torch.zeros_like(depth))


def test_aligned_depth_gradient_is_finite_even_for_a_constant_estimate():
    depth, _, mask = _frame()
    depth.requires_grad_(True)
    value = depth_l1_aligned(depth, torch.full_like(depth, 0.5), mask)  # var(est) = 0: s = 0, t = mean depth
    value.backward()
    assert torch.isfinite(value) and torch.isfinite(depth.grad).all()
    assert float(depth.grad[~mask].abs().sum()) == 0.0 and float(depth.grad[mask].abs().sum()) > 0


@pytest.mark.grad
def test_aligned_depth_gradcheck_float64():
    """The alignment (s, t) is differentiated through (not detached): the whole function passes gradcheck, in
    the render and in the estimate."""
    depth, est, mask = _frame(seed=3)
    depth.requires_grad_(True)
    est.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d, e: depth_l1_aligned(d, e, mask), (depth, est), eps=1e-6, atol=1e-7)


def test_aligned_gradient_differs_from_a_detached_alignment():
    """Negative control for the not-detached choice: treating (s, t) as constants gives another gradient."""
    depth, est, mask = _frame(seed=4)
    d1 = depth.clone().requires_grad_(True)
    depth_l1_aligned(d1, est, mask).backward()
    d2 = depth.clone().requires_grad_(True)
    dm, em = d2[mask], est[mask]
    with torch.no_grad():
        s = ((em - em.mean()) * (dm - dm.mean())).mean() / (em - em.mean()).square().mean()
        t = dm.mean() - s * em.mean()
    (s * em + t - dm).abs().mean().backward()
    assert not torch.allclose(d1.grad, d2.grad)


# ------------------------------------------------------------------ the depth rows inside the objective

import dataclasses  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import JELLY, ground_truth_views, observations, tiny_body, tiny_solver  # noqa: E402

from gca.align.cpr import CPRConfig  # noqa: E402
from gca.align.rdga import RDGAConfig  # noqa: E402
from gca.laws.lora import LoRAConfig  # noqa: E402
from gca.train.config import TrainConfig  # noqa: E402
from gca.train.law import build_law  # noqa: E402
from gca.train.loop import simulate  # noqa: E402
from gca.train.methods import get_method  # noqa: E402
from gca.train.objective import Objective, TrainData  # noqa: E402
from gca.vision import MatchConfig  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    torch.manual_seed(0)
    body = tiny_body(n_side=4, base_y=0.08)
    view, frames, _ = ground_truth_views(body, (0.5, -2.0, 0.0), n_frames=6, frame_every=2)
    est, keypoints = observations(view)
    data = TrainData(body=body, views={"train0": view}, video_frames=frames, substeps=2, est_depth=est,
                     keypoints=keypoints, v_init=torch.tensor([0.5, -2.0, 0.0]).expand_as(body.x0),
                     background=(1.0, 1.0, 1.0))
    return data


def _depth_stat(data, name):
    method = get_method(name)
    cfg = TrainConfig(iterations=1, curriculum_start=1.0)
    law = build_law(method, "", "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2,
                    family_presets={"jelly": JELLY})
    objective = Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    n_video = len(data.video_frames)
    with torch.no_grad():
        _, stats = objective.data_loss(simulate(tiny_solver(), law, data, n_video), n_video)
    return stats[method.terms[-1]]


def test_objective_aligned_depth_row_ignores_the_estimates_scale_and_shift_raw_row_does_not(scene):
    moved = dataclasses.replace(scene, est_depth=3.0 * scene.est_depth + 0.5)
    aligned = _depth_stat(scene, "pacnerf_depth_aligned")
    assert aligned > 0 and aligned == pytest.approx(_depth_stat(moved, "pacnerf_depth_aligned"), rel=1e-4)
    raw = _depth_stat(scene, "pacnerf_depth")
    assert raw != pytest.approx(_depth_stat(moved, "pacnerf_depth"), rel=1e-2)  # negative control
