"""Methods registry: every paper table row has a method, and every method runs one training iteration."""

import dataclasses
import functools
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import JELLY, NaNBackward, ground_truth_views, observations, tiny_body, tiny_solver  # noqa: E402

from gca.align import cpr as _cpr, rdga as _rdga  # noqa: E402

# The setup these tests were written for: the mean silhouette and CPR's gradient as written, one call
# (the dataclass defaults are params.yaml's since issue 24: sum, 2-frame chunks, ratio 0.3).
RDGAConfig = functools.partial(_rdga.RDGAConfig, mask_reduction="mean")
CPRConfig = functools.partial(_cpr.CPRConfig, chunk_frames=0, max_grad_ratio=0.0)
from gca.laws.checkpoint import save_prior  # noqa: E402
from gca.laws.lora import LoRAConfig  # noqa: E402
from gca.laws.neural import NeuralElasticity, NeuralPlasticity  # noqa: E402
from gca.report import paper  # noqa: E402
from gca.scenes.store import ViewData  # noqa: E402
from gca.train.config import TrainConfig  # noqa: E402
from gca.train.law import build_law  # noqa: E402
from gca.train.loop import horizon, train  # noqa: E402
from gca.train.objective import Objective, TrainData  # noqa: E402
from gca.train.methods import METHODS, UnknownMethodError, get_method  # noqa: E402
from gca.vision import MatchConfig  # noqa: E402


def test_every_paper_row_has_a_method_and_back():
    assert set(paper.METHODS) == set(METHODS)
    for name, method in METHODS.items():
        assert method.tables, f"{name} belongs to no table"


def test_unknown_method_lists_valid_ones():
    with pytest.raises(UnknownMethodError, match="valid methods: .*gca"):
        get_method("gca_v2")


def test_curriculum_grows_to_every_frame():
    cfg = TrainConfig(iterations=10, curriculum_start=0.3, curriculum_until=0.5)
    ramp = [horizon(cfg, it, 10) for it in range(10)]
    assert ramp[0] == 3 and ramp[-1] == 10 and ramp == sorted(ramp)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    torch.manual_seed(0)
    body = tiny_body(n_side=4, base_y=0.08)  # hits the floor within the video: stress (and its gradient) != 0
    view, frames, _ = ground_truth_views(body, (0.5, -2.0, 0.0), n_frames=8, frame_every=2)
    est, keypoints = observations(view)
    prior = tmp_path_factory.mktemp("prior") / "jelly.pt"
    save_prior(prior, NeuralElasticity(), NeuralPlasticity(), family="jelly")
    return body, view, frames, est, keypoints, prior


def _data(scene, method) -> TrainData:
    body, view, frames, est, keypoints, _ = scene
    views = {"train0": view}
    if method.views == "multi":  # same frames under other names: the code path is what is tested here
        views.update({n: ViewData(n, view.camera, view.rgb, view.mask, view.depth) for n in ("train1", "train2")})
    v = torch.tensor([0.5, -2.0, 0.0]).expand_as(body.x0)
    return TrainData(body=body, views=views, video_frames=frames, substeps=2, est_depth=est, keypoints=keypoints,
                     v_init=v, background=(1.0, 1.0, 1.0))


def _rollout(law, data: TrainData, **kwargs):
    """The law's rollout over every video frame of ``data`` on the tiny solver (``kwargs``: rollout's, e.g. sweep)."""
    from gca.sim.rollout import rollout
    b = data.body
    return rollout(tiny_solver(), law.material, b.x0, data.v_init, b.vol, b.mass,
                   n_steps=data.video_frames[-1] * data.substeps, steps_per_frame=data.substeps, **kwargs)


@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_method_runs_one_iteration(scene, name):
    method = get_method(name)
    cfg = TrainConfig(iterations=1, curriculum_start=1.0, lr_elasticity=1e-2, lr_plasticity=1e-3, lr_explicit=1e-2,
                      keep="last")  # the step itself is under test, not which law is kept
    law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), cfg.lr_elasticity,
                    cfg.lr_plasticity, cfg.lr_explicit, family_presets={"jelly": {**JELLY, "E": 4.0e4}}, category="elastic")
    before = [p.detach().clone() for p in law.trainable()]
    rdga = RDGAConfig(r=5, k=5)
    objective = Objective(method, _data(scene, method), cfg, rdga, CPRConfig(subset_size=16, n_groups=2),
                          MatchConfig(), cpr_target=("corotated", "identity"))
    result = train(tiny_solver(), law, _data(scene, method), objective, cfg)
    assert result.status == "ok", result.message
    if method.trains:
        assert result.iterations == 1 and torch.isfinite(torch.tensor(result.history[0]["loss"]))
        assert any(not torch.equal(b, p.detach()) for b, p in zip(before, law.trainable())), "no parameter moved"
    else:
        assert law.trainable() == [] and result.iterations == 0


@pytest.mark.parametrize("name", sorted(n for n, m in METHODS.items() if m.trains))
def test_every_method_gradient_swept_equals_autograd(scene, name):
    """One training gradient (loop._gradient) with train.reverse_sweep (the rollout differentiated frame by frame,
    last first, beside the losses) equals the one autograd pass through the whole rollout: same loss, same
    gradient to float32 rounding, for every training method (a learned launch included: PAC-NeRF rows), with frame
    weights (NeuMA's rollout weighting)."""
    from gca.train.loop import _gradient

    method = get_method(name)
    results = []
    for sweep in (False, True):
        cfg = TrainConfig(iterations=1, curriculum_start=1.0, term_shares_every=0, reverse_sweep=sweep)
        law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2,
                        family_presets={"jelly": {**JELLY, "E": 4.0e4}}, category="elastic", seed=0)
        data = _data(scene, method)
        objective = Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2),
                              MatchConfig(), cpr_target=("corotated", "identity"))
        objective.frame_weights = [0.5 ** (j % 3) for j in range(len(data.video_frames))]  # NeuMA's kind of weighting
        record = _gradient(tiny_solver(), law, data, objective, cfg, len(data.video_frames))
        results.append((record, [p.grad.detach().clone() for p in law.trainable()]))
    (ref, g_ref), (swept, g) = results
    assert swept["loss"] == pytest.approx(ref["loss"], rel=1e-5) and ref["grad_norm"] > 0
    assert swept["grad_norm"] == pytest.approx(ref["grad_norm"], rel=1e-4)
    scale = max(float(b.abs().max()) for b in g_ref)  # float32 sums in another order: relative to the largest entry
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.parametrize("sweep", [False, True])
def test_a_broken_rollout_is_a_retried_divergence_in_either_gradient(scene, sweep, monkeypatch):
    """A law turning NaN, or a rollout spreading past train.max_spread_growth, ends the gradient with one of the
    loop's divergence errors (retried), named as such: a swept rollout renders before its checks are read, and must
    still not surface as the renderer's RenderError (non-finite means) or go unchecked."""
    from gca.sim.rollout import SimulationDiverged
    from gca.train.loop import _gradient

    method = get_method("gca")
    data = _data(scene, method)

    def gradient(**cfg_kw):
        cfg = TrainConfig(iterations=1, curriculum_start=1.0, term_shares_every=0, reverse_sweep=sweep, **cfg_kw)
        law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2, seed=0)
        objective = Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2),
                              MatchConfig())
        return law, lambda: _gradient(tiny_solver(), law, data, objective, cfg, len(data.video_frames))

    law, run = gradient(max_spread_growth=-1.0)  # any rollout "blew up"
    with pytest.raises(FloatingPointError, match="rollout blew up"):
        run()
    law, run = gradient()
    monkeypatch.setattr(law.material, "stress", lambda F: torch.full_like(F, float("nan")))
    with pytest.raises(SimulationDiverged, match="non-finite x, v or F"):
        run()
    assert all(p.grad is None for p in law.trainable())  # nothing half-added


