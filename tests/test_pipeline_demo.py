"""stages/demo.py end to end on a tiny pipeline layout, and the law loading with a missing law.

The layout is written by hand (no pipeline run): three tiny procedural objects, two tiny neural
priors (untrained, soft: stress_scale 100 Pa) and one trained law (the duck's gca LoRA adapter with
non-zero B); the cat's gca law is deliberately missing.
"""

import json
import sys
from pathlib import Path

import imageio.v3 as iio
import pytest
import torch
import warp as wp
import yaml

from gca.assets.objects import gaussians_from_mesh, make_object
from gca.assets.particles import ParticleConfig, convert, save_particles
from gca.assets.ply import write_ply
from gca.config import ConfigError, load
from gca.pipeline.demo import DemoInputs, load_demo_law
from gca.pipeline.settings import Settings
from gca.laws.checkpoint import save_prior
from gca.laws.lora import LoRAConfig
from gca.laws.neural import NeuralElasticity, NeuralLawConfig, NeuralPlasticity
from gca.train.law import build_law
from gca.pipeline.train import save_law
from gca.train.methods import get_method

wp.config.quiet = True
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "stages"))

DEMO = yaml.safe_load("""
new_shape: {law_scene: duck, method: gca, object: ball, v0: [0.5, -2.0, 0.0], w0: [0.0, 0.0, 2.0]}
interaction:
  a: {scene: duck, method: gca}
  b: {scene: cat, method: gca}
  v0_a: [2.0, 0.5, 0.0]
  v0_b: [-2.0, 0.5, 0.0]
  layout: side_by_side
  gap: 0.05
n_frames: {paper: 200, ci: 6}        # the proposed params.yaml section, with CI sizes shrunk further
steps_per_frame: {paper: 4, ci: 8}
resolution: {paper: 256, ci: 32}
render_every: {paper: 1, ci: 2}
camera: {azimuth_deg: 0.0, elevation_deg: 20.0, distance: 1.3, fov_deg: 40.0, target: [0.5, 0.25, 0.5]}
sweep_deg: 60.0
strip_frames: 3
frame_ms: 40.0
margin: 0.1
floor_gap: 0.15
missing_law: prior
captures: {}
""")


def _write_object(data: Path, name: str) -> None:
    mesh, colour = make_object(name, seed=1, size=0.3)
    cloud = gaussians_from_mesh(mesh, colour, n_surface=200, n_interior=20, seed=1)
    write_ply(data / "assets" / name / "gaussians.ply", cloud)
    save_particles(data / "particles" / f"{name}.npz", convert(cloud, ParticleConfig(spacing=0.06, floor_gap=0.05),
                                                                   1000.0, mesh=mesh))


def _write_prior(path: Path, family: str, seed: int) -> None:
    torch.manual_seed(seed)
    cfg = NeuralLawConfig(widths=(16, 16), stress_scale=100.0)
    save_prior(path, NeuralElasticity(cfg), NeuralPlasticity(cfg), family)


def _write_trained_law(prior: Path, run_dir: Path) -> None:
    """A gca LoRA adapter with non-zero B (so the trained law differs from the prior)."""
    law = build_law(get_method("gca"), prior, "jelly", 1000.0, LoRAConfig(4, 4.0), 1e-3, 1e-3, 1e-3)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in law.trainable():
            p.copy_(0.5 * torch.randn(p.shape, generator=g))
    run_dir.mkdir(parents=True)
    save_law(run_dir / "law.pt", law, "jelly", {"method": "gca"})


