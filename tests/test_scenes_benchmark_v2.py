"""Benchmark v2 conditions in params.yaml (issue 21): frame interval variants, calibration scenes, version,
and the nuisance statistics computed on a generated scene."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from gca import config
from gca.report import paper
from gca.pipeline.settings import Settings
from gca.scenes import scene_video

ROOT = Path(__file__).resolve().parents[1]
NEUMA_DURATION = {"ball": 0.4, "duck": 0.4, "pawn": 0.2, "cat": 0.2, "fish": 0.2, "bottle": 0.2}


def _params(profile="paper", **video):
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["video"].update(video)
    return config.resolve(raw, profile)


def video_config(params):
    return Settings(params).video


def scene_config(params, name):
    return Settings(params).scene(name)


def test_paper_profile_supervises_at_100_fps_over_neumas_durations():
    params = _params()
    video = video_config(params)
    assert video.timing == "real_100fps" and video.fps == 100.0
    for name, duration in NEUMA_DURATION.items():
        scene = scene_config(params, name)
        v = scene_video(video, scene)
        interval = v.substeps * v.frame_every * scene.dt
        assert interval == pytest.approx(0.01, abs=1e-12), (name, interval)      # dt 5e-4 x 20, 4e-4 x 25
        assert v.n_frames * v.substeps * scene.dt == pytest.approx(duration), name
        assert scene_video(v, scene) == v                                         # idempotent


def test_named_variants_250_fps_and_30_fps_stress():
    params = _params(timing="legacy_250fps")
    v = scene_video(video_config(params), scene_config(params, "ball"))
    assert (v.n_frames, v.substeps, v.frame_every) == (200, 2, 4)               # benchmark 1.x, 250 fps at dt 5e-4
    params = _params(timing="stress_30fps")
    scene = scene_config(params, "ball")
    v = scene_video(video_config(params), scene)
    assert 1 / (v.substeps * scene.dt) == pytest.approx(30, rel=0.01)
    assert v.n_frames * v.substeps * scene.dt == pytest.approx(1.0, rel=0.02)
    with pytest.raises(config.ConfigError, match="video.timings"):
        video_config(_params(timing="nope"))


def test_ci_profile_keeps_the_interval_and_shrinks_the_duration():
    params = _params("ci")
    for name in ("ball", "fish", "duck"):
        scene = scene_config(params, name)
        v = scene_video(video_config(params), scene)
        assert v.n_frames == 4 and abs(v.substeps * scene.dt - 0.01) < 0.0011, (name, v.substeps * scene.dt)


def test_calibration_scenes_are_new_objects_and_materials_and_run_no_method():
    params = _params()
    calib = [s for s, c in params["scenes"].items() if c.get("calibration")]
    assert len(calib) >= 3
    table_scenes = [s for s in params["scenes"] if s not in calib]
    table_objects = {params["scenes"][s]["object"] for s in table_scenes}
    table_materials = {params["scenes"][s]["material"] for s in table_scenes}
    for name in calib:
        scene = scene_config(params, name)
        assert scene.calibration and scene.methods == ()
        assert scene.object not in table_objects and scene.material not in table_materials
        assert name not in paper.SCENES
        assert scene.duration_s > 0


def test_benchmark_version_is_set():
    params = _params()
    assert str(params["benchmark"]["version"]) == "2.0"


def test_nuisance_statistics_of_a_generated_scene(tmp_path):
    """The nuisance stage's numbers on a tiny scene: masks found (IoU), depth ranked (Spearman), lighting
    adds colour variance beyond an affine map."""
    from gca.eval.nuisance import depth_spearman, scene_nuisance
    from gca.render.shading import LightingConfig
    from gca.scenes import load_simulated_depth, load_view
    from gca.scenes.config import OrbitCamera, SceneConfig, VideoConfig
    from gca.scenes.ground_truth import generate
    from gca.scenes.preprocess import preprocess_view, write_prep
    from gca.scenes.store import load_plate
    from gca.sim.solver import SimConfig
    from gca.vision import VisionConfig
    from gca.vision.depth import SimulatedDepthConfig

    from synthetic import JELLY, tiny_body

    target = (0.5, 0.25, 0.5)
    scene = SceneConfig(object="tiny", material="gel", prior="jelly", dt=1e-3, v0=(0.2, -0.5, 0.0), duration_s=0.04,
                        camera=OrbitCamera(distance=1.0, target=target))
    video = VideoConfig(resolution=40, fps=100.0, background=(0.75, 0.75, 0.75))
    lighting = LightingConfig(shadows=True, shadow_resolution=16, floor_shadow=True, specular=0.2,
                              exposure_step_ev=0.05, exposure_max_ev=0.3, wb_step=0.01, wb_max=0.05)
    depth_cfg = SimulatedDepthConfig(edge_band_px=1.0, lowfreq_sigma_px=4.0, texture_copy=0.15, smooth_sigma_px=1.0,
                                     thin_px=3, thin_flatten=0.5, flicker_tilt_std=0.05)
    metrics = generate(tmp_path / "scene", tmp_path / "gt", tiny_body(n_side=4, spacing=0.05, base_y=0.15), "tiny",
                       scene, video, SimConfig(n_grid=16, dt=1e-3, bound=1, boundary="friction", friction=0.4),
                       JELLY, lighting, depth_cfg)
    assert 0.0 < metrics["lighting_unexplained_share"] < 1.0
    view = load_view(tmp_path / "scene", "train0")
    assert len(view.rgb) == 4                                                  # 0.04 s at 100 fps
    vision = VisionConfig()
    prep = preprocess_view(view, vision, simulated_depth=load_simulated_depth(tmp_path / "scene", 4),
                           plate=load_plate(tmp_path / "scene"))
    (tmp_path / "prep").mkdir()
    write_prep(tmp_path / "prep", prep)
    stats = scene_nuisance(tmp_path / "scene", tmp_path / "gt", tmp_path / "prep")
    assert 0.5 < stats["mask_iou_mean"] <= 1.0 and len(stats["mask_iou_per_frame"]) == 4
    assert 0.3 < stats["depth_spearman_mean"] < 1.0
    assert stats["lighting_unexplained_share"] == pytest.approx(metrics["lighting_unexplained_share"], abs=0.02)
    z = np.random.default_rng(0).uniform(1, 2, (2, 8, 8))
    np.testing.assert_allclose(depth_spearman(3 * z + 1, z, np.ones_like(z, bool)), 1.0)


def test_a_scene_made_at_another_dt_is_refused_not_resimulated_at_the_wrong_interval(tmp_path):
    """meta.json's substeps cover the frame interval at the dt the scene was made with; simulating them at another dt
    would compare every frame with the wrong instant (session 14: a dt/2 run on reused data did so silently)."""
    from gca.scenes.store import SceneDataError, frame_substeps

    meta = {"dt": 5e-4, "substeps": 20}
    assert frame_substeps(meta, 5e-4, tmp_path) == 20
    assert frame_substeps(meta, 5e-4 * (1 + 1e-9), tmp_path) == 20  # rounding of a YAML float is not a change
    with pytest.raises(SceneDataError, match=r"meta\.json: the video was made at dt=0\.0005 s \(20 MPM steps.*0\.5x"):
        frame_substeps(meta, 2.5e-4, tmp_path)