def test_target_removed_drops_the_hypotheses(scene):
    method = get_method("cpr_target_removed")
    objective = Objective(method, _data(scene, method), TrainConfig(), RDGAConfig(r=5, k=5),
                          CPRConfig(subset_size=16, n_groups=2), MatchConfig(), cpr_target=("corotated", "identity"))
    assert "corotated" not in objective.cpr.cfg.elastic and "identity" not in objective.cpr.cfg.plastic
    full = Objective(get_method("gca"), _data(scene, method), TrainConfig(), RDGAConfig(r=5, k=5),
                     CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    assert "corotated" in full.cpr.cfg.elastic


def test_ablation_switches_reach_rdga(scene):
    for name, field, value in (("no_global", "use_global", False), ("no_anchor", "use_anchor", False),
                               ("rank_to_l1", "depth_term", "l1")):
        objective = Objective(get_method(name), _data(scene, get_method(name)), TrainConfig(), RDGAConfig(),
                              CPRConfig(subset_size=16, n_groups=2), MatchConfig())
        assert getattr(objective.rdga, field) == value
        assert dataclasses.replace(objective.rdga, **{field: getattr(RDGAConfig(), field)}) == RDGAConfig()


def test_training_resumes_from_its_checkpoint(scene, tmp_path):
    """An interrupted run (2 of 3 iterations, checkpointed) resumes at iteration 2, not from scratch."""
    ckpt = tmp_path / "checkpoint.pt"

    def run(iterations):
        law, go = _neuma_run(scene, checkpoint_path=ckpt, iterations=iterations, checkpoint_every=1)
        return law, go()

    law2, first = run(2)
    assert ckpt.is_file() and [h["iteration"] for h in first.history] == [0, 1]
    law3, resumed = run(3)
    assert [h["iteration"] for h in resumed.history] == [0, 1, 2]  # the first two came from the checkpoint
    assert first.resumed_at == 0 and first.seconds_before == 0.0
    assert resumed.resumed_at == 2 and 0 < resumed.seconds_before <= first.seconds  # the first run's time, carried
    assert resumed.history[:2] == first.history
    moved = [not torch.equal(a, b) for a, b in zip(law2.state().values(), law3.state().values())]
    assert any(moved), "the resumed run should have taken one more optimiser step"


def test_a_resumed_run_keeps_every_process_that_trained_it(scene, tmp_path):
    """A run stopped after 2 of 3 iterations by one process and resumed by another lists both, each with the
    iteration it started at and what its caller said of it (``process``: the grid's MPS priority, say); the checkpoint
    carries the earlier ones. A fresh run lists itself alone (control)."""
    ckpt = tmp_path / "checkpoint.pt"

    def run(iterations, process):
        return _neuma_run(scene, checkpoint_path=ckpt, process=process, iterations=iterations, checkpoint_every=1)[1]()

    first = run(2, {"mps_priority": "below_normal"})
    assert first.processes == [{"resumed_at": 0, "mps_priority": "below_normal"}]
    assert torch.load(ckpt, weights_only=False)["processes"] == first.processes
    resumed = run(3, {"mps_priority": "normal"})
    assert resumed.resumed_at == 2 and resumed.iterations == 3
    assert resumed.processes == [{"resumed_at": 0, "mps_priority": "below_normal"},
                                 {"resumed_at": 2, "mps_priority": "normal"}]
    assert torch.load(ckpt, weights_only=False)["processes"] == resumed.processes  # written at iteration 3


@pytest.mark.parametrize("second", ["normal", "below_normal"])
def test_train_json_merges_the_gpu_sharing_of_every_process(scene, tmp_path, monkeypatch, second):
    """train_method on a run trained to iteration 2 by a process the grid put below normal under MPS (4 runs per GPU)
    and finished by one at ``second`` priority (8 runs per GPU): train.json lists both processes and merges them,
    ``mps_priority`` "mixed" where they differ and below-normal where both were (negative control); ``runs_per_gpu``
    the larger."""
    import types

    import gca.pipeline.train as pipeline_train
    from gca import gpu_slot
    from gca.io import read_json

    def job(iterations):
        law, _ = _neuma_run(scene)
        method = get_method("neuma")
        cfg = TrainConfig(curriculum_start=1.0, keep="last", iterations=iterations, checkpoint_every=1)
        objective = Objective(method, _data(scene, method), cfg, RDGAConfig(r=5, k=5),
                              CPRConfig(subset_size=16, n_groups=2), MatchConfig())
        return pipeline_train.TrainJob(cfg, _data(scene, method), law, objective, tiny_solver())

    def train_method(iterations, priority, per_gpu):
        monkeypatch.setattr(pipeline_train, "train_job", lambda *a, **kw: job(iterations))
        for name, value in ((gpu_slot.MPS_ENV, "1"), (gpu_slot.PRIORITY_GRID_ENV, "1"), (gpu_slot.RUNS_ENV, per_gpu),
                            (gpu_slot.MPS_PRIORITY_ENV, gpu_slot.MPS_BELOW_NORMAL if priority == "below_normal" else "0")):
            monkeypatch.setenv(name, value)
        settings = types.SimpleNamespace(scene=lambda name: types.SimpleNamespace(prior="jelly"))
        return pipeline_train.train_method(settings, "tiny", get_method("neuma"), None, ([0.5, -2.0, 0.0], [0.0] * 3),
                                           tmp_path / "neuma", keep_checkpoint=True)

    first = train_method(2, "below_normal", "4")
    assert first["mps_priority"] == "below_normal" and first["runs_per_gpu"] == 4
    train_method(3, second, "8")
    record = read_json(tmp_path / "neuma" / "train.json")
    assert record["resumed_at"] == 2 and record["iterations"] == 3
    assert [(p["resumed_at"], p["mps_priority"], p["runs_per_gpu"]) for p in record["processes"]] == \
        [(0, "below_normal", 4), (2, second, 8)]
    assert record["mps_priority"] == ("mixed" if second == "normal" else "below_normal")
    assert record["runs_per_gpu"] == 8 and record["mps"] is True


def test_a_checkpoint_from_before_processes_were_kept_resumes(scene, tmp_path):
    """A checkpoint written before it kept its processes (no ``processes`` key) resumes where it stopped, its
    earlier processes unknown: only the resuming one is listed."""
    ckpt = tmp_path / "checkpoint.pt"
    _neuma_run(scene, checkpoint_path=ckpt, iterations=2, checkpoint_every=1)[1]()
    old = torch.load(ckpt, weights_only=False)
    del old["processes"]
    torch.save(old, ckpt)
    resumed = _neuma_run(scene, checkpoint_path=ckpt, iterations=3, checkpoint_every=1)[1]()
    assert resumed.status == "ok" and resumed.resumed_at == 2 and [h["iteration"] for h in resumed.history] == [0, 1, 2]
    assert resumed.processes == [{"resumed_at": 2}]


def test_a_stop_file_checkpoints_the_iteration_in_progress_and_stops(scene, tmp_path, monkeypatch):
    """NOTES session 42 (packed runs under CUDA MPS are stopped with a file, not a signal): the file written during
    iteration 1 of 3 stops the run after that iteration, checkpointed there though ``checkpoint_every`` is far; the
    same run without the file trains its 3 iterations (negative control)."""
    from gca import stop

    flag, ckpt = tmp_path / "job.stop", tmp_path / "checkpoint.pt"
    monkeypatch.setenv(stop.STOP_FILE_ENV, str(flag))
    method = get_method("neuma")
    cfg = TrainConfig(curriculum_start=1.0, keep="last", iterations=3, checkpoint_every=100)

    def run(on_iteration):
        law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
        objective = Objective(method, _data(scene, method), cfg, RDGAConfig(r=5, k=5),
                              CPRConfig(subset_size=16, n_groups=2), MatchConfig())
        return train(tiny_solver(), law, _data(scene, method), objective, cfg, checkpoint_path=ckpt,
                     on_iteration=on_iteration)

    try:
        with pytest.raises(stop.Terminated, match="stop file"):
            run(lambda it, record: flag.write_text("1\n") if it == 1 else None)
    finally:
        stop.reset()
    assert torch.load(ckpt, weights_only=False)["iteration"] == 2
    flag.unlink()
    ckpt.unlink()
    assert [h["iteration"] for h in run(None).history] == [0, 1, 2]


def test_a_resumed_gca_run_ends_with_the_uninterrupted_law(scene, tmp_path):
    """Issue 24 item 7 (found by tests/test_fault_injection.py): a run stopped after iteration 1 and resumed
    from its checkpoint ends with the uninterrupted run's law, bit for bit, and the same losses. CPR reuses
    its fits between refits (``refit_every`` 3 here, 5 at the CI profile); before the checkpoint held them, the
    resumed run refitted at its first iteration and drifted (R_e 0.0093 against 0.0098 on the CI ball)."""
    def run(iterations, checkpoint=None):
        method = get_method("gca")
        cfg = TrainConfig(iterations=iterations, curriculum_start=0.25, curriculum_until=1.0, keep="last",
                          checkpoint_every=1)  # 2 of the 8 frames (the first iterations' horizon): quicker
        law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
        objective = Objective(method, _data(scene, method), cfg, RDGAConfig(r=5, k=5),
                              CPRConfig(subset_size=16, n_groups=2, refit_every=3), MatchConfig(),
                              cpr_target=("corotated", "identity"))
        return law, train(tiny_solver(), law, _data(scene, method), objective, cfg, checkpoint_path=checkpoint)

    whole, uninterrupted = run(2)
    run(1, tmp_path / "checkpoint.pt")  # stopped after iteration 1 (its checkpoint: what SIGTERM leaves)
    resumed_law, resumed = run(2, tmp_path / "checkpoint.pt")
    assert resumed.resumed_at == 1
    losses = lambda result: [(h["loss"], h["R_e"], h["R_p"]) for h in result.history]  # noqa: E731
    assert losses(resumed) == losses(uninterrupted)
    assert all(torch.equal(a, b) for a, b in zip(whole.state().values(), resumed_law.state().values()))


def test_a_run_resumed_from_its_last_iterations_checkpoint_only_selects_its_law(scene, tmp_path):
    """What a tuning unit stopped after its training (or in its evaluation) relies on (tune.trained, NOTES session
    43): started again from its last iteration's checkpoint, a run trains no iteration and keeps the same law by the
    same rule as the uninterrupted run (keep = best: the final law's loss against the best earlier one)."""
    ckpt = tmp_path / "checkpoint.pt"
    law, go = _neuma_run(scene, checkpoint_path=ckpt, iterations=2, keep="best", checkpoint_every=100)
    whole = go()
    assert torch.load(ckpt, weights_only=False)["iteration"] == 2  # the last iteration's, though checkpoint_every=100
    again_law, again = _neuma_run(scene, checkpoint_path=ckpt, iterations=2, keep="best", checkpoint_every=100)
    resumed = again()
    assert resumed.resumed_at == 2 and resumed.history == whole.history and resumed.status == "ok"
    assert resumed.selected == whole.selected and whole.selected["rule"] == "best"
    assert all(torch.equal(a, b) for a, b in zip(law.state().values(), again_law.state().values()))


def test_a_resumed_run_takes_back_its_last_update_as_the_uninterrupted_one(scene, tmp_path, monkeypatch):
    """NOTES session 43 (a review): the checkpoint holds the last update's Undo. Resumed after update 0, a rollout
    that diverges at once retakes update 0 at half the step and the run ends with the uninterrupted run's law; the
    same checkpoint without it (control: what checkpoints held before) ends "diverged before any update"."""
    ckpt = tmp_path / "checkpoint.pt"
    kw = dict(max_rejections=2, backtrack_factor=0.5, checkpoint_every=1)
    whole_law, run = _neuma_run(scene, iterations=3, **kw)
    _diverging_simulate(monkeypatch, fail_calls={1})
    whole = run()
    monkeypatch.undo()
    _neuma_run(scene, checkpoint_path=ckpt, iterations=1, **kw)[1]()  # stopped after update 0, checkpointed
    saved = torch.load(ckpt, weights_only=False)
    assert saved["undo"] is not None and saved["undo"]["it"] == 0

    def resume():
        law, go = _neuma_run(scene, checkpoint_path=ckpt, iterations=3, **kw)
        _diverging_simulate(monkeypatch, fail_calls={0})  # the first rollout after the resume
        try:
            return law, go()
        finally:
            monkeypatch.undo()

    law, resumed = resume()
    assert whole.status == resumed.status == "ok" and resumed.resumed_at == 1
    assert [(r["iteration"], r["lr_scale"]) for r in resumed.rejected] == [(1, 0.5)] == \
        [(r["iteration"], r["lr_scale"]) for r in whole.rejected]
    assert all(torch.equal(a, b) for a, b in zip(whole_law.state().values(), law.state().values()))
    torch.save({**saved, "undo": None}, ckpt)
    _, control = resume()
    assert control.status == "diverged" and "before any update" in control.message


def test_a_run_resumed_at_its_end_whose_final_law_diverges_keeps_the_law_before_it(scene, tmp_path, monkeypatch):
    """keep = best with no full-video loss during training (the curriculum's horizon never reached the whole video)
    and a final rollout that diverges: the law before the last update is kept, by the uninterrupted run and by one
    resumed from its last iteration's checkpoint alike (the Undo in the checkpoint; without it, control, the resumed
    run kept the diverged law)."""
    import gca.train.loop as loop

    def run(checkpoint):
        law, go = _neuma_run(scene, checkpoint_path=checkpoint, iterations=2, curriculum_start=0.25,
                             curriculum_until=1.0, keep="best", checkpoint_every=1)
        real = loop._gradient

        def gradient(*args, provenance=True, **kw):
            if not provenance:  # _select's evaluation of the final law
                raise FloatingPointError("planted: the final rollout diverged")
            return real(*args, provenance=provenance, **kw)

        monkeypatch.setattr(loop, "_gradient", gradient)
        try:
            return law, go()
        finally:
            monkeypatch.setattr(loop, "_gradient", real)

    ckpt = tmp_path / "checkpoint.pt"
    whole_law, whole = run(ckpt)
    assert whole.selected["best_earlier_loss"] == math.inf and "the final law diverged" in whole.selected["note"]
    again_law, again = run(ckpt)  # the checkpoint of iteration 2 is left: only the selection runs
    assert again.resumed_at == 2 and again.selected == whole.selected
    assert all(torch.equal(a, b) for a, b in zip(whole_law.state().values(), again_law.state().values()))
    torch.save({**torch.load(ckpt, weights_only=False), "undo": None}, ckpt)
    control_law, control = run(ckpt)
    assert control.selected["loss"] == math.inf
    assert not all(torch.equal(a, b) for a, b in zip(whole_law.state().values(), control_law.state().values()))


@pytest.mark.parametrize("gradient", ["material", "full"])
def test_fused_position_render_matches_two_passes(scene, gradient):
    """RGB + positions composited in one pass equal the separate renders (forward and gradient)."""
    from gca.train.objective import position_image_ref
    from gca.scenes.world import gaussians_at, render_gaussians

    body, view = scene[0], scene[1]
    objective = Objective(get_method("gca"), _data(scene, get_method("gca")), TrainConfig(),
                          RDGAConfig(r=5, k=5, global_gradient=gradient), CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    x = body.x0.clone().requires_grad_(True)
    means, covs = gaussians_at(body, x, torch.eye(3).expand(body.n_particles, 3, 3))
    fused = objective._render(means, covs, view, with_positions=True)
    rgb = render_gaussians(body, means, covs, body.colors, view.camera, torch.ones(3))["rgb"]
    pos = position_image_ref(body, means, covs, view.camera, gradient)
    torch.testing.assert_close(fused["rgb"], rgb)
    torch.testing.assert_close(fused["positions"], pos)
    g_fused = torch.autograd.grad(fused["positions"].sum() + fused["rgb"].sum(), x, retain_graph=True)[0]
    g_ref = torch.autograd.grad(pos.sum() + rgb.sum(), x)[0]
    # float32, summed over every pixel: a component can be a small difference of large sums (CI at 25d952f: 1.037 =
    # 23.88 - 22.84 with |g| up to 546, off by 1.5e-4), so the absolute tolerance scales with the gradient's size
    # (2e-6 of its largest component); a wrong or missing term is off by the terms' size (tens here).
    torch.testing.assert_close(g_fused, g_ref, rtol=1e-4, atol=2e-6 * g_ref.abs().max().item())


@pytest.fixture(scope="module")
def textured_scene(tmp_path_factory):
    """The ``scene`` fixture at 96^2: enough SIFT features that the rendered frames have matches."""
    torch.manual_seed(0)
    body = tiny_body(n_side=4, base_y=0.08)
    view, frames, _ = ground_truth_views(body, (0.5, -2.0, 0.0), n_frames=8, frame_every=2, resolution=96)
    est, keypoints = observations(view)
    prior = tmp_path_factory.mktemp("prior") / "jelly.pt"
    save_prior(prior, NeuralElasticity(), NeuralPlasticity(), family="jelly")
    return body, view, frames, est, keypoints, prior


@pytest.mark.parametrize("backend,weighted", [("sift", False), ("flow", False), ("flow", True)])
def test_batched_objective_equals_frame_by_frame(textured_scene, backend, weighted):
    """Objective.loss (all renders first, pooled matching, CPR's frames in one batched call, every frame's losses
    in one call on [T, ...] stacks with the matches padded (session 40), one stats read-back) equals the serial
    reference: each frame rendered, matched on the calling thread (SIFT against the cached keypoints, or flow against
    the video frame inside both masks), scored alone and given its own CPR call in turn; ``weighted``: with NeuMA's
    per-frame weights (``frame_weights``) on the image terms, the serial sum weighted frame by frame."""
    from gca.train.objective import _MeanStats
    from gca.vision.matching import match_frame

    scene = textured_scene
    method = get_method("gca")
    cfg = TrainConfig(curriculum_start=1.0, cpr_every=2)
    data = _data(scene, method)
    law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)

    def objective():
        return Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2),
                         MatchConfig(backend=backend, geometry="none"), cpr_target=("corotated", "identity"))

    n_video = len(data.video_frames)
    traj = _rollout(law, data, checkpoint=True)
    weights = [0.5 ** j for j in range(n_video)] if weighted else [1.0] * n_video
    batched_obj = objective()
    batched_obj.frame_weights = weights if weighted else None
    batched, stats = batched_obj.loss(traj, n_video, law)
    serial_obj, ref_stats, serial = objective(), _MeanStats(n_video), 0.0
    for j in range(n_video):
        outs = serial_obj._render_frame(traj, j)
        rgb = (outs["train0"]["rgb"].detach().clamp(0, 1).numpy() * 255 + 0.5).astype("uint8")
        video = (data.views["train0"].rgb[j].clip(0, 1) * 255 + 0.5).astype("uint8")
        inside = outs["train0"]["alpha"].detach().numpy() >= serial_obj.train0_rdga.alpha_threshold
        pq = match_frame(rgb, video, *data.keypoints[j], serial_obj.match, inside, data.views["train0"].mask[j])
        serial = serial + weights[j] * serial_obj._frame_loss(traj, j, outs, pq, ref_stats)
        if j % cfg.cpr_every == 0:  # CPR frame by frame (the objective batches its frames in one call)
            f = data.video_frames[j]
            R_e, R_p, _ = serial_obj.cpr.residuals(law.material.elasticity, law.material.plasticity, traj.F[f],
                                                   traj.F_trial[f])
            serial = serial + R_e + R_p
            ref_stats.add("R_e", R_e)
            ref_stats.add("R_p", R_p)
    assert stats["rdga/n_matches"] > 0 and stats["R_e"] > 0, "the test needs matches and CPR to compare"
    torch.testing.assert_close(batched, serial)
    assert stats == pytest.approx(ref_stats.read())
    params = law.trainable()
    g_b = torch.autograd.grad(batched, params, retain_graph=True, allow_unused=True)
    g_s = torch.autograd.grad(serial, params, allow_unused=True)
    for a, c in zip(g_b, g_s):
        assert (a is None) == (c is None)
        if a is not None:
            torch.testing.assert_close(a, c)


