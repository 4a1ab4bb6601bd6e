"""Smoke: the assets and particles stage mains end to end at a tiny size, into tmp_path."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages import assets as assets_stage  # noqa: E402
from stages import particles as particles_stage  # noqa: E402

from gca.assets import particles as pa  # noqa: E402
from gca.assets.ply import read_ply  # noqa: E402

PARAMS = {
    "profile": "ci",
    "objects": {"duck": {"size": 0.3, "seed": 1, "n_gaussians": {"paper": 100000, "ci": 1500},
                         "interior_fraction": 0.1, "sh_degree": 1, "opacity": 0.95, "density": 800.0}},
    "particles": {"opacity_threshold": 0.02, "spacing": {"paper": 0.008, "ci": 0.05}, "margin": 0.25,
                  "placement": "floor", "floor_gap": 0.05, "target_count": 0, "density_threshold": 0.1, "mahalanobis_chi2": 7.815,
                  "max_bound": 10, "unbound": "nearest", "n_candidates": 32},
}


def test_assets_then_particles(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.delenv("DVC_ROOT", raising=False)
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(PARAMS))
    out = tmp_path / "data/assets/duck"
    m = assets_stage.main(["--object", "duck", "--out", str(out), "--metrics", str(tmp_path / "assets.json"),
                           "--params", str(params)])
    assert {p.name for p in out.iterdir()} == {"gaussians.ply", "mesh.ply", "preview.png"}
    assert json.loads((tmp_path / "assets.json").read_text()) == m
    assert m["n_gaussians"] == 1500 and m["watertight"]
    assert read_ply(out / "gaussians.ply").sh_degree == 1
    npz, metrics = tmp_path / "data/particles/duck.npz", tmp_path / "metrics/particles/duck.json"
    particles_stage.main(["--object", "duck", "--assets", str(out), "--out", str(npz), "--metrics", str(metrics),
                          "--params", str(params)])
    p = pa.load_particles(npz)
    written = json.loads(metrics.read_text())
    assert written["n_particles"] == p.n > 50 and written["used_mesh"]
    np.testing.assert_allclose(written["mass_sim_kg"], 800.0 * p.vol.sum(), rtol=1e-5)
    # SI: the duck's real volume (its mesh's, 0.3 m across) and mass, not the unit cube's
    s = p.sim_from_world[0, 0]
    np.testing.assert_allclose(written["volume_m3"], p.vol.sum() / s**3, rtol=1e-5)
    np.testing.assert_allclose(written["mass_kg"], 800.0 * written["volume_m3"], rtol=1e-5)
    assert written["mass_kg"] < written["mass_sim_kg"] and written["mesh"]["used"]
    assert 0 < written["share_bound_within_mahalanobis"] <= 1
    # the object's bottom rests at floor_gap; the lowest lattice point is within one spacing above it
    assert 0.05 <= p.x[:, 1].min() <= 0.05 + written["spacing_sim_m"]
    assert p.x.min() > 0 and p.x.max() < 1


def test_particles_refuses_a_huge_lattice_in_one_line_naming_the_object(tmp_path, monkeypatch, capsys):
    """A lattice over MAX_LATTICE_CELLS (here: target_count 1e9) is refused before it is allocated: exit 2 and one
    line naming the object, not a process that grows until the OOM killer ends it (particles@dragon, 123 GB)."""
    from gca.assets import objects
    from gca.assets.ply import write_ply
    from gca.pipeline import cli

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.delenv("DVC_ROOT", raising=False)
    huge = {**PARAMS, "particles": {**PARAMS["particles"], "target_count": 10**9}}
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(huge))
    out = tmp_path / "data/assets/duck"
    out.mkdir(parents=True)
    mesh, _, cloud = objects.scan_object("duck", objects.ObjectConfig(size=0.3, seed=1, n_gaussians=300, sh_degree=0))
    write_ply(out / "gaussians.ply", cloud)
    mesh.export(out / "mesh.ply")
    npz = tmp_path / "data/particles/duck.npz"
    rc = cli.run(particles_stage.main, ["--object", "duck", "--assets", str(out), "--out", str(npz), "--metrics",
                                        str(tmp_path / "particles.json"), "--params", str(params)], name="particles")
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert rc == 2 and not npz.exists()
    assert len(errors) == 1 and errors[0].startswith("particles: error: particles@duck: ") and "a lattice of" in errors[0]