@pytest.fixture(scope="module")
def layout(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("demo_stage")
    for name in ("ball", "duck", "cat"):
        _write_object(tmp / "data", name)
    (tmp / "models/prior").mkdir(parents=True)
    _write_prior(tmp / "models/prior/jelly.pt", "jelly", 0)
    _write_prior(tmp / "models/prior/plasticine.pt", "plasticine", 1)
    _write_trained_law(tmp / "models/prior/jelly.pt", tmp / "runs/duck/gca")
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["profile"] = "ci"
    raw["scenes"] = {s: raw["scenes"][s] for s in ("duck", "cat")}
    raw["laws"]["lora"] = {"rank": 4, "alpha": 4.0}
    raw["demo"] = DEMO
    (tmp / "params.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
    return tmp


def _inputs(tmp: Path) -> DemoInputs:
    return DemoInputs(tmp / "runs", tmp / "data", tmp / "models/prior")


def test_trained_law_is_used_and_a_missing_one_follows_missing_law(layout):
    params = Settings(load("demo", layout / "params.yaml"))
    F = torch.eye(3) + 0.05 * torch.randn(5, 3, 3, generator=torch.Generator().manual_seed(0))
    trained, source = load_demo_law(params, "duck", "gca", _inputs(layout), 1000.0)
    assert source.endswith("runs/duck/gca/law.pt")
    prior, _ = load_demo_law(params, "duck", "nclaw", _inputs(layout), 1000.0)
    with torch.no_grad():
        assert (trained.stress(F) - prior.stress(F)).abs().max() > 1e-3, "law.pt changed the prior"
    with pytest.warns(RuntimeWarning, match="falling back to the scene's 'plasticine' prior"):
        fallback, source = load_demo_law(params, "cat", "gca", _inputs(layout), 1000.0, missing_law="prior")
    assert "fallback" in source
    with pytest.raises(FileNotFoundError, match="runs/cat/gca/law.pt"):
        load_demo_law(params, "cat", "gca", _inputs(layout), 1000.0, missing_law="error")


def test_demo_stage_writes_animations_and_metrics(layout):
    import demo

    d = lambda *p: str(layout.joinpath(*p))  # noqa: E731
    argv = ["--runs", d("runs"), "--data", d("data"), "--prior-dir", d("models/prior"), "--out", d("reports/demos"),
            "--metrics", d("metrics/demo.json"), "--params", d("params.yaml")]
    with pytest.warns(RuntimeWarning, match="runs/cat/gca/law.pt"):
        demo.main(argv)
    m = json.loads((layout / "metrics/demo.json").read_text())
    ns, it = m["new_shape"], m["interaction"]
    assert m["profile"] == "ci" and ns["status"] == "ok" and it["status"] == "ok"
    assert ns["frames"] == 6 and ns["finite"] and ns["object"] == "ball" and ns["law_source"].endswith("law.pt")
    assert it["a"]["law_source"].endswith("law.pt") and "fallback" in it["b"]["law_source"]
    assert (it["a"]["object"], it["b"]["object"]) == ("duck", "cat")
    assert it["n_particles"] == it["n_particles_a"] + it["n_particles_b"]
    for demo_metrics in (ns, it):
        frames = iio.imread(demo_metrics["gif"], index=None)
        assert frames.shape[:3] == (4, 32, 32) and demo_metrics["gif_frames"] == 4  # frames 0, 2, 4, 6
        assert Path(demo_metrics["strip_png"]).is_file()
        assert Path(demo_metrics["gif"]).parent.parent == layout / "reports/demos"


def test_proposed_section_builds_in_both_profiles():
    from gca.config import resolve
    from gca.pipeline.demo import demo_config

    paper = demo_config(Settings({"demo": resolve(DEMO, "paper")}))
    ci = demo_config(Settings({"demo": resolve(DEMO, "ci")}))
    assert (paper.n_frames, paper.resolution, paper.render_every) == (200, 256, 1)
    assert (ci.n_frames, ci.resolution, ci.render_every) == (6, 32, 2)
    assert paper.interaction.b.scene == "cat" and paper.interaction.v0_b == (-2.0, 0.5, 0.0)
    with pytest.raises(ConfigError, match="unknown keys"):
        demo_config(Settings({"demo": {**resolve(DEMO, "ci"), "fps": 25}}))