@pytest.mark.parametrize("name", ["gca", "pacnerf_depth", "pacnerf_depth_aligned", "neuma_multiview"])
def test_the_frames_losses_read_nothing_from_the_device(textured_scene, name):
    """Every frame's losses in one call (Objective._frames_loss, session 40) queue their work without one read of
    the device (the CPU sync detector, a CUDA twin): the matches go over in one copy, RDGA's checks are deferred, and
    the depth L1 terms no longer ask whether a mask is empty (``bool(mask.any())`` per frame before). Control: the
    deferred checks, judged, do read."""
    sys.path.insert(0, str(Path(__file__).parent))
    from host_sync import HostSync, no_host_sync
    from gca.align.rdga import judge
    from gca.train.objective import _MeanStats

    scene, method = textured_scene, get_method(name)
    data = _data(scene, method)
    law = build_law(get_method("gca"), scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
    objective = Objective(method, data, TrainConfig(curriculum_start=1.0), RDGAConfig(r=5, k=5),
                          CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    n_video = len(data.video_frames)
    traj = _rollout(law, data)
    renders = objective._render_frames(traj, n_video)
    matching = objective._start_matching(renders)
    (_, renders), = renders  # one chunk (4 frames, train.loss_chunk_frames 8)
    pqs = [f.result() for f in matching] if matching is not None else None
    assert (pqs is not None) == (name == "gca")
    checks = []
    with no_host_sync():
        losses = objective._frames_loss(traj, range(n_video), renders, pqs, _MeanStats(n_video), checks)
    assert losses.shape == (n_video,) and bool(torch.isfinite(losses).all()) and float(losses.detach().sum()) != 0
    if checks:
        with pytest.raises(HostSync):
            with no_host_sync():
                judge(checks)


@pytest.mark.parametrize("chunk", [0, 3])
def test_bad_renderer_input_names_its_frame_and_view_in_any_chunking(textured_scene, chunk):
    """The frames' renders are checked once for all (one read, the rows chunk by chunk, view by view, frame by frame):
    a non-finite particle at one video frame is named with that frame and the first view, whether the frames are
    rendered in one call or in chunks of 3 (session 40), and the frames' renders are chunked as the losses are."""
    from types import SimpleNamespace
    from gca.render.rasterize import RenderError

    scene, method = textured_scene, get_method("neuma_multiview")
    data = _data(scene, method)
    law = build_law(get_method("gca"), scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
    objective = Objective(method, data, TrainConfig(curriculum_start=1.0, loss_chunk_frames=chunk), RDGAConfig(r=5, k=5),
                          CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    n_video = len(data.video_frames)
    traj = _rollout(law, data)
    renders = objective._render_frames(traj, n_video)
    assert [list(js) for js, _ in renders] == ([list(range(n_video))] if chunk == 0 else
                                               [list(range(a, min(a + 3, n_video))) for a in range(0, n_video, 3)])
    bad = n_video - 1  # the last chunk's (a chunk of its own when chunked by 3)
    assert n_video % 3 == 1
    x = traj.x.clone()
    x[data.video_frames[bad], 7, 1] = float("nan")
    with pytest.raises(RenderError, match=f"video frame {bad}, view train0: means has 1 non-finite"):
        objective._render_frames(SimpleNamespace(x=x, F=traj.F), n_video)


def _diverging_simulate(monkeypatch, fail_calls, error=None):
    """Make ``loop.simulate`` raise ``error`` (SimulationDiverged) on the given call numbers; returns the
    parameters each call saw (the law's trainable tensors, cloned)."""
    from gca.sim.rollout import SimulationDiverged
    from gca.train import loop
    error = error or SimulationDiverged

    real, seen = loop.simulate, []

    def fake(solver, law, data, n_video, sweep=False):
        seen.append([p.detach().clone() for p in law.trainable()])
        if len(seen) - 1 in fail_calls:
            raise error(f"planted divergence at call {len(seen) - 1}")
        return real(solver, law, data, n_video, sweep)

    monkeypatch.setattr(loop, "simulate", fake)
    return seen


def _neuma_run(scene, checkpoint_path=None, process=None, **cfg_kw):
    """A NeuMA law on the tiny scene and a no-argument call that trains it (TrainConfig ``cfg_kw``; ``process``:
    train's)."""
    method = get_method("neuma")
    cfg = TrainConfig(**{"curriculum_start": 1.0, "keep": "last", **cfg_kw})
    law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
    objective = Objective(method, _data(scene, method), cfg, RDGAConfig(r=5, k=5),
                          CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    return law, (lambda: train(tiny_solver(), law, _data(scene, method), objective, cfg,
                               checkpoint_path=checkpoint_path, process=process))


@pytest.mark.parametrize("level", ["high", "highest"])
def test_training_runs_at_its_matmul_precision_and_restores_the_process_one(scene, monkeypatch, level):
    """train.matmul_precision holds while the run differentiates (every iteration and the final selection) and the
    process's own precision is back after the run."""
    import gca.train.loop as loop
    seen, original = [], loop._gradient

    def spy(*args, **kwargs):
        seen.append(torch.get_float32_matmul_precision())
        return original(*args, **kwargs)
    monkeypatch.setattr(loop, "_gradient", spy)
    other, own = ("highest" if level == "high" else "high"), torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision(other)
    try:
        _, run = _neuma_run(scene, iterations=2, keep="best", matmul_precision=level)
        assert run().status == "ok"
        assert seen == [level] * 3  # two iterations and the final law's evaluation
        assert torch.get_float32_matmul_precision() == other
    finally:
        torch.set_float32_matmul_precision(own)


def test_training_runs_its_mlp_kernel_and_restores_the_networks_own(scene, monkeypatch):
    """train.mlp_kernel is on every neural network while the run differentiates and the networks' own after; the
    simt run's first loss equals torch's to rounding (the same law)."""
    import gca.train.loop as loop
    from gca.laws.neural import NeuralElasticity, NeuralPlasticity
    seen, original = [], loop._gradient

    def spy(solver, law, *args, **kwargs):
        seen.append({m.mlp_kernel for m in law.material.modules() if isinstance(m, (NeuralElasticity, NeuralPlasticity))})
        return original(solver, law, *args, **kwargs)
    monkeypatch.setattr(loop, "_gradient", spy)
    losses = {}
    for kind in ("simt", "torch"):
        law, run = _neuma_run(scene, iterations=1, keep="last", mlp_kernel=kind)
        nets = [m for m in law.material.modules() if isinstance(m, (NeuralElasticity, NeuralPlasticity))]
        nets[0].mlp_kernel = "warp"  # a network's own choice (not the class default) must come back
        result = run()
        assert result.status == "ok"
        losses[kind] = result.history[0]["loss"]
        assert [net.mlp_kernel for net in nets] == ["warp"] + ["torch"] * (len(nets) - 1)  # restored, each its own
    assert seen == [{"simt"}, {"torch"}]
    assert losses["simt"] == pytest.approx(losses["torch"], rel=1e-5)


def test_a_run_whose_mlp_kernel_cannot_run_here_stops_before_reading_any_input(repo_root, tmp_path, monkeypatch):
    """The paper profile's train.mlp_kernel (triton_tf32, session 44) on a CPU without Triton's interpreter: one
    ConfigError naming params.yaml and the way out, raised before any input is read (these inputs do not exist).
    Control: the CI profile's torch passes the check and fails on the missing inputs instead."""
    from gca import config
    from gca.pipeline import train as pipeline_train
    from gca.pipeline.settings import Settings

    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    raw = config.read_yaml(repo_root / "params.yaml")
    missing = pipeline_train.SceneInputs(*(tmp_path / name for name in ("scene", "prep", "p.ply", "g.ply", "prior.pt")))
    velocity = ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    paper = Settings(config.resolve(raw, "paper"))
    assert paper.section_as(TrainConfig, "train").mlp_kernel == "triton_tf32"
    with pytest.raises(config.ConfigError, match=r"params.yaml: train.mlp_kernel=triton_tf32 .*ci profile"):
        pipeline_train.train_job(paper, "ball", get_method("gca"), missing, velocity, "cpu")
    ci = Settings(config.resolve(raw, "ci"))
    assert ci.section_as(TrainConfig, "train").mlp_kernel == "torch"
    with pytest.raises(Exception) as caught:
        pipeline_train.train_job(ci, "ball", get_method("gca"), missing, velocity, "cpu")
    assert "train.mlp_kernel" not in str(caught.value) and "scene directory not found" in str(caught.value)


def test_the_mlp_kernels_conditions_are_named():
    """gca.laws.neural.mlp_kernel_problem: torch's, warp's and simt's MLPs run anywhere; triton_tf32 on a CPU only where
    its kernels were decorated under Triton's interpreter (TRITON_INTERPRET at their import: a fresh process each)."""
    import os
    import subprocess

    from gca.laws.neural import MLP_KERNELS, mlp_kernel_problem
    assert all(mlp_kernel_problem(kind, "cpu") is None for kind in MLP_KERNELS if kind != "triton_tf32")
    pytest.importorskip("triton")
    code = "from gca.laws.neural import mlp_kernel_problem as p; print(repr(p('triton_tf32', 'cpu')))"
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    for interpret, expected in ((None, "TRITON_INTERPRET=1"), ("1", "None")):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                             env={**env, **({"TRITON_INTERPRET": interpret} if interpret else {})})
        assert out.returncode == 0 and expected in out.stdout, out.stdout + out.stderr


def test_matmul_precision_is_validated():
    with pytest.raises(ValueError, match="train.matmul_precision must be one of"):
        TrainConfig(matmul_precision="medium")
    with pytest.raises(ValueError, match="train.mlp_kernel must be one of"):
        TrainConfig(mlp_kernel="fast")
    for bad in (-1, 2.5, True):  # True would read as chunks of 1
        with pytest.raises(ValueError, match="train.loss_chunk_frames must be an integer >= 0"):
            TrainConfig(loss_chunk_frames=bad)
    assert TrainConfig(loss_chunk_frames=0).loss_chunk_frames == 0  # control: 0 (every frame in one call) is valid


def test_keep_best_returns_the_law_of_lowest_training_loss(scene):
    """keep="best": the run returns the law whose full-video training loss was lowest among the
    iterates and the final law (evaluated once more); its loss evaluated again is the one recorded."""
    import gca.train.loop as loop
    law, run = _neuma_run(scene, iterations=3, keep="best")
    result = run()
    sel = result.selected
    candidates = {h["iteration"]: h["loss"] for h in result.history} | {3: sel["final_loss"]}
    assert sel["rule"] == "best" and sel["loss"] == min(candidates.values())
    assert candidates[sel["iteration"]] == sel["loss"]
    data = _data(scene, get_method("neuma"))
    objective = Objective(get_method("neuma"), data, TrainConfig(curriculum_start=1.0), RDGAConfig(r=5, k=5),
                          CPRConfig(subset_size=16, n_groups=2), MatchConfig())
    rec = loop._gradient(tiny_solver(), law, data, objective, TrainConfig(), len(data.video_frames))
    assert rec["loss"] == pytest.approx(sel["loss"], rel=1e-5)


def test_keep_best_takes_back_a_final_update_that_made_things_worse(scene, monkeypatch):
    """The final law's loss is worse than an earlier iterate's: that earlier law is restored exactly;
    a final rollout that diverges also falls back to it."""
    import gca.train.loop as loop
    for final in (1e9, "diverge"):
        law, run = _neuma_run(scene, iterations=2, keep="best")
        seen = []
        real = loop._gradient

        def gradient(*args, **kw):
            rec = real(*args, **kw)
            seen.append([p.detach().clone() for p in law.trainable()])
            if len(seen) == 3:  # the final evaluation, after both updates
                if final == "diverge":
                    raise FloatingPointError("planted: the final rollout diverged")
                rec["loss"] = final
            return rec

        monkeypatch.setattr(loop, "_gradient", gradient)
        result = run()
        monkeypatch.setattr(loop, "_gradient", real)
        first, second = result.history[0]["loss"], result.history[1]["loss"]
        expect = 0 if first <= second else 1
        assert result.selected["iteration"] == expect and result.selected["final_loss"] == pytest.approx(
            math.inf if final == "diverge" else final)
        for p, saved in zip(law.trainable(), seen[expect]):
            assert torch.equal(p.detach(), saved)
        assert all(p.grad is None for p in law.trainable())


@pytest.mark.parametrize("error", ["SimulationDiverged", "CFLError"])
def test_a_diverging_update_is_taken_back_and_retaken_at_half_the_lr(scene, monkeypatch, error):
    """Iteration 1's rollout diverges (or the law got too stiff for dt): update 0 is undone and retaken
    from the same gradient at half the step (Adam's first step is lr * g / |g|), iteration 1 is retried
    from there, and the run goes on."""
    import gca.sim as sim
    law, run = _neuma_run(scene, iterations=3, max_rejections=2, backtrack_factor=0.5)
    seen = _diverging_simulate(monkeypatch, fail_calls={1}, error=getattr(sim, error))
    result = run()
    assert result.status == "ok", result.message
    assert [h["iteration"] for h in result.history] == [0, 1, 2]
    assert [(r["iteration"], r["lr_scale"]) for r in result.rejected] == [(1, 0.5)]
    assert "planted divergence at call 1" in result.rejected[0]["message"]
    assert len(seen) == 4  # iteration 0, 1 (diverged), 1 again, 2
    p0, p1, p1_retaken = seen[0], seen[1], seen[2]
    moved = False
    for a, b, c in zip(p0, p1, p1_retaken):
        torch.testing.assert_close(c - a, (b - a) / 2, rtol=1e-4, atol=1e-9)
        moved |= bool((b - a).abs().max() > 0)
    assert moved, "update 0 moved nothing: the test would not see a wrong retake"
    assert result.history[1]["lr_scale"] == 0.5 and result.history[0]["lr_scale"] == 1.0


def test_divergence_after_max_rejections_ends_the_run_with_the_last_finite_law(scene, monkeypatch):
    law, run = _neuma_run(scene, iterations=4, max_rejections=2)
    seen = _diverging_simulate(monkeypatch, fail_calls={1, 2, 3})
    result = run()
    assert result.status == "diverged" and result.iterations == 1
    assert "after 2 rejected updates in a row" in result.message
    assert [r["lr_scale"] for r in result.rejected] == [0.5, 0.25]
    assert [h["iteration"] for h in result.history] == [0]
    for p, p0 in zip(law.trainable(), seen[0]):  # the law whose rollout was finite, not the last attempt
        torch.testing.assert_close(p.detach(), p0, rtol=0, atol=0)


def test_a_diverged_run_keeps_its_best_law(scene, monkeypatch):
    """keep="best" and the run diverges at iteration 2 for good: the law of lowest loss among the
    iterates 0 and 1 is returned, not merely the last finite one."""
    law, run = _neuma_run(scene, iterations=4, max_rejections=0, keep="best")
    seen = _diverging_simulate(monkeypatch, fail_calls={2})
    result = run()
    assert result.status == "diverged" and [h["iteration"] for h in result.history] == [0, 1]
    losses = [h["loss"] for h in result.history]
    expect = losses.index(min(losses))
    assert result.selected == {"rule": "best", "iteration": expect, "loss": losses[expect]}
    for p, saved in zip(law.trainable(), seen[expect]):
        assert torch.equal(p.detach(), saved)


def test_divergence_of_the_prior_itself_is_not_retried(scene, monkeypatch):
    law, run = _neuma_run(scene, iterations=2, max_rejections=3)
    seen = _diverging_simulate(monkeypatch, fail_calls={0})
    result = run()
    assert result.status == "diverged" and "before any update" in result.message
    assert len(seen) == 1 and result.rejected == [] and result.history == []


def test_backtracking_settings_are_validated():
    with pytest.raises(ValueError, match="backtrack_factor"):
        TrainConfig(backtrack_factor=1.0)
    with pytest.raises(ValueError, match="max_rejections"):
        TrainConfig(max_rejections=-1)


def test_seeds_name_the_runs():
    """``train.seeds`` lists the runs; each run's ``seed`` is one of them (the first by default), and its folder
    is the method's name for seed 0 and ``<method>@seed<k>`` otherwise: the names the report parses back."""
    from gca.config import ConfigError
    from gca.report.runs import _NAME
    from gca.train.config import run_dir_name
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import run_seeds

    cfg = TrainConfig(seeds=[2, 0, 5])
    assert cfg.seeds == (2, 0, 5) and cfg.seed == 2 and TrainConfig().seed == 0
    assert dataclasses.replace(cfg, seed=5).seed == 5
    for bad in ([], [1, 1], [-1], [0.5], [True]):
        with pytest.raises(ValueError, match="train.seeds"):
            TrainConfig(seeds=bad)
    with pytest.raises(ValueError, match="is not one of train.seeds"):
        TrainConfig(seeds=(0, 1), seed=3)  # e.g. an old `train.seed: 3` beside the default seeds
    assert [run_dir_name("gca", s) for s in (0, 4)] == ["gca", "gca@seed4"]
    for s in (0, 4):
        parsed = _NAME.match(run_dir_name("neuma", s) + ".json")
        assert parsed["method"] == "neuma" and int(parsed["seed"] or 0) == s

    from gca import config

    shipped = config.load(path=Path(__file__).resolve().parents[1] / "params.yaml", via_dvc=False)["train"]
    params = Settings({"train": {**shipped, "seeds": [0, 1, 2]}})  # every train key is required
    assert run_seeds(params, get_method("gca")) == [0, 1, 2]
    # the prior does not depend on the seed, but its launch velocity comes from the seed's own nuisance draw
    assert run_seeds(params, get_method("nclaw")) == [0, 1, 2]
    assert run_seeds(params, get_method("gca"), [2, 1]) == [1, 2] and run_seeds(params, get_method("nclaw"), [1]) == [1]
    with pytest.raises(ConfigError, match=r"seeds \[7\] are not in train.seeds"):
        run_seeds(params, get_method("gca"), [7])


def test_prior_gradient_is_capped_only_when_it_dominates():
    """g = g_data + min(1, r |g_data| / |g_prior|) g_prior: a prior 1000x the data is cut to r x; a weak one
    is added unscaled (the objective as written); r = 0 adds it unscaled whatever its size."""
    from gca.train.objective import add_prior_gradient

    a, b = torch.tensor([3.0, 0.0, 4.0], dtype=torch.float64), torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64)
    for weight, ratio, expect_scale in ((1000.0, 0.5, 0.5 * 5.0 / (1000.0 * 2.0)), (1e-3, 0.5, 1.0), (1000.0, 0.0, 1.0)):
        p = torch.zeros(3, dtype=torch.float64, requires_grad=True)
        (p @ a).backward()
        info = add_prior_gradient([p], [weight * b], ratio=ratio)
        assert info["grad_norm_data"] == pytest.approx(5.0) and info["grad_norm_prior"] == pytest.approx(2.0 * weight)
        assert info["prior_scale"] == pytest.approx(expect_scale)
        torch.testing.assert_close(p.grad, a + expect_scale * weight * b)


def _gca_step(scene, method_name="gca", **cpr_kw):
    method = get_method(method_name)
    cfg = TrainConfig(iterations=1, curriculum_start=1.0, keep="last")
    law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), cfg.lr_elasticity,
                    cfg.lr_plasticity, cfg.lr_explicit, family_presets={"jelly": {**JELLY, "E": 4.0e4}}, category="elastic")
    before = [p.detach().clone() for p in law.trainable()]
    objective = Objective(method, _data(scene, method), cfg, RDGAConfig(r=5, k=5),
                          CPRConfig(subset_size=16, n_groups=2, **cpr_kw), MatchConfig())
    result = train(tiny_solver(), law, _data(scene, method), objective, cfg)
    moved = any(not torch.equal(b, p.detach()) for b, p in zip(before, law.trainable()))
    return result, moved


def test_capped_cpr_gradient_in_a_training_step(scene):
    """With ``max_grad_ratio`` the gca step records both norms and keeps CPR's share at most the ratio; a
    method with CPR only (no_rdga) is not capped to nothing."""
    result, _ = _gca_step(scene, max_grad_ratio=0.1)
    rec = result.history[0]
    assert result.status == "ok" and rec["grad_norm_data"] > 0 and rec["grad_norm_prior"] > 0
    assert rec["prior_scale"] == pytest.approx(min(1.0, 0.1 * rec["grad_norm_data"] / rec["grad_norm_prior"]))
    result, moved = _gca_step(scene, "no_rdga", max_grad_ratio=0.1)
    assert result.history[0]["prior_scale"] == 1.0 and moved
    with pytest.raises(ValueError, match="max_grad_ratio"):
        CPRConfig(max_grad_ratio=-1.0)
    with pytest.raises(ValueError, match="chunk_frames"):
        CPRConfig(chunk_frames=-1)


@pytest.mark.parametrize("chunk", [1, 2, 0])
def test_chunked_prior_gradient_equals_the_whole_graph(textured_scene, chunk):
    """Objective.prior_gradient (CPR chunk by chunk, each graph freed) = the gradient of the one-call
    R_e + R_p of :meth:`Objective.loss` (the reference), and the same R_e, R_p stats."""

    scene = textured_scene
    method = get_method("no_rdga")  # CPR only: the loss is R_e + R_p
    cfg = TrainConfig(curriculum_start=1.0, cpr_every=1)
    data = _data(scene, method)
    law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
    params = law.trainable()
    traj = _rollout(law, data, checkpoint=True)
    n_video = len(data.video_frames)
    objective = lambda: Objective(method, data, cfg, RDGAConfig(r=5, k=5),  # noqa: E731
                                  CPRConfig(subset_size=16, n_groups=2, chunk_frames=chunk), MatchConfig())
    whole, stats = objective().loss(traj, n_video, law)
    g_ref = torch.autograd.grad(whole, params, allow_unused=True)
    value, g, chunk_stats = objective().prior_gradient(traj, n_video, law, params)
    assert n_video >= 3 and float(whole.detach()) > 0
    torch.testing.assert_close(value, whole.detach(), rtol=1e-5, atol=0)
    assert chunk_stats["R_e"] == pytest.approx(stats["R_e"], rel=1e-5)
    assert chunk_stats["R_p"] == pytest.approx(stats["R_p"], rel=1e-5)
    for a, c in zip(g, g_ref):
        assert (a is None) == (c is None)
        if a is not None:
            torch.testing.assert_close(a, c, rtol=1e-4, atol=1e-6 * float(c.abs().max()))


def test_lora_init_is_seeded(scene):
    """LoRA's A matrices come from ``train.seed``: the same seed builds the same law in any process and
    whatever torch's global RNG did before; another seed another one (session 8: they were unseeded)."""
    def adapters(seed, global_seed):
        torch.manual_seed(global_seed)  # the global RNG must not matter
        law = build_law(get_method("gca"), scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3,
                        1e-2, seed=seed)
        return [p.detach().clone() for p in law.trainable()]

    same, again, other = adapters(0, 1), adapters(0, 2), adapters(1, 1)
    assert all(torch.equal(a, b) for a, b in zip(same, again))
    assert any(not torch.equal(a, b) for a, b in zip(same, other))


@pytest.mark.parametrize("sweep", [False, True])
@pytest.mark.parametrize("name,chunk,weighted", [("gca", 0, False), ("gca", 3, False), ("neuma", 0, False),
                                                 ("neuma", 3, True), ("no_rdga", 0, False)])
def test_objective_gradient_equals_its_reference_loss(textured_scene, name, chunk, weighted, sweep):
    """Objective.gradient (what training differentiates: CPR chunked, image terms backward separately) =
    the autograd gradient of Objective.loss (every term with its graph, one call) when CPR's gradient is not
    rescaled (max_grad_ratio = 0: eq. 8 as written), same loss value; with a ratio the CPR share is scaled.
    ``sweep``: on a swept rollout (train.reverse_sweep: each frame's loss differentiated last frame first into
    the rollout's ReverseSweep) the same, to float rounding; ``chunk``: the frames' losses ``train.loss_chunk_frames``
    at a time (chunks of 3, the last one shorter, last first) against the reference's one call, the same;
    ``weighted``: with NeuMA's per-frame weights, which each chunk must take for its own frames."""

    scene, method = textured_scene, get_method(name)
    cfg = TrainConfig(curriculum_start=1.0, cpr_every=1, loss_chunk_frames=chunk)
    whole_cfg = dataclasses.replace(cfg, loss_chunk_frames=0)  # the reference: every frame in one call
    data = _data(scene, method)
    law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
    params = law.trainable()
    n_video = len(data.video_frames)
    weights = [1.0, 0.5, 0.25, 2.0, 0.75][:n_video] if weighted else None
    assert not weighted or (len(weights) == n_video and n_video > chunk)

    def objective(ratio, config=cfg):
        made = Objective(method, data, config, RDGAConfig(r=5, k=5),
                         CPRConfig(subset_size=16, n_groups=2, chunk_frames=1, max_grad_ratio=ratio), MatchConfig())
        made.frame_weights = weights
        return made

    def traj(swept=sweep):
        return _rollout(law, data, sweep=swept)

    whole, _ = objective(0.0, whole_cfg).loss(traj(False), n_video, law)
    g_ref = torch.autograd.grad(whole, params, allow_unused=True)
    if weighted:  # control: the same frames unweighted are another loss
        unweighted = objective(0.0, whole_cfg)
        unweighted.frame_weights = None
        assert abs(float(unweighted.loss(traj(False), n_video, law)[0].detach()) - float(whole.detach())) > \
            1e-3 * abs(float(whole.detach()))
    phases = []
    value, stats = objective(0.0).gradient(traj(), n_video, law, phases.append)
    # finite and nonzero; not positive: the anchor term (eq. 7, a sum of -gamma) under the tuned lambda_2 may lead
    assert phases == ["render_losses", "backward"]
    assert math.isfinite(float(whole.detach())) and float(whole.detach()) != 0
    torch.testing.assert_close(value, whole.detach(), rtol=1e-5, atol=0)
    for p, r in zip(params, g_ref):
        ref = torch.zeros_like(p) if r is None else r
        torch.testing.assert_close(p.grad if p.grad is not None else torch.zeros_like(p), ref, rtol=1e-4, atol=1e-9)
    if name == "gca":  # negative control: a ratio that binds changes the gradient, not the loss
        for p in params:
            p.grad = None
        value2, stats2 = objective(1e-3).gradient(traj(), n_video, law)
        assert stats2["prior_scale"] < 1 and float(value2) == pytest.approx(float(value), rel=1e-5)
        assert any(not torch.allclose(p.grad, r) for p, r in zip(params, g_ref) if r is not None)


def test_train0_matching_runs_while_cpr_computes(textured_scene, monkeypatch):
    """Objective.gradient starts the matching of train0's frames (the default backend, dense flow) before CPR's
    gradient (the host threads overlap CPR's work) and feeds the losses the same matches as matching each rendered
    frame with its video frame on its own."""
    import gca.train.objective as objective_module
    from gca.vision.matching import match_frame

    scene, method = textured_scene, get_method("gca")
    cfg = TrainConfig(curriculum_start=1.0, cpr_every=1)
    data = _data(scene, method)
    law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2)
    n_video = len(data.video_frames)
    traj = _rollout(law, data)
    objective = Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2),
                          MatchConfig())
    events, seen = [], {}
    start, prior, losses = objective._start_matching, objective.prior_gradient, objective._frame_losses

    def start_spy(renders):
        events.append("match")
        (_, out), = renders  # one chunk (4 frames, train.loss_chunk_frames 8)
        seen["frames"] = list(objective_module.to_uint8(out["train0"]["rgb"]).numpy())
        seen["inside"] = list(out["train0"]["alpha"].detach().numpy() >= objective.train0_rdga.alpha_threshold)
        seen["futures"] = start(renders)
        return seen["futures"]

    def losses_spy(traj_, renders, matching):
        seen["matches"] = [f.result() for f in matching]
        return losses(traj_, renders, matching)

    monkeypatch.setattr(objective, "_start_matching", start_spy)
    monkeypatch.setattr(objective, "prior_gradient", lambda *a: (events.append("cpr"), prior(*a))[1])
    monkeypatch.setattr(objective, "_frame_losses", losses_spy)
    objective.gradient(traj, n_video, law)
    assert events == ["match", "cpr"] and len(seen["futures"]) == n_video
    view = data.views["train0"]
    direct = [match_frame(f, (view.rgb[j].clip(0, 1) * 255 + 0.5).astype(np.uint8), *kp, objective.match, inside,
                          view.mask[j])
              for j, (f, kp, inside) in enumerate(zip(seen["frames"], data.keypoints, seen["inside"]))]
    assert sum(len(p) for p, _ in direct) > 0  # the scene has matches (else the comparison is empty)
    for (p, q), (p_ref, q_ref) in zip(seen["matches"], direct):
        np.testing.assert_array_equal(p, p_ref)
        np.testing.assert_array_equal(q, q_ref)
    # a method without matching terms starts none (NeuMA: colour only)
    assert Objective(get_method("neuma"), _data(scene, get_method("neuma")), cfg, RDGAConfig(r=5, k=5),
                     CPRConfig(subset_size=16, n_groups=2), MatchConfig())._start_matching([]) is None


