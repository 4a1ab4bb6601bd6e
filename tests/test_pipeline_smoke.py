"""End-to-end smoke run of every stage main at the CI profile, into a temporary directory.

The shipped params.yaml is used with `profile: ci`, restricted to one scene (the gel duck, which
also exercises the law-level metrics) and a few methods so the chain runs in about a minute:
assets -> particles -> prior -> ground_truth -> preprocess -> train -> evaluate -> report.
"""

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "stages"))

SCENE, OBJECT, FAMILY = "duck", "duck", "jelly"
METHODS = ["gca", "neuma", "nclaw", "pacnerf_depth"]


def _params(tmp: Path) -> Path:
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["profile"] = "ci"
    raw["objects"] = {OBJECT: raw["objects"][OBJECT]}
    raw["scenes"] = {SCENE: {**raw["scenes"][SCENE], "methods": METHODS}}
    raw["prior"]["families"] = {FAMILY: raw["prior"]["families"][FAMILY]}
    raw["demo"]["new_shape"].update(law_scene=SCENE, object=OBJECT)  # the demo refers to scenes that exist
    for side in ("a", "b"):
        raw["demo"]["interaction"][side]["scene"] = SCENE
    raw["demo"]["captures"] = {}  # no capture scene here (tests/test_capture_e2e.py)
    path = tmp / "params.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pipeline")
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{tmp / 'mlflow.db'}"
    params = str(_params(tmp))
    d = lambda *p: str(tmp.joinpath(*p))  # noqa: E731
    import assets, ground_truth, particles, preprocess, prior, report, train, evaluate  # noqa: E401

    assets.main(["--object", OBJECT, "--out", d("data/assets", OBJECT), "--metrics", d("metrics/assets.json"),
                 "--params", params])
    particles.main(["--object", OBJECT, "--assets", d("data/assets", OBJECT), "--out", d("data/particles/duck.npz"),
                    "--metrics", d("metrics/particles.json"), "--params", params])
    prior.main(["--family", FAMILY, "--out", d("models/prior", f"{FAMILY}.pt"), "--metrics", d("metrics/prior.json"),
                "--plots", d("metrics/prior.png"), "--params", params])
    ground_truth.main(["--scene", SCENE, "--assets", d("data/assets", OBJECT), "--particles", d("data/particles/duck.npz"),
                       "--out", d("data/scenes", SCENE), "--gt", d("data/gt", SCENE), "--metrics", d("metrics/gt.json"),
                       "--params", params])
    # preprocessing and training run with the ground-truth directory absent, and open nothing under it
    hidden = tmp / "hidden_gt"
    (tmp / "data/gt").rename(hidden)
    common = ["--scene", SCENE, "--scene-dir", d("data/scenes", SCENE), "--particles", d("data/particles/duck.npz"),
              "--gaussians", d("data/assets", OBJECT, "gaussians.ply"), "--prior-dir", d("models/prior"), "--params", params]
    from test_scenes_truth_isolation import recorder
    with recorder() as rec:
        preprocess.main(["--scene", SCENE, "--scene-dir", d("data/scenes", SCENE), "--out", d("data/prep", SCENE),
                         "--metrics", d("metrics/prep.json"), "--params", params])
        train.main(common + ["--prep", d("data/prep", SCENE), "--out", d("runs", SCENE)])
    (tmp / "gt_opened_by_training.json").write_text(json.dumps({
        "gt": [p for p in rec.paths if "gt" in Path(p).parts or str(hidden) in p],
        "prep_opened": sum(str(tmp / "data/prep") in p for p in rec.paths)}))
    hidden.rename(tmp / "data/gt")
    evaluate.main(common + ["--gt", d("data/gt", SCENE), "--runs", d("runs", SCENE), "--out", d("metrics/eval", SCENE)])
    report.main(["--metrics", d("metrics/eval"), "--out", d("reports"), "--summary", d("metrics/report.json"),
                 "--params", params])
    return tmp


