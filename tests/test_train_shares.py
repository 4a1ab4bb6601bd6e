"""Issue 22, item 2: every loss term's share of the gradient (its norm and its cosine with the total)."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import JELLY, ground_truth_views, observations, tiny_body, tiny_solver  # noqa: E402

from gca.align.cpr import CPRConfig  # noqa: E402
from gca.align.rdga import RDGAConfig  # noqa: E402
from gca.laws.checkpoint import save_prior  # noqa: E402
from gca.laws.lora import LoRAConfig  # noqa: E402
from gca.laws.neural import NeuralElasticity, NeuralPlasticity  # noqa: E402
from gca.train.config import TrainConfig  # noqa: E402
from gca.train.law import build_law  # noqa: E402
from gca.train.loop import simulate, train  # noqa: E402
from gca.train.methods import get_method  # noqa: E402
from gca.train.objective import Objective, TrainData, term_shares  # noqa: E402
from gca.vision import MatchConfig  # noqa: E402


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    torch.manual_seed(0)
    body = tiny_body(n_side=4, base_y=0.08)
    view, frames, _ = ground_truth_views(body, (0.5, -2.0, 0.0), n_frames=6, frame_every=2)
    est, keypoints = observations(view)
    prior = tmp_path_factory.mktemp("prior") / "jelly.pt"
    save_prior(prior, NeuralElasticity(), NeuralPlasticity(), family="jelly")
    data = TrainData(body=body, views={"train0": view}, video_frames=frames, substeps=2, est_depth=est,
                     keypoints=keypoints, v_init=torch.tensor([0.5, -2.0, 0.0]).expand_as(body.x0),
                     background=(1.0, 1.0, 1.0))
    return data, prior


def _setup(scene, name, ratio=0.0, **cfg_kw):
    data, prior = scene
    method = get_method(name)
    cfg = TrainConfig(**{"iterations": 1, "curriculum_start": 1.0, "keep": "last", **cfg_kw})
    law = build_law(method, prior, "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), cfg.lr_elasticity,
                    cfg.lr_plasticity, cfg.lr_explicit, family_presets={"jelly": {**JELLY, "E": 4.0e4}}, category="elastic")
    objective = Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2,
                          max_grad_ratio=ratio), MatchConfig())
    return method, cfg, law, objective


@pytest.mark.parametrize("name", ["gca", "pacnerf_depth", "pacnerf_depth_aligned"])
def test_term_gradients_sum_to_the_total(scene, name):
    """eq. 8 with max_grad_ratio 0: the per-term gradients add up to the gradient training applies."""
    method, cfg, law, objective = _setup(scene, name)
    data = scene[0]
    n_video = len(data.video_frames)
    params = law.trainable()
    traj = simulate(tiny_solver(), law, data, n_video)
    loss, stats = objective.gradient(traj, n_video, law, shares=True)
    grads = objective.last_term_grads
    assert set(grads) == set(method.terms), (sorted(grads), method.terms)
    assert objective.last_shares_summed  # the total is the terms' sum (no pass of its own): the comparison that
    # makes it independent is the default path's below, and test_default_path_computes_no_shares_and_the_same_gradient
    total = [p.grad.detach().clone() for p in params]
    for p in params:
        p.grad = None
    objective.gradient(simulate(tiny_solver(), law, data, n_video), n_video, law)  # the plain path: its own pass
    for t, p in zip(total, params):
        torch.testing.assert_close(p.grad, t, rtol=1e-4, atol=1e-9)
    summed = [sum(g[i] for g in grads.values() if g[i] is not None) for i in range(len(params))]
    for t, s_ in zip(total, summed):
        torch.testing.assert_close(s_, t, rtol=1e-4, atol=1e-9)
    for term in method.terms:
        assert stats[f"share/{term}/norm"] >= 0 and -1.0 - 1e-9 <= stats[f"share/{term}/cos"] <= 1.0 + 1e-9
    # negative control: leaving one term out no longer reproduces the total
    dropped = [sum(g[i] for k, g in grads.items() if k != method.terms[0] and g[i] is not None)
               for i in range(len(params))]
    assert any(not torch.allclose(torch.as_tensor(d), t, rtol=1e-4, atol=1e-9) for d, t in zip(dropped, total))


def test_default_path_computes_no_shares_and_the_same_gradient(scene):
    _, cfg, law, objective = _setup(scene, "gca")
    data = scene[0]
    n_video = len(data.video_frames)
    traj = simulate(tiny_solver(), law, data, n_video)
    _, stats = objective.gradient(traj, n_video, law)
    assert not any(k.startswith("share/") for k in stats) and objective.last_term_grads is None
    plain = [p.grad.detach().clone() for p in law.trainable()]
    for p in law.trainable():
        p.grad = None
    traj = simulate(tiny_solver(), law, data, n_video)
    objective.gradient(traj, n_video, law, shares=True)
    for a, b in zip(plain, law.trainable()):
        torch.testing.assert_close(b.grad, a)


def test_term_shares_cosines():
    g = [torch.tensor([1.0, 0.0])]
    out = term_shares({"a": [torch.tensor([2.0, 0.0])], "b": [torch.tensor([0.0, 3.0])], "c": [None]}, g)
    assert out["share/a/norm"] == pytest.approx(2.0) and out["share/a/cos"] == pytest.approx(1.0)
    assert out["share/b/cos"] == pytest.approx(0.0) and out["share/c/norm"] == 0.0


def test_history_records_shares_every_k(scene):
    _, cfg, law, objective = _setup(scene, "neuma", term_shares_every=2, iterations=3)
    result = train(tiny_solver(), law, scene[0], objective, cfg)
    assert result.status == "ok"
    has = [any(k.startswith("share/color/") for k in rec) for rec in result.history]
    assert has == [True, False, True]
    with pytest.raises(ValueError, match="term_shares_every"):
        TrainConfig(term_shares_every=-1)


@pytest.mark.parametrize("name", ["neuma", "gca"])
def test_term_gradients_sum_to_the_total_under_frame_weights(scene, name):
    """NeuMA's rollout weighting (``frame_weights``, set by the loop each iteration) weighs each frame's terms as it
    weighs its loss: the per-term gradients still add up to the total (NeuMA's one term: share 1, cosine 1)."""
    method, cfg, law, objective = _setup(scene, name)
    data = scene[0]
    n_video = len(data.video_frames)
    objective.frame_weights = [0.5 ** (j // 2) for j in range(n_video)]
    traj = simulate(tiny_solver(), law, data, n_video)
    _, stats = objective.gradient(traj, n_video, law, shares=True)
    grads = objective.last_term_grads
    assert objective.last_shares_summed  # the weighted terms still add up: no extra pass
    for p, g in zip(law.trainable(), grads[method.terms[0]]):  # a copy, not the term's own gradient (which in-place
        assert g is None or p.grad.data_ptr() != g.data_ptr()  # clipping of .grad would rescale: NeuMA's one term)
    total = [p.grad.detach().clone() for p in law.trainable()]
    summed = [sum(g[i] for g in grads.values() if g[i] is not None) for i in range(len(total))]
    for p in law.trainable():
        p.grad = None
    objective.gradient(simulate(tiny_solver(), law, data, n_video), n_video, law)  # the plain path, same weights
    for t, p in zip(total, law.trainable()):
        torch.testing.assert_close(p.grad, t, rtol=1e-4, atol=1e-9)
    for t, s_ in zip(total, summed):
        torch.testing.assert_close(s_, t, rtol=1e-4, atol=1e-9)
    if name == "neuma":
        assert stats["share/color/norm"] == pytest.approx(stats["share/total/norm"], rel=1e-5)
        assert stats["share/color/cos"] == pytest.approx(1.0, abs=1e-6)


def test_terms_that_do_not_add_up_fall_back_to_the_losss_own_pass(scene, monkeypatch):
    # a term collected wrong (here: halved) no longer sums to the data loss: the total is the loss's own backward pass
    # (the plain path's gradient), not the terms' sum, which would miss half a term
    _, cfg, law, objective = _setup(scene, "gca")
    data = scene[0]
    n_video = len(data.video_frames)
    objective.gradient(simulate(tiny_solver(), law, data, n_video), n_video, law)
    plain = [p.grad.detach().clone() for p in law.trainable()]
    for p in law.trainable():
        p.grad = None
    collect = Objective._collect
    monkeypatch.setattr(Objective, "_collect", lambda self, term, value: collect(
        self, term, 0.5 * value if term == "silhouette" else value))
    objective.gradient(simulate(tiny_solver(), law, data, n_video), n_video, law, shares=True)
    assert not objective.last_shares_summed
    for a, p in zip(plain, law.trainable()):
        torch.testing.assert_close(p.grad, a)