def test_methods_declare_their_terms():
    """Every registry method's terms are known; the RDGA switches follow from them alone, and bad declarations fail."""
    from gca.train.methods import TERMS, Method

    assert all(set(m.terms) <= TERMS.keys() for m in METHODS.values())
    assert get_method("gca").rdga_switches() == {"enabled": True, "use_global": True, "use_anchor": True,
                                                 "depth_term": "rank"}
    assert get_method("no_global").rdga_switches()["use_global"] is False
    assert get_method("rank_to_l1").rdga_switches()["depth_term"] == "l1"
    assert get_method("neuma").rdga_switches() is None and get_method("no_rdga").rdga_switches() is None
    assert Method("t", terms=("global",)).rdga_switches()["lambda_mask"] == 0.0  # alignment without L_mask
    assert get_method("no_cpr").uses("silhouette") and not get_method("no_cpr").uses("cpr")
    with pytest.raises(ValueError, match="unknown loss terms"):
        Method("bad", terms=("mask",))
    with pytest.raises(ValueError, match="two forms"):
        Method("bad", terms=("anchor", "anchor_l1"))
    with pytest.raises(ValueError, match="two forms"):
        Method("bad", terms=("depth_l1", "depth_l1_aligned"))
    with pytest.raises(ValueError, match="cpr_remove_target"):
        Method("bad", terms=("silhouette",), cpr_remove_target=True)
    with pytest.raises(KeyError):
        get_method("gca").uses("mask")


