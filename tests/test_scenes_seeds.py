"""Seeds cover the nuisance draws (issue 22 item 4): each training seed k observes its own lighting / exposure /
white-balance draw, its own depth-estimator noise and hence its own segmentation errors, rendered from the one
true trajectory; seed 0's data are the data made before seeds covered the nuisances, byte for byte."""

import json
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import yaml

from gca.render import shading
from gca.render.shading import LightingConfig
from gca.scenes import ground_truth, read_meta, truth
from gca.scenes.config import OrbitCamera, SceneConfig, VideoConfig
from gca.scenes.store import nuisance_seed, seed_dir
from gca.sim.solver import SimConfig
from gca.vision.depth import SimulatedDepthConfig

from synthetic import JELLY, tiny_body
from test_scenes_truth_isolation import recorder

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "stages"))

SEEDS = (0, 1, 2)
TARGET = (0.5, 0.25, 0.5)


def _generate(out: Path, seeds, monkeypatch=None, calls=None):
    body = tiny_body(n_side=4, spacing=0.05, base_y=0.15)
    cfg = SceneConfig(object="tiny", material="gel", prior="jelly", dt=1e-3, v0=(0.2, -0.5, 0.0), light_seed=11,
                      camera=OrbitCamera(distance=1.0, target=TARGET),
                      extra_train_cameras=(OrbitCamera(azimuth_deg=120, distance=1.0, target=TARGET),),
                      eval_cameras=(OrbitCamera(azimuth_deg=60, distance=1.0, target=TARGET),))
    video = VideoConfig(n_frames=8, substeps=2, frame_every=2, resolution=32, fps=0.0, timing="")
    sim = SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="friction", friction=0.4)
    return ground_truth.generate(out / "scene", out / "gt", body, "tiny", cfg, video, sim, JELLY, LightingConfig(),
                                 SimulatedDepthConfig(edge_band_px=1.0, lowfreq_sigma_px=4.0), seed=0, seeds=seeds)


def _files(root: Path, skip_seeds: bool = True) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
            and not (skip_seeds and p.relative_to(root).parts[0].startswith("seed"))}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """The tiny scene made with seeds [0] (as before) and with seeds [0, 1, 2], counting the simulations."""
    tmp = tmp_path_factory.mktemp("seeds")
    simulate, counted = ground_truth.simulate_scene, []

    def counting(*a, **k):
        counted.append(1)
        return simulate(*a, **k)

    ground_truth.simulate_scene = counting
    try:
        one = _generate(tmp / "one", (0,))
        three = _generate(tmp / "three", SEEDS)
    finally:
        ground_truth.simulate_scene = simulate
    return tmp, one, three, counted


def _params(tmp: Path, seeds) -> Path:
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    params["profile"] = "ci"
    params["scenes"]["tiny"] = dict(params["scenes"]["ball"])  # the stages check the scene is a key of scenes
    params["train"]["seeds"] = list(seeds)
    path = tmp / f"params_{len(seeds)}.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


def test_nuisance_seed_keeps_seed_zero_and_gives_other_seeds_their_own_streams():
    assert nuisance_seed(11, 0) == 11 and nuisance_seed(0, 0) == 0
    others = {nuisance_seed(11, k) for k in (1, 2, 3)} | {nuisance_seed(12, 1), nuisance_seed(0, 1)}
    assert len(others) == 5 and 11 not in others and 12 not in others
    assert nuisance_seed(11, 2) == nuisance_seed(11, 2)  # reproducible
    assert seed_dir("data/prep/ball", 0) == Path("data/prep/ball")
    assert seed_dir("data/prep/ball", 2) == Path("data/prep/ball/seed2")
    for bad in (-1, 1.0, True):
        with pytest.raises(ValueError, match="training seed"):
            seed_dir("x", bad)


def test_seed_zero_data_are_unchanged_by_the_other_seeds(scenes):
    """The top level (seed 0's draw) and the ground truth are the same bytes with seeds [0] and [0, 1, 2]."""
    tmp, one, three, _ = scenes
    for part in ("scene", "gt"):
        a, b = _files(tmp / "one" / part), _files(tmp / "three" / part)
        assert a.keys() == b.keys() and all(a[k] == b[k] for k in a), part
    assert not any(p.name.startswith("seed") for p in (tmp / "one/scene").iterdir())
    assert {k: v for k, v in three.items() if not k.startswith("seed")} == one


def test_seed_zero_draws_with_the_generator_seeds_it_always_had(tmp_path, monkeypatch):
    """Seed 0's lights come from ``light_seed`` and its estimator noise from the global seed, as before seeds
    covered the nuisances; seeds 1 and 2 use their own (negative control: they are not the base seeds)."""
    lights, depths = [], []
    sample, estimator = shading.sample_lights, ground_truth.SimulatedDepth

    def spy_lights(cfg, n, seed):
        lights.append(seed)
        return sample(cfg, n, seed=seed)

    class SpyDepth(estimator):
        def __init__(self, cfg, seed=0):
            depths.append(seed)
            super().__init__(cfg, seed)

    monkeypatch.setattr(shading, "sample_lights", spy_lights)
    monkeypatch.setattr(ground_truth, "SimulatedDepth", SpyDepth)
    _generate(tmp_path, SEEDS)
    assert lights == [11, nuisance_seed(11, 1), nuisance_seed(11, 2)]
    assert depths == [0, nuisance_seed(0, 1), nuisance_seed(0, 2)]


