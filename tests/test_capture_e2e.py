"""The README's "Your own object" path end to end on the worked example, at the CI profile: the example capture
is written (``python -m gca.capture.example``), then every stage command dvc.yaml gives the capture scene runs in
DVC's order (assets, particles, prior, ground_truth, preprocess, nuisance, train, evaluate, demo_capture, report),
each taken from dvc.yaml itself (``gca.pipeline.grid.expand``) and run in this process (one import of torch and
warp, not ten). Asserts the held-out metrics, CPR's sentence, the new-scene demo and the report page. No stage can
read ground truth: the example's ``truth.json`` (how it was made) is moved out of the repository before the stages
run, and ``data/gt`` (a capture has none: a README says so) is moved away while preprocess and train run. (The
open-recording audit hook of the synthetic smoke test is not used: it slowed the velocity fit eightfold.)

The synthetic ``demo`` stage (ball and cat's laws) is not part of a capture's path; the params are the shipped
ones cut to the capture (as tests/test_dvc_pipeline.py cuts them to two scenes).
"""

from __future__ import annotations

import importlib
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "stages"))

from gca.pipeline.grid import expand, grid_params, link  # noqa: E402

SCENE = "example_capture"
TRAINING_SIDE = ("preprocess", "train")  # stages that must never open ground truth