def test_ground_truth_outputs_are_consistent(pipeline):
    from gca.scenes import load_view, read_meta, truth

    scene_dir, gt_dir = pipeline / "data/scenes" / SCENE, pipeline / "data/gt" / SCENE
    meta = read_meta(scene_dir)
    view = load_view(scene_dir, "train0")
    T = len(meta["video_frames"])
    assert view.rgb.shape[0] == T and view.mask is None and view.depth is None
    assert truth.load_trajectory(gt_dir).shape[0] == T + 1
    assert (scene_dir / "preview.gif").is_file()
    assert set(meta["views"]["train"]) == {"train0", "train1", "train2"} and meta["views"]["eval"]
    alpha, depth = truth.load_alpha(gt_dir, "train0"), truth.load_true_depth(gt_dir, "train0")
    mask = alpha > 0.5
    assert 0.005 < mask.mean() < 0.8, "the object should be visible but not fill the frame"
    assert np.all(depth[mask] > 0) and np.all(depth[~mask] == 0)


def test_preprocess_and_training_never_opened_the_ground_truth(pipeline):
    opened = json.loads((pipeline / "gt_opened_by_training.json").read_text())
    assert opened["prep_opened"] > 0  # the recorder saw the stages' own reads (not a vacuous pass)
    assert opened["gt"] == [], opened["gt"]


def test_true_alpha_matches_the_rendered_alpha(pipeline):
    """Re-simulate and re-render the last ground-truth frame: the stored true alpha is its alpha."""
    import torch

    from gca import config
    from gca.laws.presets import material_from_preset
    from gca.pipeline.settings import Settings
    from gca.scenes import load_view, read_meta, truth
    from gca.scenes.ground_truth import simulate_scene
    from gca.scenes.world import gaussians_at, render_gaussians

    settings = Settings(config.load(path=pipeline / "params.yaml", via_dvc=False))
    scene, video = settings.scene(SCENE), settings.video
    scene_dir = pipeline / "data/scenes" / SCENE
    body = settings.load_body(pipeline / "data/particles/duck.npz", pipeline / "data/assets" / OBJECT / "gaussians.ply")
    material = material_from_preset(settings.material(scene.material), dt=scene.dt, n_particles=body.n_particles)
    traj = simulate_scene(body, material, scene, video, settings.sim)
    view, meta = load_view(scene_dir, "train0"), read_meta(scene_dir)
    j, f = len(meta["video_frames"]) - 1, meta["video_frames"][-1]
    means, covs = gaussians_at(body, traj.x[f], traj.F[f])
    with torch.no_grad():
        alpha = render_gaussians(body, means, covs, body.colors, view.camera, torch.ones(3))["alpha"].numpy()
    stored = truth.load_alpha(pipeline / "data/gt" / SCENE, "train0")[j] > video.mask_threshold
    agree = ((alpha > video.mask_threshold) == stored).mean()
    assert agree > 0.999, f"true alpha and re-rendered alpha agree on only {agree:.4f} of the pixels"


def test_every_method_has_metrics_and_reports_exist(pipeline):
    for method in METHODS:
        m = json.loads((pipeline / "metrics/eval" / SCENE / f"{method}.json").read_text())
        assert m["method"] == method and m["profile"] == "ci"
        assert m["status"] == "ok", (method, m["status"])  # no method diverges at the CI profile
        assert np.isfinite(m["chamfer_mean"]) and len(m["chamfer_per_frame"]) > 1
        assert 0 < m["psnr_train"] < 100
        trained = json.loads((pipeline / "runs" / SCENE / method / "train.json").read_text())
        assert m["train_commit"] == trained["commit"] and m["commit"] not in ("", "unknown")
        assert m["velocity_source"] == "train.json"  # evaluated with the launch velocity it trained with
    gca = json.loads((pipeline / "metrics/eval" / SCENE / "gca.json").read_text())
    assert "law_error_uniaxial_pct" in gca and "law_curves" in gca
    assert (pipeline / "reports/README.md").is_file()
    assert f"trained at `{gca['train_commit']}`" in (pipeline / "reports/table1_synthetic_cd.md").read_text()


