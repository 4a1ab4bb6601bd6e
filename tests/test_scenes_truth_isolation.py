"""Ground truth isolated (issue 21, item 6): the ground_truth stage writes observations and ground-truth-only
data to two directories; preprocessing runs with the ground-truth directory absent and opens nothing in it;
the scene loader cannot return masks, true depth or the trajectory."""

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from gca.render.shading import LightingConfig
from gca.scenes import SceneDataError, load_trajectory, load_view, read_meta, truth
from gca.scenes.config import OrbitCamera, SceneConfig, VideoConfig
from gca.scenes.ground_truth import generate
from gca.sim.solver import SimConfig
from gca.vision.depth import SimulatedDepthConfig

from synthetic import JELLY, tiny_body

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "stages"))


class OpenRecorder:
    """Records every path opened (sys.audit 'open') while active; audit hooks cannot be removed, so it gates."""

    installed = None

    def __init__(self):
        self.paths, self.active = [], False
        if OpenRecorder.installed is None:
            OpenRecorder.installed = self
            sys.addaudithook(lambda event, args: OpenRecorder.installed._hook(event, args))

    def _hook(self, event, args):
        if self.active and event in ("open", "os.listdir", "os.scandir") and args and isinstance(args[0], (str, Path)):
            self.paths.append(str(args[0]))

    def __enter__(self):
        self.paths, self.active = [], True
        return self

    def __exit__(self, *exc):
        self.active = False


def recorder() -> OpenRecorder:
    return OpenRecorder.installed or OpenRecorder()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("iso")
    body = tiny_body(n_side=4, spacing=0.05, base_y=0.15)
    cfg = SceneConfig(object="tiny", material="gel", prior="jelly", dt=1e-3, v0=(0.2, -0.5, 0.0),
                      camera=OrbitCamera(distance=1.0, target=(0.5, 0.25, 0.5)),
                      extra_train_cameras=(OrbitCamera(azimuth_deg=120, distance=1.0, target=(0.5, 0.25, 0.5)),),
                      eval_cameras=(OrbitCamera(azimuth_deg=60, distance=1.0, target=(0.5, 0.25, 0.5)),))
    video = VideoConfig(n_frames=8, substeps=2, frame_every=2, resolution=32, fps=0.0, timing="")  # fixed frames
    sim = SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="friction", friction=0.4)
    metrics = generate(tmp / "scene", tmp / "gt", body, "tiny", cfg, video, sim, JELLY, LightingConfig(),
                       SimulatedDepthConfig(edge_band_px=1.0, lowfreq_sigma_px=4.0), seed=0)
    return tmp, metrics


def test_observations_and_ground_truth_are_written_apart(scene):
    tmp, _ = scene
    obs = {p.relative_to(tmp / "scene").as_posix() for p in (tmp / "scene").rglob("*") if p.is_file()}
    assert not any(name.endswith(("trajectory.npz", "alpha.npy", "law.json", "unlit.npy")) or "/mask/" in name
                   or name.endswith("views/train0/depth.npy") for name in obs), sorted(obs)
    assert "views/train0/depth_sim.npy" in obs and "meta.json" in obs
    T = len(read_meta(tmp / "scene")["video_frames"])
    assert truth.load_trajectory(tmp / "gt").shape[0] == T + 1
    for view in ("train0", "train1", "eval0"):
        alpha, depth = truth.load_alpha(tmp / "gt", view), truth.load_true_depth(tmp / "gt", view)
        assert alpha.shape == depth.shape and alpha.shape[0] == T
        assert np.all(depth[alpha > 0.5] > 0) and np.all(depth[alpha <= 0.5] == 0)
    assert truth.load_law(tmp / "gt")["preset"] == JELLY


def test_the_scene_loader_returns_no_ground_truth(scene):
    tmp, _ = scene
    view = load_view(tmp / "scene", "train0")
    assert view.mask is None and view.depth is None and view.rgb.ndim == 4
    with pytest.raises(truth.GroundTruthUnavailable, match="evaluation-only"):
        load_trajectory(tmp / "scene")
    with truth.bind(tmp / "scene", tmp / "gt"):
        assert load_trajectory(tmp / "scene").shape[-1] == 3
    with pytest.raises(truth.GroundTruthUnavailable):
        load_trajectory(tmp / "scene")  # unbound again after the block