@pytest.mark.parametrize("sweep", [False, True])
def test_a_nonfinite_gradient_is_traced_by_a_probed_replay(scene, sweep, monkeypatch):
    """A healthy iteration attaches no gradient probe (its hooks were a large share of a host-bound iteration, NOTES
    s39); a non-finite gradient is raised as a divergence whose message names where it entered, from the same
    iteration replayed with the probe (here the particles-to-Gaussians map, broken on purpose), in either gradient
    pass. A break that does not come back in the replay is said to be not reproduced, no stage named."""
    import gca.train.objective as objective_module
    from gca.train import loop
    from gca.train.probe import GradProbe

    method = get_method("gca")
    data = _data(scene, method)
    probes = []
    monkeypatch.setattr(loop, "GradProbe", lambda: probes.append(GradProbe()) or probes[-1])

    def gradient():
        cfg = TrainConfig(iterations=1, curriculum_start=1.0, term_shares_every=0, reverse_sweep=sweep)
        law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2, seed=0)
        objective = Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2),
                              MatchConfig())
        return law, objective, lambda: loop._gradient(tiny_solver(), law, data, objective, cfg,
                                                      len(data.video_frames))

    law, objective, run = gradient()
    assert math.isfinite(run()["grad_norm"]) and probes == [] and objective.probe is None  # healthy: no probe
    advance = objective.state()["cpr"]["calls"]  # CPR's calls in one iteration (from a fresh objective)
    assert advance > 0
    real, calls = objective_module.gaussians_at, []

    def broken_map(body, x, F, every_call=True):
        calls.append(1)
        means, covs = real(body, x, F)
        return (NaNBackward.apply(means) if every_call or len(calls) <= 1 else means), covs  # one call: every frame

    monkeypatch.setattr(objective_module, "gaussians_at", broken_map)
    law, objective, run = gradient()
    with pytest.raises(FloatingPointError, match="non-finite gradients after backward .*provenance: .*"
                       "first broken at 'particles': made by the particles-to-Gaussians map's backward"):
        run()
    assert len(probes) == 1 and objective.probe is None  # one probed replay, detached after it
    assert objective.state()["cpr"]["calls"] == advance  # the replay's CPR calls taken back
    monkeypatch.setattr(objective_module, "gaussians_at", lambda *a: broken_map(*a, every_call=False))
    calls.clear()
    law, objective, run = gradient()
    with pytest.raises(FloatingPointError, match="replay of the iteration had finite gradients \\(not reproduced"):
        run()
    assert len(calls) == 2  # the iteration and its replay each placed every frame's Gaussians in one call