def test_training_wrote_history_and_adapters(pipeline):
    run = pipeline / "runs" / SCENE
    v0 = json.loads((run / "velocity.json").read_text())["v0"]
    assert len(v0) == 3 and all(np.isfinite(v0))
    for method in ("gca", "neuma"):
        train = json.loads((run / method / "train.json").read_text())
        assert train["status"] == "ok", (method, train["status"])
        assert (run / method / "law.pt").is_file() and not (run / method / "checkpoint.pt").exists()
        assert train["commit"] not in ("", "unknown") and train["device"].startswith("cpu")  # what made it
        assert train["velocity"] == {k: v for k, v in json.loads((run / "velocity.json").read_text()).items()
                                     if k in ("v0", "w0")}  # the launch velocity it trained with


def test_an_interrupted_train_stage_resumes_with_its_launch_velocity(pipeline, tmp_path, monkeypatch, capsys):
    """A train stage re-run where a method left a checkpoint (stopped by grid.py's deadline) does not
    estimate the launch velocity again: its first iterations used the one in velocity.json."""
    import shutil
    import train

    out = tmp_path / "runs"
    shutil.copytree(pipeline / "runs" / SCENE, out)
    (out / "neuma" / "checkpoint.pt").write_bytes(b"")  # the marker of an interrupted run (train_method is stubbed)
    saved = json.loads((out / "velocity.json").read_text())

    def no_estimate(*a, **k):
        raise AssertionError("the launch velocity was estimated again")

    used = []
    monkeypatch.setattr(train, "estimate_scene_velocity", no_estimate)
    monkeypatch.setattr(train, "train_method", lambda params, scene, method, inputs, velocity, *a: used.append(velocity)
                        or {"status": "ok", "train_seconds": 0.0})
    params = str(pipeline / "params.yaml")
    d = lambda *p: str(pipeline.joinpath(*p))  # noqa: E731
    train.main(["--scene", SCENE, "--scene-dir", d("data/scenes", SCENE), "--particles", d("data/particles/duck.npz"),
                "--gaussians", d("data/assets", OBJECT, "gaussians.ply"), "--prior-dir", d("models/prior"),
                "--params", params, "--prep", d("data/prep", SCENE), "--out", str(out), "--methods", "neuma"])
    assert used and [list(v) for v in used[0]] == [saved["v0"], saved["w0"]]
    # the marker has no stamp of the params and inputs it was made with (gca.stamp): not resumed, and said so
    assert f"{out / 'neuma' / 'checkpoint.pt'}: not resumed: the checkpoint has no stamp" in capsys.readouterr().out
    assert not (out / "neuma" / "checkpoint.pt").exists()  # no checkpoint: a fresh run estimates it
    with pytest.raises(AssertionError, match="estimated again"):
        train.main(["--scene", SCENE, "--scene-dir", d("data/scenes", SCENE), "--particles", d("data/particles/duck.npz"),
                    "--gaussians", d("data/assets", OBJECT, "gaussians.ply"), "--prior-dir", d("models/prior"),
                    "--params", params, "--prep", d("data/prep", SCENE), "--out", str(out), "--methods", "neuma"])