def test_other_seeds_draw_their_own_nuisances_of_one_true_trajectory(scenes):
    tmp, _, three, counted = scenes
    assert len(counted) == 2  # one simulation per generate call, whatever the number of seeds
    scene = tmp / "three/scene"
    meta0 = read_meta(scene)
    frames = {}
    for k in SEEDS:
        folder = seed_dir(scene, k)
        meta = read_meta(folder)
        # the same video of the same trajectory: frames, times, training cameras
        assert meta["video_frames"] == meta0["video_frames"] and meta["times"] == meta0["times"]
        assert meta["views"]["train"] == meta0["views"]["train"]
        assert json.loads((folder / "cameras.json").read_text())["train0"] == \
            json.loads((scene / "cameras.json").read_text())["train0"]
        frames[k] = {v: np.stack([np.asarray(iio.imread(p), np.float32)
                                  for p in sorted((folder / "views" / v / "rgb").glob("*.png"))])
                     for v in ("train0", "train1")}
        frames[k]["depth"] = np.load(folder / "views/train0/depth_sim.npy")
        frames[k]["plate"] = np.asarray(iio.imread(folder / "views/train0/plate.png"), np.float32)
    for k in (1, 2):
        meta = read_meta(seed_dir(scene, k))
        assert meta["views"]["eval"] == [] and meta["seed"] == k  # evaluation stays on seed 0's scene directory
        assert not (seed_dir(scene, k) / "views/eval0").exists()
        for key in ("train0", "train1", "depth", "plate"):
            assert not np.array_equal(frames[k][key], frames[0][key]), (k, key)
        assert frames[k]["train0"].shape == frames[0]["train0"].shape
        assert 0 <= three[f"seed{k}/lighting_unexplained_share"] <= 1
    assert not np.array_equal(frames[1]["train0"], frames[2]["train0"])
    # one trajectory: in every seed's frames the object is where the one true silhouette is (it departs from the
    # seed's own plate there), and the object's pixels are lit differently from seed to seed
    gt_alpha = truth.load_alpha(tmp / "three/gt", "train0") > 0.5
    for k in SEEDS:
        differs = np.abs(frames[k]["train0"] - frames[k]["plate"]).max(-1) > 20
        assert (differs & gt_alpha).sum() > 0.8 * gt_alpha.sum(), k



def test_preprocess_makes_each_seeds_observations_without_the_ground_truth(scenes, tmp_path):
    """data/prep/<scene> (seed 0) is the same with seeds [0] and [0, 1, 2]; seed k's masks and depth come from seed
    k's frames (segmentation errors differ), and nothing under the ground-truth directory is opened."""
    import preprocess

    tmp, _, _, _ = scenes
    hidden = tmp_path / "moved_gt"
    (tmp / "three/gt").rename(hidden)
    try:
        outs = {}
        for seeds in ((0,), SEEDS):
            params = _params(tmp_path, seeds)
            out = tmp_path / f"prep{len(seeds)}"
            with recorder() as rec:
                preprocess.main(["--scene", "tiny", "--scene-dir", str(tmp / "three/scene"), "--out", str(out),
                                 "--metrics", str(tmp_path / "prep.json"), "--params", str(params)])
            assert not [p for p in rec.paths if str(hidden) in p or "/gt/" in p], rec.paths
            outs[len(seeds)] = out
        metrics = json.loads((tmp_path / "prep.json").read_text())
        assert _files(outs[1]) == _files(outs[3])
        assert not (outs[1] / "seed1").exists()
        masks = {k: np.load(seed_dir(outs[3], k) / "masks.npy") for k in SEEDS}
        depth = {k: np.load(seed_dir(outs[3], k) / "depth.npy") for k in SEEDS}
        from gca.vision.segment import iou
        true = truth.load_alpha(hidden, "train0") > 0.5
        for k in (1, 2):
            assert not np.array_equal(masks[k], masks[0]) and not np.array_equal(depth[k], depth[0])
            assert iou(masks[k], true).mean() > 0.4  # each finds the object of the one trajectory
            assert metrics[f"seed{k}/n_frames"] == len(masks[k])
    finally:
        hidden.rename(tmp / "three/gt")


