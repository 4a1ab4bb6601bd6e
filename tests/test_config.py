"""gca.config: profile resolution, typed sections, and the shipped params.yaml."""

import dataclasses
from pathlib import Path

import pytest
from gca import config


def test_resolve_picks_active_profile_everywhere():
    tree = {"a": {"paper": 100, "ci": 3}, "b": [{"paper": 1, "ci": 2}], "c": {"d": 5}}
    assert config.resolve(tree, "ci") == {"a": 3, "b": [2], "c": {"d": 5}}
    assert config.resolve(tree, "paper") == {"a": 100, "b": [1], "c": {"d": 5}}
    assert tree["a"] == {"paper": 100, "ci": 3}  # input untouched


def test_unknown_profile_is_refused(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("profile: laptop\n")
    with pytest.raises(config.ConfigError, match="laptop"):
        config.load(path=path, via_dvc=False)


def test_missing_and_malformed_files_name_the_file(tmp_path):
    with pytest.raises(config.ConfigError, match="nope.yaml"):
        config.load(path=tmp_path / "nope.yaml", via_dvc=False)
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(config.ConfigError, match="bad.yaml"):
        config.load(path=bad, via_dvc=False)


@dataclasses.dataclass(frozen=True)
class _Inner:
    dt: float = 1e-3  # s


@dataclasses.dataclass(frozen=True)
class _Outer:
    n: int
    inner: _Inner = _Inner()


def test_build_nested_and_refuses_unknown_keys():
    built = config.build(_Outer, {"n": 3, "inner": {"dt": 2e-3}}, "sim")
    assert built == _Outer(3, _Inner(2e-3))
    with pytest.raises(config.ConfigError, match="sim.inner: unknown keys \\['dx'\\]"):
        config.build(_Outer, {"n": 3, "inner": {"dx": 1}}, "sim")
    with pytest.raises(config.ConfigError, match="sim"):
        config.build(_Outer, {}, "sim")


def test_section_names_missing_key():
    with pytest.raises(config.ConfigError, match="'a.b.c'"):
        config.section({"a": {"b": {}}}, "a.b.c")


def test_flatten():
    assert config.flatten({"a": {"b": 1, "c": {"d": [1]}}, "e": 2}) == {"a.b": 1, "a.c.d": [1], "e": 2}


def test_shipped_params_resolve_in_both_profiles(repo_root):
    raw = config.read_yaml(repo_root / "params.yaml")
    assert raw["profile"] in config.PROFILES
    for profile in config.PROFILES:
        resolved = config.resolve(raw, profile)
        _assert_no_switch_left(resolved)


def _assert_no_switch_left(node):
    if isinstance(node, dict):
        assert set(node) != set(config.PROFILES), f"unresolved profile switch {node}"
        for v in node.values():
            _assert_no_switch_left(v)
    elif isinstance(node, list):
        for v in node:
            _assert_no_switch_left(v)


def _numeric_strings(node, path=""):
    """YAML 1.1 reads 1.0e5 (no exponent sign) as a string: find such values."""
    import re
    if isinstance(node, dict):
        return [p for k, v in node.items() for p in _numeric_strings(v, f"{path}.{k}")]
    if isinstance(node, list):
        return [p for i, v in enumerate(node) for p in _numeric_strings(v, f"{path}[{i}]")]
    return [f"{path}={node!r}"] if isinstance(node, str) and re.fullmatch(r"[-+]?[0-9.]+[eE][-+]?[0-9]+", node) else []


@pytest.mark.parametrize("profile", config.PROFILES)
def test_every_section_of_the_shipped_params_validates(repo_root, profile):
    from gca.align import CPRConfig, RDGAConfig
    from gca.assets.objects import ObjectConfig
    from gca.assets.particles import ParticleConfig
    from gca.eval.config import MetricsConfig
    from gca.pipeline.demo import demo_config
    from gca.laws.lora import LoRAConfig
    from gca.laws.neural import NeuralLawConfig
    from gca.laws.presets import material_from_preset
    from gca.render.shading import LightingConfig
    from gca.report import ReportConfig
    from gca.pipeline.settings import Settings
    from gca.sim.solver import SimConfig
    from gca.train.config import TrainConfig, VelocityConfig
    from gca.train.methods import get_method
    from gca.pipeline.prior import prior_configs
    from gca.vision import VisionConfig

    raw = config.read_yaml(repo_root / "params.yaml")
    assert _numeric_strings(raw) == []
    p = config.resolve(raw, profile)
    for cls, name in ((SimConfig, "sim"), (LightingConfig, "render.lighting"), (VisionConfig, "vision"),
                      (RDGAConfig, "align.rdga"), (CPRConfig, "align.cpr"), (NeuralLawConfig, "laws.neural"),
                      (LoRAConfig, "laws.lora"), (TrainConfig, "train"), (VelocityConfig, "velocity"),
                      (ParticleConfig, "particles"), (ReportConfig, "report"), (MetricsConfig, "eval.metrics")):
        config.build(cls, config.section(p, name), name)
    settings = Settings(p)
    settings.load_body  # noqa: B018  (bound: the body's rasterizer settings build)
    assert settings.backend in ("auto", "torch", "gsplat") and settings.raster is not None
    settings.video
    demo_config(settings)
    from gca.capture.objects import capture_config, is_capture
    for name in p["objects"]:
        if is_capture(p["objects"][name]):  # a user's scan (gca.capture.objects)
            capture_config(p["objects"][name], name)
            continue
        config.build(ObjectConfig, p["objects"][name], f"objects.{name}")
    for family in p["prior"]["families"]:
        prior_configs(settings, family)
        material_from_preset(p["prior"]["families"][family])
    for name in p["scenes"]:
        scene = settings.scene(name)
        assert scene.object in p["objects"] and scene.material in p["materials"] and scene.prior in p["prior"]["families"]
        for m in scene.methods:
            get_method(m)
        if scene.is_capture:  # no ground-truth law (materials.none); its video is checked by the ground_truth stage
            assert p["materials"][scene.material] == {}
            continue
        gt = material_from_preset(p["materials"][scene.material], dt=scene.dt, n_particles=100)
        prior = material_from_preset(p["prior"]["families"][scene.prior])
        sim = config.build(SimConfig, p["sim"], "sim")
        speed = max(abs(v) for v in scene.v0) * 3 ** 0.5 + 0.5 * max(abs(w) for w in scene.w0)  # |v| at launch
        for law in (gt, prior):  # both run on this dt: the ground truth and every method starting from the prior
            bound = sim.cfl * sim.dx / (law.wave_speed() + speed)
            assert scene.dt <= bound, f"scenes.{name}.dt={scene.dt} exceeds the CFL bound {bound:.3g} ({profile})"


def test_render_backend_auto_resolves_per_device():
    from gca.scenes.world import resolve_backend

    assert resolve_backend("auto", "cpu") == "torch"
    with pytest.warns(RuntimeWarning, match="needs CUDA"):
        assert resolve_backend("gsplat", "cpu") == "torch"
    with pytest.raises(ValueError, match="render.backend='opengl'"):
        resolve_backend("opengl", "cpu")


def test_settings_build_each_section_once_and_name_missing_keys(repo_root):
    """Settings (the pipeline's typed params) builds a section on first use and keeps it; a section the stage
    did not declare is a ConfigError naming the key; an unknown scene names the known ones."""
    from gca.pipeline.settings import Settings

    settings = Settings(config.resolve(config.read_yaml(repo_root / "params.yaml"), "ci"))
    assert settings.train is settings.train and settings.scene("duck") is settings.scene("duck")
    assert settings.train_for(None) is settings.train and settings.train_for(0).seed == 0
    with pytest.raises(config.ConfigError, match="unknown scene .nosuch."):
        settings.scene("nosuch")
    with pytest.raises(config.ConfigError, match="missing key 'align'"):
        Settings({"profile": "ci"}).rdga


def _own_prior_scenes(raw: dict) -> list[str]:
    """Scenes whose ground-truth material is exactly their prior family (same laws and parameters)."""
    families, materials = raw["prior"]["families"], raw["materials"]
    return [n for n, scene in raw["scenes"].items() if materials[scene["material"]] == families[scene["prior"]]]


def test_no_scene_is_its_own_prior(repo_root):
    """Table 1 compares adapting a prior against not adapting it: a scene whose ground truth is its prior
    family's law makes NCLaw exact and the comparison empty (duck and cat were, until session 7)."""
    raw = config.read_yaml(repo_root / "params.yaml")
    assert not _own_prior_scenes(raw), f"params.yaml: scenes whose ground truth is their prior: {_own_prior_scenes(raw)}"
    degenerate = {**raw, "materials": {**raw["materials"], "gel": dict(raw["prior"]["families"]["jelly"])}}
    assert "duck" in _own_prior_scenes(degenerate)  # the check catches the old params