def test_a_checkpoint_of_other_params_is_not_resumed(pipeline, tmp_path, monkeypatch, capsys):
    """Issue 24's probe: a train stage stopped mid-run, then re-run with other params (2 iterations, lr x100),
    trains afresh and says so; re-run with its own params, it resumes."""
    import shutil
    import train

    from gca import stop

    out = tmp_path / "runs"
    shutil.copytree(pipeline / "runs" / SCENE, out)
    seen = []

    def interrupted(params, scene, method, inputs, velocity, out_dir, *a):
        seen.append((out_dir / "checkpoint.pt").is_file())
        (out_dir / "checkpoint.pt").write_bytes(b"iteration 15 of 40")
        raise stop.Terminated()

    saved = json.loads((out / "velocity.json").read_text())
    estimated = []

    def estimate(params, scene, inputs, path, device):
        estimated.append(path)
        path.write_text(json.dumps({"v0": saved["v0"], "w0": saved["w0"]}))
        return {"v0": saved["v0"], "w0": saved["w0"]}

    monkeypatch.setattr(train, "estimate_scene_velocity", estimate)
    monkeypatch.setattr(train, "train_method", interrupted)
    d = lambda *p: str(pipeline.joinpath(*p))  # noqa: E731
    raw = yaml.safe_load((pipeline / "params.yaml").read_text())
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump({**raw, "train": {**raw["train"], "iterations": 2,
                                                      "lr_elasticity": 100 * raw["train"]["lr_elasticity"]}}))

    def stage(params):
        with pytest.raises(stop.Terminated):
            train.main(["--scene", SCENE, "--scene-dir", d("data/scenes", SCENE), "--particles", d("data/particles/duck.npz"),
                        "--gaussians", d("data/assets", OBJECT, "gaussians.ply"), "--prior-dir", d("models/prior"),
                        "--params", str(params), "--prep", d("data/prep", SCENE), "--out", str(out), "--methods", "neuma"])

    stage(pipeline / "params.yaml")  # a fresh run, stopped
    stage(pipeline / "params.yaml")  # same params and inputs: resumes
    capsys.readouterr()
    stage(other)  # other params: the checkpoint goes
    assert seen == [False, True, False]
    assert len(estimated) == 1  # the resumed runs reuse the stamped velocity.json (train params are not its inputs)
    assert capsys.readouterr().out.splitlines()[0].startswith(
        f"{out / 'neuma' / 'checkpoint.pt'}: not resumed: the checkpoint was made with other params or inputs (stamp ")