def test_each_seeds_runs_read_that_seeds_observations(scenes, tmp_path, monkeypatch):
    """The train stage estimates one launch velocity per seed from that seed's observations and trains each run
    on its seed's scene and prep directories (seed 0: the top level); evaluation reads the run's seed's velocity."""
    import train as train_stage

    import gca.pipeline.train as pipeline_train
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import SceneInputs, observed_inputs, velocity_path
    from gca.train.methods import get_method

    tmp, _, _, _ = scenes
    scene_dir, prep_dir = tmp / "three/scene", tmp_path / "prep"
    params = _params(tmp_path, SEEDS)
    estimated, trained, loaded = [], [], []

    def fake_estimate(settings, scene, inputs, out, device="cpu"):
        estimated.append((inputs.scene_dir, inputs.prep_dir))
        k = 0 if inputs.scene_dir == scene_dir else int(inputs.scene_dir.name[4:])
        out.write_text(json.dumps({"v0": [0.0, -float(k), 0.0], "w0": [0.0, 0.0, 0.0]}))
        return {"v0": [0.0, -float(k), 0.0], "w0": [0.0, 0.0, 0.0]}

    def fake_train(settings, scene, method, inputs, velocity, out_dir, run=None, device="cpu", seed=None):
        trained.append((method.name, seed, velocity[0][1]))
        with pytest.raises(RuntimeError, match="seen"):
            pipeline_train.train_method(settings, scene, method, inputs, velocity, out_dir, run, device, seed)
        out_dir.mkdir(parents=True, exist_ok=True)
        return {"status": "ok", "train_seconds": 0.0}

    def fake_load(settings, inputs, method, velocity, background, device="cpu", dt=None):
        loaded.append((inputs.scene_dir, inputs.prep_dir))
        raise RuntimeError("seen")

    monkeypatch.setattr(train_stage, "estimate_scene_velocity", fake_estimate)
    monkeypatch.setattr(train_stage, "train_method", fake_train)
    monkeypatch.setattr(pipeline_train, "load_train_data", fake_load)
    runs = tmp_path / "runs"
    train_stage.main(["--scene", "tiny", "--scene-dir", str(scene_dir), "--prep", str(prep_dir), "--particles",
                      str(tmp_path / "p.npz"), "--gaussians", str(tmp_path / "g.ply"), "--prior-dir", str(tmp_path),
                      "--out", str(runs), "--methods", "gca", "nclaw", "--params", str(params)])
    want = [(seed_dir(scene_dir, k), seed_dir(prep_dir, k)) for k in SEEDS]
    assert estimated == want  # one launch velocity per seed, each from its own observations
    assert loaded == [w for w in want for _ in range(2)]  # every run loads its seed's observations
    assert trained == [(m, k, -float(k)) for k in SEEDS for m in ("gca", "nclaw")]  # with its seed's velocity
    assert [json.loads(velocity_path(runs, k).read_text())["v0"][1] for k in SEEDS] == [0.0, -1.0, -2.0]
    assert velocity_path(runs, 0).name == "velocity.json" and velocity_path(runs, 2).name == "velocity@seed2.json"
    # a capture scene has one real video: every seed observes it
    from gca import config
    settings = Settings(config.load(path=params, via_dvc=False))
    inputs = SceneInputs(scene_dir, prep_dir, None, None, None)
    assert observed_inputs(settings, "tiny", inputs, 2).scene_dir == scene_dir / "seed2"
    assert observed_inputs(settings, "example_capture", inputs, 2) == inputs
    with pytest.raises(SystemExit, match="one seed's estimate"):
        train_stage.main(["--scene", "tiny", "--scene-dir", str(scene_dir), "--prep", str(prep_dir), "--particles",
                          str(tmp_path / "p.npz"), "--gaussians", str(tmp_path / "g.ply"), "--prior-dir", str(tmp_path),
                          "--out", str(runs), "--methods", "gca", "--velocity", str(velocity_path(runs, 0)),
                          "--params", str(params)])
    assert get_method("nclaw").trains is False


def test_nuisance_measures_every_seeds_own_draws(scenes, tmp_path):
    """The nuisance stage measures seed 0's observations (the headline numbers, as before) and each other seed's
    own draws under ``seeds``; with train.seeds [0] there is no ``seeds`` entry."""
    import nuisance
    import preprocess

    tmp, _, _, _ = scenes
    params = _params(tmp_path, SEEDS)
    prep = tmp_path / "prep"
    preprocess.main(["--scene", "tiny", "--scene-dir", str(tmp / "three/scene"), "--out", str(prep),
                     "--metrics", str(tmp_path / "prep.json"), "--params", str(params)])
    args = ["--scene", "tiny", "--scene-dir", str(tmp / "three/scene"), "--gt", str(tmp / "three/gt"),
            "--prep", str(prep)]
    three = nuisance.main(args + ["--out", str(tmp_path / "n3.json"), "--params", str(params)])
    one = nuisance.main(args + ["--out", str(tmp_path / "n1.json"), "--params", str(_params(tmp_path, (0,)))])
    assert "seeds" not in one and one["mask_iou_mean"] == three["mask_iou_mean"]
    assert sorted(three["seeds"]) == ["1", "2"]
    for k in ("1", "2"):
        m = three["seeds"][k]
        assert 0.0 < m["mask_iou_mean"] <= 1.0 and "image_mean_per_frame" not in m
        assert m["lighting_unexplained_share"] != three["lighting_unexplained_share"]  # its own lighting draw
