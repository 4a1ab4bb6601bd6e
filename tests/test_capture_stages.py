"""The assets and particles stages on a capture object: a scan of any name, z up, in centimetres, with
floaters and a Gaussian at 1e30 m, and an open mesh beside it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages import assets as assets_stage  # noqa: E402
from stages import particles as particles_stage  # noqa: E402

from gca.assets import particles as pa  # noqa: E402
from gca.assets.ply import read_ply, write_ply  # noqa: E402
from gca.assets.testscan import torus_scan, torus_volume  # noqa: E402
from gca.capture.objects import read_object_from_scan  # noqa: E402

R_CM, r_CM = 5.0, 2.0  # torus radii in the scan's units [cm]


def _params(tmp_path, scan_entry):
    return {"profile": "ci", "objects": {"donut": scan_entry},
            "particles": {"opacity_threshold": 0.02, "spacing": {"paper": 0.008, "ci": 0.012}, "target_count": 4000,
                          "margin": 0.25, "placement": "floor", "floor_gap": 0.05, "density_threshold": 0.1,
                          "mahalanobis_chi2": 7.815, "max_bound": 10, "unbound": "nearest", "n_candidates": 32}}


def _run(tmp_path, entry, stage="assets"):
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(_params(tmp_path, entry)))
    out = tmp_path / "data/assets/donut"
    m = assets_stage.main(["--object", "donut", "--out", str(out), "--metrics", str(tmp_path / "assets.json"),
                           "--params", str(params)])
    return params, out, m


@pytest.fixture
def env(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.delenv("DVC_ROOT", raising=False)
    monkeypatch.chdir(tmp_path)
    cloud = torus_scan(n=6000, R=R_CM, r=r_CM, up="z", n_floaters=22, floater_box=12, far_outlier=1e30, sh_degree=1)
    write_ply(tmp_path / "my scan.ply", cloud)
    return tmp_path


def test_capture_object_through_assets_and_particles(env):
    entry = {"scan": "my scan.ply", "density": 1100.0,
             "scan_options": {"up": "+z", "metres_per_unit": 0.01}}
    params, out, m = _run(env, entry)
    assert m["removed"] == {"far": 1, "statistical": 22, "component": 0} and m["n_gaussians"] == 6000
    assert {p.name for p in out.iterdir()} == {"gaussians.ply", "object_from_scan.json", "preview.png"}
    cloud = read_ply(out / "gaussians.ply")
    ext = np.ptp(cloud.means, axis=0)
    assert abs(ext.max() - 0.14) < 2e-3 and ext[1] < 0.05  # metres, lying flat (y thin)
    assert cloud.sh_degree == 1
    np.testing.assert_allclose(np.linalg.det(read_object_from_scan(out)[:3, :3]), 0.01**3, rtol=1e-6)
    npz, metrics = env / "p.npz", env / "p.json"
    particles_stage.main(["--object", "donut", "--assets", str(out), "--out", str(npz), "--metrics", str(metrics),
                          "--params", str(params)])
    written = json.loads(metrics.read_text())
    true_volume = torus_volume(0.05, 0.02)  # [m^3]
    assert abs(written["volume_m3"] / true_volume - 1) < 0.1
    assert abs(written["mass_kg"] / (1100.0 * true_volume) - 1) < 0.1  # ~0.43 kg, SI
    assert 0 <= written["share_bound_within_mahalanobis"] < 1 and written["n_fallback_nearest"] > 0
    p = pa.load_particles(npz)
    assert np.ptp(p.x[:, 1]) < 0.5 * np.ptp(p.x[:, 0])  # simulated lying flat


def test_capture_with_open_mesh_reports_and_ignores_it(env):
    half = trimesh.creation.torus(R_CM, r_CM)
    half = trimesh.Trimesh(half.vertices, half.faces[half.triangles_center[:, 0] > 0])
    half.export(env / "donut_mesh.obj")
    _, out, m = _run(env, {"scan": "my scan.ply", "mesh": "donut_mesh.obj",
                           "scan_options": {"up": "+z", "metres_per_unit": 0.01}})
    assert m["mesh"]["watertight"] is False and m["mesh"]["used"] is False and "ignored" in m["mesh"]["reason"]
    assert not (out / "mesh.ply").exists()


@pytest.mark.parametrize("entry, message", [
    ({"scan": "missing.ply"}, r"missing.ply: scan file not found \(objects.donut.scan\)"),
    ({"scan": "my scan.ply", "scan_options": {"up": "z"}}, r"up='z'"),
    ({"scan": "my scan.ply", "scan_options": {"crop": [[9, 9, 9], [10, 10, 10]]}}, r"my scan.ply: 0 of 6023 Gaussians left"),
    ({"scan": "my scan.ply", "density": -1.0}, r"density: must be > 0"),
])
def test_bad_capture_input_is_one_line_and_writes_nothing(env, entry, message, capsys):
    with pytest.raises(SystemExit) as exc:
        _run(env, entry)
    text = str(exc.value.code)
    assert text.startswith("assets@donut: ") and "\n" not in text
    import re
    assert re.search(message, text), text
    assert not (env / "data/assets/donut").exists() and not (env / "assets.json").exists()