def test_seeds_are_separate_runs_that_the_report_averages(pipeline, tmp_path):
    """``train.seeds: [0, 3]``: every method runs once per seed (``gca``, ``gca@seed3``, ``nclaw@seed3``), each seed
    on its own nuisance draw (issue 22 item 4) of the one simulated trajectory: the ground_truth and preprocess stages
    write seed 3's observations beside seed 0's, which stay byte for byte those of ``train.seeds: [0]``; training
    opens seed 3's and never the ground truth; evaluation writes one record per run and the report reduces them to
    mean and std."""
    import shutil

    import evaluate
    import ground_truth
    import preprocess
    import torch
    import train

    from gca import config
    from gca.config import ConfigError
    from gca.report.runs import load_runs, reduce_seeds
    from gca.train.methods import get_method
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import SceneInputs, load_learned_law
    from test_scenes_truth_isolation import recorder

    raw = yaml.safe_load((pipeline / "params.yaml").read_text())
    raw["train"]["seeds"] = [0, 3]
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(raw, sort_keys=False))
    d = lambda *p: str(pipeline.joinpath(*p))  # noqa: E731
    t = lambda *p: str(tmp_path.joinpath(*p))  # noqa: E731
    ground_truth.main(["--scene", SCENE, "--assets", d("data/assets", OBJECT), "--particles", d("data/particles/duck.npz"),
                       "--out", t("scenes"), "--gt", t("gt"), "--metrics", t("gt.json"), "--params", str(params)])
    preprocess.main(["--scene", SCENE, "--scene-dir", t("scenes"), "--out", t("prep"), "--metrics", t("prep.json"),
                     "--params", str(params)])

    def files(root: Path) -> dict:
        return {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*")
                if p.is_file() and not p.relative_to(root).parts[0].startswith("seed")}

    # seed 0's observations and the ground truth: the same bytes as the pipeline's, made with train.seeds [0]
    for ours, theirs in (("scenes", "data/scenes"), ("prep", "data/prep"), ("gt", "data/gt")):
        assert files(tmp_path / ours) == files(pipeline / theirs / SCENE), ours
    assert (tmp_path / "scenes/seed3/views/train0/depth_sim.npy").is_file() and (tmp_path / "prep/seed3/masks.npy").is_file()
    assert not np.array_equal(np.load(tmp_path / "prep/seed3/masks.npy"), np.load(tmp_path / "prep/masks.npy"))
    common = ["--scene", SCENE, "--scene-dir", t("scenes"), "--particles", d("data/particles/duck.npz"),
              "--gaussians", d("data/assets", OBJECT, "gaussians.ply"), "--prior-dir", d("models/prior"),
              "--params", str(params), "--methods", "gca", "nclaw"]
    gt = ["--gt", t("gt")]
    runs, metrics = tmp_path / "runs", tmp_path / "eval" / SCENE
    hidden = tmp_path / "hidden"
    (tmp_path / "gt").rename(hidden)
    with recorder() as rec:
        trained = train.main(common + ["--prep", t("prep"), "--out", str(runs)])
    hidden.rename(tmp_path / "gt")
    assert not [p for p in rec.paths if str(hidden) in p or "/gt/" in p]
    assert any("/scenes/seed3/" in p for p in rec.paths) and any("/prep/seed3/" in p for p in rec.paths)
    assert list(trained) == ["gca", "nclaw", "gca@seed3", "nclaw@seed3"]  # seeds outermost
    assert {p.name for p in runs.iterdir() if p.is_dir()} == {"gca", "gca@seed3", "nclaw", "nclaw@seed3"}
    assert [json.loads((runs / n / "train.json").read_text())["seed"] for n in ("gca", "gca@seed3")] == [0, 3]
    # one launch velocity per seed, each fitted to its own observations
    velocities = [json.loads((runs / n).read_text()) for n in ("velocity.json", "velocity@seed3.json")]
    assert velocities[0]["v0"] != velocities[1]["v0"]
    # both laws rebuilt the same way (seed 0's init), so only their law.pt files can make them differ
    loaded = Settings(config.load(path=params, via_dvc=False))
    prior = SceneInputs(None, None, None, None, pipeline / "models/prior" / f"{FAMILY}.pt")
    flat = [torch.cat([t.detach().flatten() for t in load_learned_law(loaded, SCENE, get_method("gca"), prior,
                                                                      runs / n, 1000.0).trainable()])
            for n in ("gca", "gca@seed3")]
    assert not torch.equal(flat[0], flat[1])  # another seed, another LoRA init and draw, another trained law

    evaluated = evaluate.main(common + gt + ["--runs", str(runs), "--out", str(metrics)])
    assert list(evaluated) == ["gca", "nclaw", "gca@seed3", "nclaw@seed3"]
    assert {p.name for p in metrics.glob("*.json")} == {"gca.json", "gca@seed3.json", "nclaw.json", "nclaw@seed3.json"}
    assert (metrics / "gca@seed3" / "strip.png").is_file()
    read = load_runs(metrics.parent)
    assert [r["seed"] for r in read[SCENE, "gca"]] == [0, 3] and [r["seed"] for r in read[SCENE, "nclaw"]] == [0, 3]
    cell = reduce_seeds(read[SCENE, "gca"], "chamfer_mean")
    cds = [json.loads((metrics / f"{n}.json").read_text())["chamfer_mean"] for n in ("gca", "gca@seed3")]
    assert cell.n == 2 and cell.mean == pytest.approx(np.mean(cds)) and cell.std == pytest.approx(np.std(cds, ddof=1))

    assert list(evaluate.main(common + gt + ["--runs", str(runs), "--out", str(metrics), "--seeds", "3"])) == \
        ["gca@seed3", "nclaw@seed3"]
    with pytest.raises(ConfigError, match=r"seeds \[5\] are not in train.seeds \[0, 3\]"):
        evaluate.main(common + gt + ["--runs", str(runs), "--out", str(metrics), "--seeds", "5"])