def test_preprocess_runs_without_the_ground_truth_directory_and_never_opens_it(scene, tmp_path):
    import shutil

    import preprocess

    tmp, _ = scene
    hidden = tmp_path / "moved_gt"
    shutil.copytree(tmp / "gt", hidden)
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    params["profile"] = "ci"
    params["scenes"]["tiny"] = dict(params["scenes"]["ball"])  # the stages check the scene is a key of scenes
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    argv = ["--scene", "tiny", "--scene-dir", str(tmp / "scene"), "--out", str(tmp_path / "prep"),
            "--metrics", str(tmp_path / "prep.json"), "--params", str(tmp_path / "params.yaml")]
    with recorder() as rec:
        metrics = preprocess.main(argv)
    assert not [p for p in rec.paths if str(hidden) in p or "/gt/" in p or p.endswith(("trajectory.npz", "alpha.npy"))]
    assert any(p.endswith("depth_sim.npy") for p in rec.paths)  # the recorder sees np.load's opens
    masks = np.load(tmp_path / "prep" / "masks.npy")
    assert masks.shape[0] == metrics["n_frames"] and masks.any()
    # the masks come from the frames, so they are not the true silhouette, but they find the object
    from gca.vision.segment import iou
    score = iou(masks, truth.load_alpha(hidden, "train0") > 0.5)
    assert score.mean() > 0.4, score


def test_a_missing_simulated_depth_names_the_file(scene, tmp_path):
    import shutil

    from gca.scenes import load_simulated_depth

    tmp, _ = scene
    shutil.copytree(tmp / "scene", tmp_path / "scene")
    (tmp_path / "scene/views/train0/depth_sim.npy").unlink()
    with pytest.raises(SceneDataError, match="depth_sim.npy"):
        load_simulated_depth(tmp_path / "scene", 4)


def test_true_depth_is_alpha_normalised_at_the_silhouette(scene):
    """The stored true depth is z, not the compositing sum alpha * z: edge pixels lie within the object's
    depth range (benchmark 1.x stored the sum, so edge pixels read up to twice nearer)."""
    tmp, _ = scene
    alpha, depth = truth.load_alpha(tmp / "gt", "train0"), truth.load_true_depth(tmp / "gt", "train0")
    inside = alpha > 0.5
    solid = alpha > 0.98
    assert solid.any() and (inside & ~solid).any()
    lo, hi = depth[solid].min(), depth[solid].max()
    edge = depth[inside & ~solid]
    assert edge.min() > lo - 0.1 * (hi - lo) - 0.02, (edge.min(), lo, hi)


def test_the_nuisance_stage_reads_the_ground_truth_and_reports_per_frame(scene, tmp_path):
    import json

    import nuisance
    import preprocess

    tmp, _ = scene
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    params["profile"] = "ci"
    params["scenes"]["tiny"] = dict(params["scenes"]["ball"])  # the stages check the scene is a key of scenes
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    p = ["--params", str(tmp_path / "params.yaml")]
    preprocess.main(["--scene", "tiny", "--scene-dir", str(tmp / "scene"), "--out", str(tmp_path / "prep"),
                     "--metrics", str(tmp_path / "prep.json")] + p)
    out = tmp_path / "nuisance.json"
    nuisance.main(["--scene", "tiny", "--scene-dir", str(tmp / "scene"), "--gt", str(tmp / "gt"),
                   "--prep", str(tmp_path / "prep"), "--out", str(out)] + p)
    record = json.loads(out.read_text())
    T = len(read_meta(tmp / "scene")["video_frames"])
    assert record["benchmark_version"] == str(params["benchmark"]["version"])
    assert len(record["mask_iou_per_frame"]) == len(record["depth_spearman_per_frame"]) == T
    assert 0 <= record["mask_iou_min"] <= record["mask_iou_mean"] <= 1
    assert 0 <= record["lighting_unexplained_share"] <= 1
    with pytest.raises(truth.GroundTruthUnavailable, match="alpha.npy"):
        nuisance.main(["--scene", "tiny", "--scene-dir", str(tmp / "scene"), "--gt", str(tmp_path / "nowhere"),
                       "--prep", str(tmp_path / "prep"), "--out", str(out)] + p)