def test_a_probed_replay_leaves_cpr_where_the_iteration_did_and_its_own_failure_is_said(scene, monkeypatch):
    """The replay runs from the objective's state before the iteration (CPR's call count and fits: with
    ``refit_every`` > 1 a second advance would shift every later refit) and leaves it where the iteration left it;
    a replay that fails in any way (here a RuntimeError, which is no divergence) is said in the divergence's
    message, which stays a FloatingPointError (the loop rejects the update instead of crashing)."""
    import gca.train.objective as objective_module
    from gca.train import loop

    method = get_method("gca")
    data = _data(scene, method)
    cfg = TrainConfig(iterations=1, curriculum_start=1.0, term_shares_every=0)
    law = build_law(method, scene[5], "jelly", 1000.0, LoRAConfig(rank=4, alpha=4.0), 1e-2, 1e-3, 1e-2, seed=0)
    objective = Objective(method, data, cfg, RDGAConfig(r=5, k=5), CPRConfig(subset_size=16, n_groups=2, refit_every=3),
                          MatchConfig())
    calls = lambda: objective.state()["cpr"]["calls"]  # noqa: E731
    run = lambda: loop._gradient(tiny_solver(), law, data, objective, cfg, len(data.video_frames))  # noqa: E731
    c0 = calls()
    run()
    advance = calls() - c0
    assert advance > 0
    real, renders = objective_module.gaussians_at, []

    def broken_map(body, x, F):
        renders.append(1)
        if len(renders) > 1:  # the replay's (one call places every frame's Gaussians)
            raise RuntimeError("planted: the replay fails")
        means, covs = real(body, x, F)
        return NaNBackward.apply(means), covs

    monkeypatch.setattr(objective_module, "gaussians_at", broken_map)
    c1 = calls()
    with pytest.raises(FloatingPointError, match="non-finite gradients after backward .*provenance: the probed replay "
                       "of the iteration failed \\(RuntimeError: planted: the replay fails\\)"):
        run()
    assert calls() - c1 == advance and objective.probe is None
