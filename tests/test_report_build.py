"""Tables, figures and the report stage built from a tiny synthetic metrics folder.

Expected cells are computed by hand from the records written by ``_metrics_dir`` below.
"""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from gca.report import ReportConfig, build_reports
from gca.report import figures, tables
from gca.report.runs import load_runs

CD_DEF = "mean of the two one-sided mean squared nearest-neighbour distances, sim units x 1e3"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _record(scene, method, status="ok", seed=0, **values):
    base = {"scene": scene, "material": "m", "object": scene, "method": method, "seed": seed, "profile": "ci",
            "device": "cpu", "status": status, "chamfer_definition": CD_DEF, "lpips_train": None,
            "lpips_reason": "no local LPIPS weights"}
    return {**base, **values}


def _write(root: Path, record: dict, name: str | None = None) -> None:
    path = root / record["scene"] / (name or f"{record['method']}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))


def _metrics_dir(root: Path) -> Path:
    """nclaw: CD 1..6 on the six synthetic scenes; gca: ball 0.5, duck seeds 0.4/0.6, pawn diverged;
    neuma: ball failed, duck 1.0 with law errors; plus a strip and curves for the figures."""
    metrics = root / "metrics"
    for k, scene in enumerate(("ball", "duck", "pawn", "cat", "fish", "bottle"), start=1):
        _write(metrics, _record(scene, "nclaw", chamfer_mean=float(k), chamfer_per_frame=[0.0, k / 2, float(k)],
                                train_seconds=60.0 * k, rollout_seconds=1.0, peak_memory_gib=2.0,
                                psnr_train=20.0 + k, psnr_heldout=18.0 + k, ssim_train=0.9, ssim_heldout=0.8))
    curves = {"uniaxial": {"stretch": [0.8, 1.0, 1.2], "ours": [-1.0, 0.0, 1.1], "reference": [-1.0, 0.0, 1.0]},
              "shear": {"strain": [0.0, 0.2], "ours": [0.0, 0.25], "reference": [0.0, 0.2]}}  # evaluate's key
    _write(metrics, _record("ball", "gca", chamfer_mean=0.5, chamfer_per_frame=[0.0, 0.5], train_seconds=120.0,
                            peak_memory_gib=1.0, rollout_seconds=2.0, strip_png="runs/ball/gca/strip.png"))
    _write(metrics, _record("duck", "gca", chamfer_mean=0.4, law_error_uniaxial_pct=10.0,
                            law_error_shear_pct=4.0, law_curves=curves))
    _write(metrics, _record("duck", "gca", seed=1, chamfer_mean=0.6, law_error_uniaxial_pct=12.0,
                            law_error_shear_pct=6.0), "gca@seed1.json")
    _write(metrics, _record("pawn", "gca", status="diverged", chamfer_mean=55.0, chamfer_per_frame=[0.1, None]))
    _write(metrics, _record("ball", "neuma", status="failed", chamfer_mean=None))
    _write(metrics, _record("ball", "neuma_multiview", chamfer_mean=0.9, strip_png="runs/ball/missing.png"))
    _write(metrics, _record("duck", "neuma", chamfer_mean=1.0, law_error_uniaxial_pct=50.0,
                            law_error_shear_pct=None))
    (metrics / "ball" / "ground_truth.json").write_text(json.dumps({"frames": 3}))  # another stage's file
    strip = root / "runs" / "ball" / "gca" / "strip.png"
    strip.parent.mkdir(parents=True)
    import matplotlib.image as mpimg
    mpimg.imsave(strip, np.linspace(0, 1, 8 * 32 * 3).reshape(8, 32, 3))
    return metrics


@pytest.fixture
def metrics(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # strip_png paths are relative to the repository root
    return _metrics_dir(tmp_path)


def _row(df: pd.DataFrame, label: str, source: str) -> dict:
    key = "Method" if "Method" in df.columns else "Configuration"
    rows = df[(df[key] == label) & (df["Source"] == source)]
    assert len(rows) == 1, (label, source, df)
    return rows.iloc[0].to_dict()


def test_table1_cells(metrics):
    df = tables.table1_synthetic_cd(load_runs(metrics)).df
    ours, nclaw, neuma = (_row(df, m, "measured") for m in ("Ours", "NCLaw", "NeuMA"))
    assert ours["Ball (Elastomer)"] == "0.50000 (1 of 2 seeds)"  # measured CDs [m] with 5 decimals, the paper's
    # with 3; one seed beside the duck's two: said (session 27)
    assert ours["Duck (Gel)"] == "0.50000 ± 0.14142"  # mean and sample std of 0.4, 0.6
    assert ours["Pawn (Rubber)"] == "55.00000 (diverged) (1 of 2 seeds)"  # the measured CD, its status beside it
    assert ours["Cat (Plasticine)"] == "—"
    assert ours["Average"] == "18.66667 (diverged) (3/6 scenes)"  # (0.5 + 0.5 + 55) / 3
    assert nclaw["Average"] == "3.50000"  # mean of 1..6
    assert neuma["Ball (Elastomer)"] == "failed"
    assert neuma["Average"] == "1.00000 (1/6 scenes)"
    assert _row(df, "NeuMA", "paper")["Duck (Gel)"] == "1.863"
    assert _row(df, "Ours", "paper")["Average"] == "0.496"
    assert list(df["Source"]) == ["measured", "paper"] * 3


def test_other_tables_cells(metrics):
    runs = load_runs(metrics)
    t3 = tables.table3_ablation_cd(runs).df
    assert _row(t3, "w/o Global Align.", "paper")["Ball (Elastomer)"] == "> 100 (Diverged)"
    assert _row(t3, "w/o Global Align.", "measured")["Ball (Elastomer)"] == "—"
    assert _row(t3, "Ours (Full)", "paper")["Note"] == "Best performance"
    t4 = tables.table4_efficiency(runs).df
    lora = _row(t4, "Ours (LoRA)", "measured")
    # train: ball 120 s only (duck has none, pawn diverged has none) -> 2.0 min; CD average is diverged
    cells = (lora["Train (min)"], lora["Mem. (GB)"], lora["CD"], lora["Scenes"])
    assert cells == ("2.00", "1.00", "18.66667 (diverged) (3/6 scenes)", "3/6")  # >= 3 significant digits
    assert _row(t4, "NeuMA", "paper")["Mem. (GB)"] == "28.9"
    assert _row(t4, "NeuMA", "measured")["Mem. (GB)"] == "n/a"  # ball failed, duck reported no memory
    t5 = tables.table5_explicit(runs).df
    assert _row(t5, "PAC-NeRF + Depth (raw L1)", "paper")["Ball (Elastomer)"] == "> 100 (Diverged)"
    assert _row(t5, "PAC-NeRF + Depth (aligned L1)", "paper")["Ball (Elastomer)"] == "--"  # not in the paper
    assert _row(t5, "PAC-NeRF + Depth (aligned L1)", "paper")["Status"] == "not in paper"
    assert _row(t5, "PAC-NeRF + Depth (raw L1)", "measured")["Status"] == "not run"
    assert t5[t5["Supervision"] == "Multi-view"].iloc[2]["Ball (Elastomer)"] == "0.900"
    t6 = tables.table6_ood(runs).df
    assert _row(t6, "Ours (Target Removed)", "paper")["Composite (undefined)"] == "--"
    law = tables.table_law_level(runs).df
    assert _row(law, "Ours", "measured")["Avg. (%)"] == "8.00 ± 1.41"  # seed averages 7.0 and 9.0: std sqrt(2)
    assert _row(law, "NeuMA", "measured")["Sh. (%)"] == "n/a"


def test_markdown_header_states_provenance(metrics, tmp_path):
    _write(metrics, _record("fish", "gca", chamfer_mean=0.1, profile="paper", device="NVIDIA H100 80GB HBM3"))
    written = build_reports(metrics, tmp_path / "reports", ReportConfig(dpi=40))
    text = (tmp_path / "reports" / "table1_synthetic_cd.md").read_text()
    assert "profile `mixed (ci, paper)`" in text and "mixed (NVIDIA H100 80GB HBM3, cpu)" in text
    assert CD_DEF in text and "not comparable to the paper" in text
    law_md = (tmp_path / "reports" / "table_law_level.md").read_text()
    assert "profile `ci`, device `cpu`, 4 metrics files" in law_md  # nclaw, neuma, gca x2
    assert all(p.exists() and p.stat().st_size > 0 for p in written)


def test_reports_are_byte_identical_indexed_and_figures_drawn(metrics, tmp_path):
    cfg = ReportConfig(dpi=50)
    first = build_reports(metrics, tmp_path / "a", cfg)
    second = build_reports(metrics, tmp_path / "b", cfg)
    assert [p.relative_to(tmp_path / "a") for p in first] == [p.relative_to(tmp_path / "b") for p in second]
    for a, b in zip(first, second):
        assert a.read_bytes() == b.read_bytes(), a.name  # tables, README and PNGs alike
    index = (tmp_path / "a" / "README.md").read_text()
    for path in first[:-1]:
        assert f"`{path.relative_to(tmp_path / 'a').as_posix()}`" in index
    names = {p.name for p in first}
    assert {"table1_synthetic_cd.md", "table6_ood.csv", "table_law_level.md"} <= names
    assert pd.read_csv(tmp_path / "a" / "table1_synthetic_cd.csv").shape == (6, 9)
    pngs = {p.name: p for p in first if p.suffix == ".png"}
    expected = {"cd_time_ball.png", "cd_time_pawn.png", "render_metrics.png", "law_curves.png", "strip_ball.png"}
    assert expected <= set(pngs)
    assert "strip_duck.png" not in pngs  # no strip_png on duck
    assert all(p.read_bytes()[:8] == PNG_SIGNATURE and p.stat().st_size > 1000 for p in pngs.values())
    import matplotlib.image as mpimg
    height = mpimg.imread(pngs["strip_ball.png"]).shape[0]
    assert height == round((1.4 * 1 + 0.3) * 50)  # one row: neuma_multiview's strip file is missing


def test_figures_return_none_without_data(metrics, tmp_path):
    runs = {k: v for k, v in load_runs(metrics).items() if k[1] == "neuma"}  # no curves, strips or frames
    out = tmp_path / "figs"
    assert figures.plot_cd_over_time(runs, "duck", out / "cd.png", 50) is None
    assert figures.plot_law_curves(runs, out / "law.png", 50) is None
    assert figures.plot_render_metrics(runs, out / "render.png", 50) is None
    assert figures.compose_strips(runs, "ball", out / "strip.png", 50, [tmp_path]) is None
    assert not out.exists()


def test_per_frame_mean_over_seeds_keeps_gaps():
    records = [{"status": "ok", "chamfer_per_frame": [1.0, 2.0, None, 4.0]},
               {"status": "diverged", "chamfer_per_frame": [3.0, None, None]},
               {"status": "failed", "chamfer_per_frame": [100.0, 100.0, 100.0]}]
    curve = figures.per_frame_mean(records)
    np.testing.assert_array_equal(curve[:2], [2.0, 2.0])  # (1+3)/2, then 2 alone; truncated to 3 frames
    assert curve.shape == (3,) and np.isnan(curve[2])


def test_bad_metrics_files_are_named(tmp_path):
    metrics = tmp_path / "metrics"
    _write(metrics, _record("ball", "gca", chamfer_mean=0.5), "nclaw.json")
    with pytest.raises(ValueError, match=r"nclaw\.json.*do not match its path"):
        load_runs(metrics)
    (metrics / "ball" / "nclaw.json").unlink()
    _write(metrics, _record("ball", "gca", status="exploded"))
    with pytest.raises(ValueError, match=r"gca\.json: status='exploded'"):
        load_runs(metrics)
    with pytest.raises(FileNotFoundError, match="metrics folder not found"):
        load_runs(tmp_path / "nowhere")


def test_duplicate_seed_is_ignored_with_a_warning(metrics):
    _write(metrics, _record("ball", "gca", chamfer_mean=9.0), "gca@seed0.json")
    with pytest.warns(RuntimeWarning, match="seed 0 of ball/gca already read"):
        runs = load_runs(metrics)
    assert [r["chamfer_mean"] for r in runs["ball", "gca"]] == [0.5]


def test_the_file_name_says_the_seed(metrics):
    """``gca.json`` is seed 0 whatever its record says (records before ``train.seeds`` stored the global data
    seed): a stale record cannot take the place of ``gca@seed1.json``."""
    _write(metrics, _record("cat", "gca", seed=1, chamfer_mean=2.0), "gca.json")
    _write(metrics, _record("cat", "gca", seed=1, chamfer_mean=3.0), "gca@seed1.json")
    with pytest.warns(RuntimeWarning, match="the record says seed 1, its name seed 0"):
        runs = load_runs(metrics)
    assert [(r["seed"], r["chamfer_mean"]) for r in runs["cat", "gca"]] == [(0, 2.0), (1, 3.0)]


def _load_stage(repo_root: Path):
    spec = importlib.util.spec_from_file_location("stage_report", repo_root / "stages" / "report.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_stage_main_end_to_end(metrics, tmp_path, repo_root):
    params = tmp_path / "params.yaml"
    shipped = yaml.safe_load((Path(__file__).resolve().parents[1] / "params.yaml").read_text())
    params.write_text(yaml.safe_dump({"profile": "ci", "report": shipped["report"]}))  # every report key is required
    stage = _load_stage(repo_root)
    runs_before = load_runs(metrics)
    written = stage.main(["--metrics", str(metrics), "--out", str(tmp_path / "reports"),
                          "--summary", str(metrics / "report.json"), "--params", str(params)])
    assert (tmp_path / "reports" / "README.md") in written
    headline = json.loads((metrics / "report.json").read_text())
    assert headline["table1_average_cd"]["nclaw"]["mean_cd"] == pytest.approx(3.5)
    assert headline["table1_average_cd"]["gca"]["status"] == "diverged"
    assert headline["status_counts"] == {"diverged": 1, "failed": 1, "ok": 11}
    assert load_runs(metrics) == runs_before  # report.json, now at the top level, is not read as a run
    import mlflow
    found = mlflow.search_runs(experiment_names=["gca/report"], output_format="list")
    assert len(found) == 1 and found[0].data.tags["stage"] == "report"
    assert found[0].data.metrics["table1_average_cd.nclaw"] == pytest.approx(3.5)


def test_strips_come_from_the_reported_runs_not_the_current_checkout(tmp_path, monkeypatch):
    """Results kept elsewhere (``<root>/metrics/eval``) resolve ``strip_png`` against ``<root>``: a
    same-named strip of this checkout's own runs (the cwd) must not be drawn in their report."""
    import matplotlib.image as mpimg
    kept, here = tmp_path / "kept", tmp_path / "checkout"
    rel = "metrics/eval/ball/gca/strip.png"
    _write(kept / "metrics" / "eval", _record("ball", "gca", chamfer_mean=0.5, strip_png=rel))
    (here / rel).parent.mkdir(parents=True)
    mpimg.imsave(here / rel, np.zeros((8, 32, 3)))  # the decoy
    monkeypatch.chdir(here)
    written = build_reports(kept / "metrics" / "eval", tmp_path / "r1")
    assert "strip_ball.png" not in {p.name for p in written}
    (kept / rel).parent.mkdir(parents=True)
    mpimg.imsave(kept / rel, np.ones((8, 32, 3)))
    written = build_reports(kept / "metrics" / "eval", tmp_path / "r2")
    assert "strip_ball.png" in {p.name for p in written}


def test_a_report_stopped_while_it_copies_capture_media_keeps_the_previous_one(metrics, tmp_path, monkeypatch):
    """Issue 24 item 7: a capture scene's page and media are written inside the report folder replaced as one;
    stopped (SIGTERM) while copying them, the previous report stays as it was and nothing is left beside it."""
    from gca import stop
    from gca.report import captures

    out = tmp_path / "reports"
    build_reports(metrics, out, ReportConfig(dpi=40))
    before = {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    gif = tmp_path / "resim.gif"
    gif.write_bytes(b"GIF89a")
    _write(metrics, {"scene": "mine", "method": "gca", "kind": "capture", "status": "ok", "resim_gif": str(gif)})

    def cut(src, dst):
        Path(dst).write_bytes(b"GIF")
        raise stop.Terminated()

    monkeypatch.setattr(captures.shutil, "copyfile", cut)
    with pytest.raises(stop.Terminated):
        build_reports(metrics, out, ReportConfig(dpi=40))
    assert {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []
    monkeypatch.undo()
    written = build_reports(metrics, out, ReportConfig(dpi=40))
    assert out / "captures" / "mine.md" in written and (out / "captures" / "mine_gca_resim.gif").read_bytes() == b"GIF89a"


def test_table4_says_when_its_times_are_packed(tmp_path):
    """Runs that shared their GPU (the grid's slots, under MPS) are named in Table 4's notes: packed times are not
    solo times. Runs that did not (a record without the field counts as alone) add no note (negative control)."""
    alone, packed = tmp_path / "alone", tmp_path / "packed"
    for root, extra in ((alone, {}), (packed, {"runs_per_gpu": 8, "mps": True})):
        for method in ("gca", "gca_full_ft"):
            _write(root, _record("ball", method, chamfer_mean=0.1, train_seconds=60.0, peak_memory_gib=1.0,
                                 **(extra if method == "gca" else {})))
    assert not any("packed" in n for n in tables.table4_efficiency(load_runs(alone)).notes)
    (note,) = [n for n in tables.table4_efficiency(load_runs(packed)).notes if "packed" in n]
    assert note.startswith("1 of 2 runs trained with up to 8 runs on one GPU (under CUDA MPS)")
    assert "below-normal" not in note  # the grid's priority: said only where a run had it
    low = tmp_path / "low"
    for method in ("gca", "gca_full_ft"):
        _write(low, _record("ball", method, chamfer_mean=0.1, train_seconds=60.0, peak_memory_gib=1.0,
                            runs_per_gpu=8, mps=True, mps_priority="below_normal" if method == "gca" else "normal"))
    (note,) = [n for n in tables.table4_efficiency(load_runs(low)).notes if "packed" in n]
    assert note.startswith("2 of 2 runs trained with up to 8 runs on one GPU (under CUDA MPS, 1 of them at MPS's "
                           "below-normal priority (")
    assert "more than one" not in note  # no run was stopped and resumed at another priority
    for seed, priority in ((1, "mixed"), (2, "mixed")):  # stopped and resumed at another priority (merged_sharing)
        _write(low, _record("ball", "gca", seed=seed, chamfer_mean=0.1, train_seconds=60.0, peak_memory_gib=1.0,
                            runs_per_gpu=8, mps=True, mps_priority=priority), name=f"gca@seed{seed}.json")
    (note,) = [n for n in tables.table4_efficiency(load_runs(low)).notes if "packed" in n]
    assert note.startswith("4 of 4 runs trained with up to 8 runs on one GPU (under CUDA MPS, 1 of them at MPS's "
                           "below-normal priority and 2 at more than one MPS priority, stopped and resumed at "
                           "another (")


def test_a_runs_gpu_sharing_comes_from_its_launcher(monkeypatch):
    """train.json's runs_per_gpu and mps: the grid's environment; a run started otherwise counts as alone."""
    from gca.pipeline.train import gpu_sharing

    monkeypatch.delenv("GCA_RUNS_PER_GPU", raising=False)
    monkeypatch.delenv("GCA_MPS", raising=False)
    monkeypatch.delenv("CUDA_MPS_CLIENT_PRIORITY", raising=False)
    monkeypatch.delenv("GCA_MPS_PRIORITY", raising=False)
    assert gpu_sharing() == {"runs_per_gpu": 1, "mps": False, "mps_priority": None}
    monkeypatch.setenv("GCA_RUNS_PER_GPU", "8")
    monkeypatch.setenv("GCA_MPS", "1")
    assert gpu_sharing() == {"runs_per_gpu": 8, "mps": True, "mps_priority": None}
    monkeypatch.setenv("CUDA_MPS_CLIENT_PRIORITY", "1")  # CUDA's own, set by someone else: not the grid's priority
    assert gpu_sharing()["mps_priority"] is None
    monkeypatch.setenv("GCA_MPS_PRIORITY", "1")  # a grid that gave priorities: this run below normal
    assert gpu_sharing()["mps_priority"] == "below_normal"
    monkeypatch.setenv("CUDA_MPS_CLIENT_PRIORITY", "0")  # normal, beside below-normal ones
    assert gpu_sharing()["mps_priority"] == "normal"
    monkeypatch.setenv("GCA_MPS", "0")  # without MPS no priority acts
    assert gpu_sharing()["mps_priority"] is None


def test_a_runs_gpu_sharing_merges_the_processes_that_trained_it():
    """A run stopped and resumed at another MPS priority is "mixed" (Table 4's note and the grid's estimates read
    it); one priority throughout stays that one (negative control); the most runs per GPU and any MPS count; an
    entry without the fields (a process that gave train none) counts as alone."""
    from gca.pipeline.train import merged_sharing

    low, normal = ({"runs_per_gpu": n, "mps": True, "mps_priority": p} for n, p in ((8, "below_normal"), (4, "normal")))
    assert merged_sharing([low, normal]) == {"runs_per_gpu": 8, "mps": True, "mps_priority": "mixed"}
    assert merged_sharing([low, {**low, "runs_per_gpu": 2}])["mps_priority"] == "below_normal"
    assert merged_sharing([{"resumed_at": 0}, {**low, "resumed_at": 5}])["mps_priority"] == "mixed"  # partly below
    assert merged_sharing([{"resumed_at": 2}]) == {"runs_per_gpu": 1, "mps": False, "mps_priority": None}


def test_a_run_is_evaluated_with_the_launch_velocity_it_trained_with(tmp_path):
    """A grid going on on another machine may estimate a seed's shared velocity.json again (its remade inputs differ
    in float32 noise, session 20); a run trained before keeps its own estimate in train.json, and evaluation uses
    that. A run from before session 20 (no ``velocity`` in train.json) falls back to the shared file."""
    from gca.io import read_json
    from gca.pipeline.train import trained_velocity

    def evaluated_with(run):
        return trained_velocity(read_json(runs / run / "train.json"), runs, run, 0)

    runs = tmp_path / "runs"
    (runs / "gca").mkdir(parents=True)
    (runs / "velocity.json").write_text(json.dumps({"v0": [9.0, 9.0, 9.0], "w0": [0.0, 0.0, 0.0]}))  # re-estimated
    (runs / "gca/train.json").write_text(json.dumps({"velocity": {"v0": [1.0, 2.0, 3.0], "w0": [0.0, 0.1, 0.0]}}))
    assert evaluated_with("gca") == (([1.0, 2.0, 3.0], [0.0, 0.1, 0.0]), "train.json")
    (runs / "gca/train.json").write_text(json.dumps({"status": "ok"}))  # an older run: the shared file
    assert evaluated_with("gca") == (([9.0, 9.0, 9.0], [0.0, 0.0, 0.0]), "velocity.json")
    (runs / "gca/train.json").write_text(json.dumps({"velocity": {"v0": [1.0, float("nan"), 3.0], "w0": [0, 0, 0]}}))
    with pytest.raises(ValueError, match="gca/train.json: v0 must be 3 finite numbers"):
        evaluated_with("gca")