def _order(jobs: dict) -> list[str]:
    """Job names in dependency order (``Job.after``), ties by name."""
    done, order = set(), []
    while len(order) < len(jobs):
        ready = sorted(n for n, j in jobs.items() if n not in done and j.after <= done)
        assert ready, f"dvc.yaml: a cycle among {sorted(set(jobs) - done)}"
        order.append(ready[0])
        done.add(ready[0])
    return order


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("capture_e2e")
    old_cwd, old_uri = Path.cwd(), os.environ.get("MLFLOW_TRACKING_URI")
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{tmp / 'mlflow.db'}"
    os.chdir(tmp)  # stage commands use dvc.yaml's relative paths, params.yaml's capture paths too
    try:
        t0 = time.perf_counter()
        from gca.capture import example
        example.main(["--out", "captures/example"])  # README: regenerate the worked example
        truth = tmp_path_factory.mktemp("outside") / "truth.json"
        (tmp / "captures/example/truth.json").rename(truth)  # no stage can read how the example was made
        params = grid_params("ci", [SCENE], None, [])
        (tmp / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        jobs = expand(yaml.safe_load((ROOT / "dvc.yaml").read_text()), params)
        jobs = link({n: j for n, j in jobs.items() if n != "demo"})
        seconds, gt_files = {}, {}
        for name in _order(jobs):
            argv = shlex.split(jobs[name].cmd)
            assert argv[0] == "python" and argv[1].startswith("stages/"), jobs[name].cmd
            module = importlib.import_module(Path(argv[1]).stem)
            hide = name.split("@")[0] in TRAINING_SIDE
            if hide:
                (tmp / "data/gt").rename(tmp / "hidden_gt")
            start = time.perf_counter()
            try:
                module.main(argv[2:])
            finally:
                if hide:
                    (tmp / "hidden_gt").rename(tmp / "data/gt")
            seconds[name] = time.perf_counter() - start
            if name.startswith("ground_truth@"):
                gt_files = sorted(p.name for p in (tmp / "data/gt" / SCENE).rglob("*") if p.is_file())
        seconds["total"] = time.perf_counter() - t0
        (tmp / "e2e.json").write_text(json.dumps({"seconds": seconds}, indent=1))
        return tmp, seconds, gt_files
    finally:
        os.chdir(old_cwd)
        if old_uri is None:
            os.environ.pop("MLFLOW_TRACKING_URI", None)
        else:
            os.environ["MLFLOW_TRACKING_URI"] = old_uri


def test_every_stage_of_the_capture_path_ran_in_dvc_order(capture):
    _, seconds, _ = capture
    names = [n for n in seconds if n != "total"]
    assert {f"{s}@{SCENE}" for s in ("assets", "particles", "ground_truth", "preprocess", "nuisance", "train",
                                     "evaluate", "demo_capture")} | {"prior@jelly", "report"} == set(names)
    assert names.index(f"train@{SCENE}") < names.index(f"evaluate@{SCENE}") < names.index("report")
    assert names.index(f"demo_capture@{SCENE}") < names.index("report")
    print("stage seconds:", {k: round(v, 1) for k, v in seconds.items()})


def test_a_capture_has_no_ground_truth_and_none_was_needed(capture):
    tmp, _, gt_files = capture
    assert gt_files == ["README.md"]  # ground_truth imported the video; it wrote no trajectory, depth or law
    assert not (tmp / "captures/example/truth.json").exists()  # moved out before any stage ran
    assert "no ground truth" in json.loads((tmp / "metrics/nuisance" / f"{SCENE}.json").read_text())["skipped"]


def test_heldout_metrics_are_finite_and_sane(capture):
    tmp, _, _ = capture
    m = json.loads((tmp / "metrics/eval" / SCENE / "gca.json").read_text())
    assert m["status"] == "ok" and m["kind"] == "capture" and m["profile"] == "ci"
    assert m["n_train_frames"] == 8 and m["n_heldout_frames"] == 2
    assert 10.0 < m["psnr_heldout"] < 60.0
    assert 0.2 < m["ssim_heldout"] <= 1.0
    assert 0.3 < m["mask_iou_heldout"] <= 1.0
    assert 0.0 <= m["silhouette_cd_px_heldout"] < 10.0  # [px] on a 64 x 48 video
    law = m["nearest_law"]
    assert law["sentence"].startswith("behaves like ") and "E = " in law["sentence"]
    assert math.isfinite(law["E_pa"]) and 1e3 < law["E_pa"] < 1e7 and 0.0 <= law["nu"] < 0.5
    for kind in ("e", "p"):
        assert abs(sum(w for k, w in law["weights"].items() if k.startswith(kind + "/")) - 1) < 1e-6
    frames = iio.imread(tmp / m["resim_gif"], index=None)
    assert frames.shape[:3] == (10, 48, 128)  # input | re-simulation, every frame


def test_new_scene_demo_threw_the_learned_law_elsewhere(capture):
    tmp, _, _ = capture
    d = json.loads((tmp / "metrics/demo_capture" / f"{SCENE}.json").read_text())
    assert d["status"] == "ok" and d["finite"] and d["law_source"].endswith(f"runs/{SCENE}/gca/law.pt")
    video_v0 = json.loads((tmp / "runs" / SCENE / "velocity.json").read_text())["v0"]
    assert d["lift_m"] > 0 and max(abs(a - b) for a, b in zip(d["v0"], video_v0)) > 0.5  # not the video's throw
    assert d["com_drop_m"] > d["lift_m"] and 0.0 < d["max_strain"] < 1.0  # it fell to the floor and deformed
    frames = iio.imread(tmp / d["gif"], index=None)
    assert frames.shape[1:3] == (48, 64) and len(frames) == d["gif_frames"] >= 2
    assert (frames[0] != frames[-1]).any()  # it moved


def test_report_page_has_the_metrics_the_law_and_both_videos(capture):
    tmp, _, _ = capture
    reports = tmp / "reports/ci"
    page = (reports / "captures" / f"{SCENE}.md").read_text()
    m = json.loads((tmp / "metrics/eval" / SCENE / "gca.json").read_text())
    for key in ("psnr_heldout", "ssim_heldout", "mask_iou_heldout", "silhouette_cd_px_heldout"):
        assert f"{m[key]:.3g}" in page, key
    assert "silhouette CD [px]" in page and "the learned law behaves like" in page
    assert m["nearest_law"]["sentence"] in page
    for name in (f"{SCENE}_gca_resim.gif", f"{SCENE}_demo.gif"):
        assert f"]({name})" in page and (reports / "captures" / name).is_file()
    assert "## New-scene demo" in page
    index = (reports / "README.md").read_text()
    assert f"(captures/{SCENE}.md)" in index
