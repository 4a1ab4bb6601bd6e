"""gca/pipeline/grid.py: the dvc.yaml stages expanded for a scene grid, ordered by deps/outs; its command line
through the engine's local executor. Running the jobs (failures, GPU slots, requeue, deadline, resume):
tests/test_pipeline_dispatch.py."""

import argparse
import contextlib
import json
import tarfile
from pathlib import Path

import pytest
import yaml

from gca.pipeline import grid

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def jobs():
    params = grid.grid_params("ci", ["ball", "cat"], ["gca", "nclaw"], ["train.iterations=3"])
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    return params, grid.link(grid.split_runs(grid.expand(dvc, params, ["assets", "particles", "prior", "ground_truth",
                                                                          "preprocess", "train", "evaluate", "report"]),
                                              params))


def test_grid_params_keep_only_what_the_scenes_need():
    params = grid.grid_params("paper", ["fish"], None, ["train.iterations=7"])
    assert list(params["scenes"]) == ["fish"] and list(params["objects"]) == ["fish"]
    assert list(params["prior"]["families"]) == ["sand"] and params["train"]["iterations"] == 7
    with pytest.raises(SystemExit, match="unknown scene"):
        grid.grid_params("ci", ["teapot"], None, [])


def test_stage_commands_are_dvc_yaml_expanded(jobs):
    params, jobs = jobs
    assert {"assets@ball", "assets@cat", "prior@jelly", "prior@plasticine", "ground_truth@cat", "evaluate@ball:gca",
            "report", "train@ball:nclaw", "train@ball:gca"} <= set(jobs)
    assert "prior@sand" not in jobs and "train@ball" not in jobs and "evaluate@ball" not in jobs
    assert jobs["report"].cmd.split("--out ")[1].startswith("reports/ci ")
    assert jobs["assets@cat"].cmd.startswith("python stages/assets.py --object cat --out data/assets/cat")
    gca = jobs["train@ball:gca"]
    assert gca.cmd.endswith("--methods gca --velocity runs/ball/velocity.json")
    assert jobs["train@ball:nclaw"].cmd.endswith("--methods nclaw")  # the cheap one estimates the velocity


def test_seeds_split_training_into_one_job_per_run():
    params = grid.grid_params("ci", ["ball"], ["gca", "nclaw"], ["train.seeds=[0,2]"])
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    jobs = grid.link(grid.split_runs(grid.expand(dvc, params, ["train", "evaluate"]), params))
    train = {n: j for n, j in jobs.items() if n.startswith("train@")}
    # every method runs every seed (the prior's launch velocity comes from the seed's own nuisance draw)
    assert set(train) == {"train@ball:nclaw", "train@ball:gca", "train@ball:nclaw@seed2", "train@ball:gca@seed2"}
    # each seed's cheapest run estimates that seed's launch velocity from its observations; the seed's others reuse it
    assert train["train@ball:nclaw"].cmd.endswith("--methods nclaw --seeds 0")
    assert train["train@ball:nclaw@seed2"].cmd.endswith("--methods nclaw --seeds 2")
    assert train["train@ball:nclaw@seed2"].outs == ["runs/ball/nclaw@seed2", "runs/ball/velocity@seed2.json"]
    assert train["train@ball:gca@seed2"].cmd.endswith("--methods gca --seeds 2 --velocity runs/ball/velocity@seed2.json")
    assert train["train@ball:gca@seed2"].outs == ["runs/ball/gca@seed2"]
    assert train["train@ball:gca@seed2"].after == {"train@ball:nclaw@seed2"}
    assert train["train@ball:gca"].after == {"train@ball:nclaw"}
    # each run is evaluated after its own training (and its seed's launch velocity), not after the scene's others
    evaluate = {n: j for n, j in jobs.items() if n.startswith("evaluate@")}
    assert set(evaluate) == {n.replace("train@", "evaluate@") for n in train}
    assert evaluate["evaluate@ball:gca@seed2"].cmd.endswith("--methods gca --seeds 2")
    assert evaluate["evaluate@ball:gca@seed2"].outs == ["metrics/eval/ball/gca@seed2.json", "metrics/eval/ball/gca@seed2"]
    assert evaluate["evaluate@ball:gca@seed2"].after & set(train) == {"train@ball:gca@seed2", "train@ball:nclaw@seed2"}
    assert evaluate["evaluate@ball:gca"].after & set(train) == {"train@ball:gca", "train@ball:nclaw"}


def test_order_follows_deps_and_outs(jobs):
    _, jobs = jobs
    assert {"train@ball:nclaw", "prior@jelly", "ground_truth@ball", "preprocess@ball", "particles@ball",
            "assets@ball"} <= jobs["train@ball:gca"].after
    assert "prior@plasticine" not in jobs["train@ball:gca"].after
    assert {"train@cat:gca", "train@cat:nclaw"} <= jobs["evaluate@cat:gca"].after
    assert {"evaluate@ball:gca", "evaluate@cat:nclaw"} <= jobs["report"].after
    prio = grid.critical_path(jobs)  # gca.pipeline.dispatch's
    assert prio["prior@jelly"] > prio["train@ball:gca"] > prio["evaluate@ball:gca"] > prio["report"] > 0


def test_collect_keeps_the_small_results(tmp_path):
    for rel in ("metrics/eval/ball/gca.json", "reports/ci/table1_synthetic_cd.md", "runs/ball/gca/train.json",
                "runs/ball/gca/law.pt", "data/scenes/ball/meta.json", "models/prior/jelly.pt"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x")
    with tarfile.open(grid.collect(tmp_path, tmp_path / "out")) as tar:
        names = set(tar.getnames())
    assert names == {"metrics/eval/ball/gca.json", "reports/ci/table1_synthetic_cd.md", "runs/ball/gca/train.json",
                     "runs/ball/gca/law.pt", "models/prior/jelly.pt"}
    assert not (tmp_path / "out" / "grid_media.tar.gz").exists()  # no media, no media archive


def test_collect_puts_the_media_beside_the_results_under_a_cap(tmp_path, monkeypatch, capsys):
    """An evaluation's media go to grid_media.tar.gz, the still images first, while their bytes stay under
    grid.MEDIA_CAP (the device tool's 16-MiB files: session 56's three-seed archive went over and did not come
    back); the results' archive holds none of them. Control: with the cap above every file, all are packed."""
    sizes = {"metrics/eval/ball/gca/rollout.gif": 600, "metrics/eval/ball/gca/strip.png": 300,
             "metrics/eval/cat/gca@seed1/cd_time.png": 300, "metrics/eval/cat/gca@seed1/rollout.gif": 600,
             "metrics/eval/ball/gca.json": 10, "reports/ci/figures/law_curves.png": 50}
    for rel, n in sizes.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"x" * n)
    monkeypatch.setattr(grid, "MEDIA_CAP", 1300)
    with tarfile.open(grid.collect(tmp_path, tmp_path / "out")) as tar:
        assert set(tar.getnames()) == {"metrics/eval/ball/gca.json", "reports/ci/figures/law_curves.png"}
    with tarfile.open(tmp_path / "out" / "grid_media.tar.gz") as tar:
        assert tar.getnames() == ["metrics/eval/ball/gca/strip.png", "metrics/eval/cat/gca@seed1/cd_time.png",
                                  "metrics/eval/ball/gca/rollout.gif"]  # 1200 bytes: the second GIF over the cap
    assert "1 of 4 files left out of grid_media.tar.gz" in capsys.readouterr().out
    monkeypatch.setattr(grid, "MEDIA_CAP", 10 ** 6)
    grid.collect(tmp_path, tmp_path / "out2")
    with tarfile.open(tmp_path / "out2" / "grid_media.tar.gz") as tar:
        assert len(tar.getnames()) == 4
    assert "left out" not in capsys.readouterr().out


def test_collect_passes_over_a_file_a_running_grid_removed(tmp_path, monkeypatch):
    """A snapshot of a running grid (table_bundle.sh, DETACH=1) lists the files, then packs them: one removed
    meanwhile is passed over, the rest packed, by collect and by save_state's pack_files. Negative control: a file
    that became a folder still raises."""
    for rel in ("runs/ball/gca/train.json", "runs/ball/gca/history.json", ".grid/train@ball:gca.done"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x")
    stale = grid._listed(tmp_path)
    (tmp_path / "runs/ball/gca/history.json").unlink()  # gone between the listing and the add
    (tmp_path / ".grid/train@ball:gca.done").unlink()
    monkeypatch.setattr(grid, "_listed", lambda work, tries=3: stale)
    with tarfile.open(grid.collect(tmp_path, tmp_path / "out")) as tar:
        assert tar.getnames() == ["runs/ball/gca/train.json"]
    from gca.io import pack_files
    assert pack_files(tmp_path, [".grid/train@ball:gca.done", "runs/ball/gca/train.json"], tmp_path / "s.tgz") == 1
    (tmp_path / "runs/ball/gca/history.json").mkdir()
    with pytest.raises(IsADirectoryError):
        grid.collect(tmp_path, tmp_path / "out2")


def test_the_listing_is_made_again_when_a_folder_vanished_midway(tmp_path, monkeypatch):
    """grid._listed: rglob raises when a folder it walks is removed midway (a temporary of gca.io.atomic_path in a
    running grid); the listing is made again. Negative control: a listing that keeps failing raises."""
    (tmp_path / "a.json").write_text("x")
    real, calls = Path.rglob, []

    def flaky(self, pattern):
        calls.append(1)
        if len(calls) == 1:
            raise FileNotFoundError("tmp folder gone")
        return real(self, pattern)

    monkeypatch.setattr(Path, "rglob", flaky)
    assert [rel for _, rel, _ in grid._listed(tmp_path)] == ["a.json"] and len(calls) == 2
    monkeypatch.setattr(Path, "rglob", lambda self, pattern: (_ for _ in ()).throw(FileNotFoundError("gone")))
    with pytest.raises(FileNotFoundError):
        grid._listed(tmp_path)


def test_before_runs_once_ahead_of_the_jobs(tmp_path):
    work = tmp_path / "w"
    state = grid.main(["--work", str(work), "--scenes", "duck", "--profile", "ci", "--stages", "report",
                       "--before", "python -c \"open('before.txt','w').write('x')\""])
    assert (work / "before.txt").read_text() == "x" and (work / "params.yaml").is_file()
    assert set(state) == {"report"}


STUB_MPS = """#!/usr/bin/env bash
echo "args=$* stdin=$(if [ -z "$*" ]; then cat; fi)" >> "{log}"
exit {code}
"""


def _mps_stub(tmp_path, monkeypatch, code=0, root=True):
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    log = tmp_path / "mps.log"
    (bin_ / grid.MPS_CONTROL).write_text(STUB_MPS.format(log=log, code=code))
    (bin_ / grid.MPS_CONTROL).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_}:/usr/bin:/bin")
    monkeypatch.setattr(grid.os, "geteuid", lambda: 0 if root else 1000)
    return log


def test_mps_started_for_the_jobs_and_stopped_after(tmp_path, monkeypatch):
    calls = _mps_stub(tmp_path, monkeypatch)
    lines = []
    with grid.mps_daemon(True, lines.append) as on:
        assert on and calls.read_text().splitlines() == ["args=-d stdin="]  # started before the jobs
    assert calls.read_text().splitlines() == ["args=-d stdin=", "args= stdin=quit"]  # stopped after
    assert "daemon started" in lines[0] and "daemon stopped" in lines[1]


def test_mps_stopped_even_when_the_jobs_fail(tmp_path, monkeypatch):
    calls = _mps_stub(tmp_path, monkeypatch)
    with pytest.raises(KeyboardInterrupt), grid.mps_daemon(True, lambda m: None):
        raise KeyboardInterrupt
    assert calls.read_text().splitlines()[-1] == "args= stdin=quit"


@pytest.mark.parametrize("case", ["not root", "no binary", "start fails", "off"])
def test_mps_says_why_it_does_not_run(tmp_path, monkeypatch, case):
    calls = _mps_stub(tmp_path, monkeypatch, code=1 if case == "start fails" else 0, root=case != "not root")
    if case == "no binary":
        monkeypatch.setenv("PATH", "/usr/bin:/bin")
    lines = []
    with grid.mps_daemon(case != "off", lines.append) as on:
        assert not on
    expected = {"not root": "not root", "no binary": "not on PATH", "start fails": "failed", "off": None}[case]
    if expected is None:
        assert lines == [] and not calls.exists()
    else:
        assert len(lines) == 1 and expected in lines[0] and "time-slice" in lines[0]
        assert ("quit" not in calls.read_text()) if calls.exists() else True  # nothing to stop


def test_grid_main_runs_jobs_under_mps(tmp_path, monkeypatch):
    calls = _mps_stub(tmp_path, monkeypatch)
    seen = []

    def fake_run(*args, **kwargs):
        seen.append(calls.read_text())
        return {}
    monkeypatch.setattr(grid.dispatch, "run", fake_run)
    grid.main(["--work", str(tmp_path / "w"), "--scenes", "ball", "--methods", "gca", "--profile", "ci",
               "--stages", "assets", "--mps"])
    assert seen == ["args=-d stdin=\n"] and calls.read_text().endswith("args= stdin=quit\n")


def test_gpu_ids():
    assert grid.gpu_ids("2,3") == [2, 3] and grid.gpu_ids("4") == 4 and grid.gpu_ids("0,") == [0]
    with pytest.raises(argparse.ArgumentTypeError, match="comma-separated"):
        grid.gpu_ids("1;2")


def test_a_work_folder_links_the_cited_tuning_record_only(tmp_path, monkeypatch):
    """The report in a grid's work folder reads the tuning record params.yaml cites: linked as a file, never the
    checkout's tuning/ folder (a tuning's work folder, made by the same function, would write its units there)."""
    root = tmp_path / "checkout"
    for name in ("stages", "gca", "dvc.yaml"):
        (root / name).mkdir(parents=True)
    (root / "tuning").mkdir()
    (root / "tuning/record.json").write_text("{}")
    monkeypatch.setattr(grid, "ROOT", root)
    cited, uncited = tmp_path / "cited", tmp_path / "uncited"
    grid.prepare(cited, {"tuning": {"record": "tuning/record.json"}})
    grid.prepare(uncited, {"tuning": {"record": ""}})
    assert (cited / "tuning/record.json").read_text() == "{}" and not (cited / "tuning").is_symlink()
    assert not (uncited / "tuning").exists()
    (cited / "tuning/gca").mkdir()
    assert not (root / "tuning/gca").exists()


def test_needed_runs_what_a_job_to_run_reads_and_the_ends(jobs):
    """After a restored state, a scene whose training and evaluation are done does not remake its inputs; one
    with a run left remakes what that run reads (negative control: nothing done runs everything)."""
    _, js = jobs
    assert grid.needed(js, set()) == set(js)
    ball_done = {n for n in js if n.startswith(("train@ball", "evaluate@ball"))}
    need = grid.needed(js, ball_done)
    assert not any(n.endswith("@ball") for n in need)  # assets@ball .. preprocess@ball: nothing left reads them
    assert {"assets@cat", "preprocess@cat", "train@cat:gca", "evaluate@cat:gca", "report"} <= need
    one_left = ball_done - {"train@ball:gca"}  # a run to redo (its marker removed): it remakes what it reads
    need = grid.needed(js, one_left)
    assert {"train@ball:gca", "preprocess@ball", "assets@ball"} <= need
    assert "train@ball:nclaw" not in need  # done: never run again
    prior = next(n for n in js if n.startswith("prior@"))
    assert prior in need  # the inputs still read by the runs left (ball's gca, every cat job)


def _write(root, rels, text="x"):
    for rel in rels:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)


def test_grid_state_moves_runs_and_evaluations_not_inputs(tmp_path):
    """--save-state keeps what another machine needs to go on (the runs' results and laws, the
    launch velocities, the evaluations' JSON, the training/evaluation markers) and not the inputs, nor what nothing
    downstream reads (histories, media, MLflow), nor a cut-off run's checkpoint (it would not resume on remade
    inputs); --restore-state refuses a state made under other params, or with a member that is not a state file,
    writing nothing, and leaves out the checkpoints of an older state."""
    work, elsewhere = tmp_path / "w", tmp_path / "elsewhere"
    params = grid.grid_params("ci", ["ball"], ["gca", "nclaw"], ["train.seeds=[0,1]"])
    grid.prepare(work, params)
    state = [".grid/train@ball:gca.done", ".grid/evaluate@ball:gca.done", "runs/ball/gca/train.json",
             "runs/ball/gca/law.pt", "runs/ball/velocity.json", "runs/ball/velocity@seed1.json", "metrics/eval/ball/gca.json"]
    inputs = [".grid/assets@ball.done", ".grid/preprocess@ball.done", "data/scenes/ball/meta.json",
              "metrics/assets/ball.json", ".grid/grid.log", ".grid/report.done",
              # what nothing downstream reads: each call returns it instead (--collect)
              "runs/ball/gca/history.json", "runs/ball/gca/loss.png", "metrics/eval/ball/gca/strip.png", "mlflow.db",
              "runs/ball/gca@seed1/checkpoint.pt", "runs/ball/gca@seed1/checkpoint.pt.stamp"]
    _write(work, state + inputs)
    archive = tmp_path / "state.tgz"
    assert grid.save_state(work, archive) == len(state) + 1  # and the params digest
    grid.prepare(elsewhere, params)
    assert grid.restore_state(archive, elsewhere) == len(state) + 1
    assert all((elsewhere / rel).read_text() == "x" for rel in state)
    assert not any((elsewhere / rel).exists() for rel in inputs)
    (elsewhere / "runs/ball/gca/train.json").write_text("newer")
    grid.restore_state(archive, elsewhere)
    assert (elsewhere / "runs/ball/gca/train.json").read_text() == "newer"  # a file there is kept

    other = tmp_path / "other"
    grid.prepare(other, grid.grid_params("ci", ["ball"], ["gca", "nclaw"], ["train.seeds=[0,1,2]"]))
    with pytest.raises(SystemExit, match="made under other params"):
        grid.restore_state(archive, other)
    assert not (other / "runs").exists()
    bad = tmp_path / "bad.tgz"
    with tarfile.open(archive) as src, tarfile.open(bad, "w:gz") as tar:
        for m in src.getmembers():
            tar.addfile(m, src.extractfile(m))
        info = tarfile.TarInfo("data/scenes/ball/meta.json")
        info.size = 1
        import io
        tar.addfile(info, io.BytesIO(b"y"))
    fresh = tmp_path / "fresh"
    grid.prepare(fresh, params)
    with pytest.raises(SystemExit, match="is not a grid state file"):
        grid.restore_state(bad, fresh)
    assert not (fresh / "runs").exists()
    with pytest.raises(SystemExit, match="no grid state there"):
        grid.restore_state(tmp_path / "missing.tgz", fresh)

    # a state of session 21 carried checkpoints: it restores, without them (they would train afresh here)
    old = tmp_path / "old.tgz"
    with tarfile.open(archive) as src, tarfile.open(old, "w:gz") as tar:
        for m in src.getmembers():
            tar.addfile(m, src.extractfile(m))
        for rel in ("runs/ball/gca@seed1/checkpoint.pt", "runs/ball/gca@seed1/checkpoint.pt.stamp"):
            info = tarfile.TarInfo(rel)
            info.size = 1
            tar.addfile(info, io.BytesIO(b"c"))
    grid.prepare(tmp_path / "from_old", params)
    assert grid.restore_state(old, tmp_path / "from_old") == len(state) + 1
    assert not (tmp_path / "from_old/runs/ball/gca@seed1/checkpoint.pt").exists()


def test_a_grid_state_grows_by_methods_and_runs_only_the_new_runs(tmp_path, monkeypatch):
    """Table 3's rows after Table 1's: a state restored into a grid with more methods keeps the runs done and their
    evaluations; only the new methods' runs are trained and evaluated (one evaluation job per run). A grid with other
    knobs is refused (negative control); one over a subset of the state's methods: test_a_grid_over_part_of_a_state...."""
    work = tmp_path / "w"
    grid.prepare(work, grid.grid_params("ci", ["ball", "cat"], ["nclaw"], []))
    _write(work, [".grid/train@ball:nclaw.done", ".grid/evaluate@ball:nclaw.done", ".grid/train@cat:nclaw.done",
                  ".grid/evaluate@cat:nclaw.done", "runs/ball/nclaw/train.json", "metrics/eval/ball/nclaw.json"])
    archive = tmp_path / "state.tgz"
    grid.save_state(work, archive)
    params = grid.grid_params("ci", ["ball", "cat"], ["nclaw"], [])
    params["scenes"]["ball"]["methods"] = ["nclaw", "gca"]
    grown = tmp_path / "grown"
    grid.prepare(grown, params)
    grid.restore_state(archive, grown)
    assert (grown / ".grid/train@ball:nclaw.done").is_file() and (grown / "runs/ball/nclaw/train.json").is_file()
    assert (grown / ".grid/evaluate@ball:nclaw.done").is_file()  # evaluated before: kept
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    jobs = grid.link(grid.split_runs(grid.expand(dvc, params, ["train", "evaluate"]), params))
    todo = {n for n in jobs if not grid.dispatch.is_done(grown, n)}
    assert todo == {"train@ball:gca", "evaluate@ball:gca"}  # ball's new run only
    knob = tmp_path / "knob"
    grid.prepare(knob, grid.grid_params("ci", ["ball", "cat"], ["nclaw"], ["align.rdga.lambda1=0.5"]))
    with pytest.raises(SystemExit, match="made under other params"):
        grid.restore_state(archive, knob)


def test_execution_only_values_are_tuples_not_strings():
    """``value in equal_at``: a bare string would be a substring test ("high" in "highest": TF32 taken as FP32)."""
    from gca.train.config import EXECUTION_ONLY

    assert EXECUTION_ONLY and all(v is None or (isinstance(v, tuple) and all(isinstance(x, str) for x in v))
                                  for v in EXECUTION_ONLY.values())
    assert "high" not in EXECUTION_ONLY["matmul_precision"] and "triton_tf32" not in EXECUTION_ONLY["mlp_kernel"]


def test_a_grid_state_goes_on_across_execution_only_knobs(tmp_path):
    """A state made before train.reverse_sweep, matmul_precision and mlp_kernel existed (Tables 2-6's state.tgz,
    session 30) goes on under today's params, and one made under another MLP kernel or without the reverse sweep too
    (the same numbers to float rounding); TF32 products are not rounding-equal: a state made at ``highest`` is refused
    under ``high`` (negative control), so is one under the TF32 Triton MLP, and so is a knob that changes the method."""
    import yaml as _yaml

    params = grid.grid_params("ci", ["ball"], ["nclaw"], [])
    older = tmp_path / "older"
    grid.prepare(older, params)
    raw = _yaml.safe_load((older / "params.yaml").read_text())
    for knob in ("reverse_sweep", "matmul_precision", "mlp_kernel"):
        assert knob in raw["train"]
        del raw["train"][knob]
    (older / "params.yaml").write_text(_yaml.safe_dump(raw))
    _write(older, [".grid/train@ball:nclaw.done", "runs/ball/nclaw/train.json"])
    archive = tmp_path / "state.tgz"
    grid.save_state(older, archive)
    switched = tmp_path / "switched"  # a profile switch at the rounding-equal value is that value
    grid.prepare(switched, params)
    raw_here = _yaml.safe_load((switched / "params.yaml").read_text())
    raw_here["train"]["matmul_precision"] = {"paper": "high", "ci": "highest"}
    (switched / "params.yaml").write_text(_yaml.safe_dump(raw_here))
    assert grid.restore_state(archive, switched) == 2 + 1
    for i, overrides in enumerate([[], ["train.mlp_kernel=simt", "train.reverse_sweep=false"]]):
        here = tmp_path / f"here{i}"
        grid.prepare(here, grid.grid_params("ci", ["ball"], ["nclaw"], overrides))
        assert grid.restore_state(archive, here) == 2 + 1
        assert (here / ".grid/train@ball:nclaw.done").is_file()
    for i, overrides in enumerate([["train.matmul_precision=high"], ["train.mlp_kernel=triton_tf32"],
                                   ["train.iterations=7"]]):
        refused = tmp_path / f"refused{i}"
        grid.prepare(refused, grid.grid_params("ci", ["ball"], ["nclaw"], overrides))
        with pytest.raises(SystemExit, match="made under other params"):
            grid.restore_state(archive, refused)
        assert not (refused / "runs").exists()


def test_evaluations_that_lack_a_metric_added_since_run_again_once(tmp_path):
    """Session 21 added chamfer_mean_true_launch: Table 1's 54 evaluations lack it. Those jobs (and the report) are
    done no more, the training is kept; an evaluation that has it stays done, so a second call undoes nothing."""
    work = tmp_path / "w"
    grid.prepare(work, grid.grid_params("ci", ["ball"], ["nclaw", "gca"], []))
    _write(work, [".grid/train@ball:nclaw.done", ".grid/evaluate@ball:nclaw.done", ".grid/train@ball:gca.done",
                  ".grid/evaluate@ball:gca.done", ".grid/report.done"])
    (work / "metrics/eval/ball").mkdir(parents=True)
    (work / "metrics/eval/ball/nclaw.json").write_text(json.dumps({"chamfer_mean": 0.1}))
    (work / "metrics/eval/ball/gca.json").write_text(json.dumps({"chamfer_mean": 0.1, "chamfer_mean_true_launch": 0.05}))
    # a batched evaluation (CPU: `--runs-per-job`) whose second run lacks it; a diverged rollout (no CD: nothing to
    # remake, stays done); a scene-level marker of a tuning (no run in its name): ignored
    for rel in ("evaluate@ball:gca@seed1+nclaw@seed1", "evaluate@ball:neuma", "evaluate@calib"):
        grid.dispatch.marker(work, rel).write_text("1\n")
    (work / "metrics/eval/ball/gca@seed1.json").write_text(json.dumps({"chamfer_mean": 0.1, "chamfer_mean_true_launch": 0.1}))
    (work / "metrics/eval/ball/nclaw@seed1.json").write_text(json.dumps({"chamfer_mean": 0.1}))
    (work / "metrics/eval/ball/neuma.json").write_text(json.dumps({"status": "diverged"}))
    assert grid.evaluate_missing(work, "chamfer_mean_true_launch") == ["evaluate@ball:gca@seed1+nclaw@seed1",
                                                                       "evaluate@ball:nclaw"]
    assert grid.dispatch.is_done(work, "evaluate@ball:neuma") and grid.dispatch.is_done(work, "evaluate@calib")
    assert not grid.dispatch.is_done(work, "evaluate@ball:nclaw") and not grid.dispatch.is_done(work, "report")
    assert grid.dispatch.is_done(work, "evaluate@ball:gca") and grid.dispatch.is_done(work, "train@ball:nclaw")
    for run in ("nclaw", "gca@seed1+nclaw@seed1"):  # evaluated again, now with the metric
        (work / f".grid/evaluate@ball:{run}.done").write_text("1\n")
    for run in ("nclaw", "nclaw@seed1"):
        (work / f"metrics/eval/ball/{run}.json").write_text(json.dumps({"chamfer_mean": 0.1, "chamfer_mean_true_launch": 0.08}))
    (work / ".grid/report.done").write_text("1\n")
    assert grid.evaluate_missing(work, "chamfer_mean_true_launch") == []
    assert grid.dispatch.is_done(work, "report")


def test_a_grid_state_grows_by_scenes_into_one_report(tmp_path):
    """Tables 2, 5 and 6 after Tables 1 and 3, in one state (one report, one claims table): a state restored into a
    grid with more scenes keeps every run done; a new scene starts from nothing. Refused (negative controls, nothing
    written): a grid where a scene of the state is defined otherwise (its object), and one with other knobs."""
    work = tmp_path / "w"
    grid.prepare(work, grid.grid_params("ci", ["ball", "cat"], ["nclaw"], []))
    _write(work, [".grid/train@ball:nclaw.done", ".grid/evaluate@ball:nclaw.done", "runs/ball/nclaw/train.json",
                  "metrics/eval/ball/nclaw.json"])
    archive = tmp_path / "state.tgz"
    grid.save_state(work, archive)
    more = tmp_path / "more"
    grid.prepare(more, grid.grid_params("ci", ["ball", "cat", "dragon", "composite"], ["nclaw"], []))
    assert grid.restore_state(archive, more) == 5
    assert (more / ".grid/evaluate@ball:nclaw.done").is_file()  # evaluated: not evaluated again
    assert not (more / "runs/dragon").exists()
    for name, scenes, overrides, why in [
            ("moved", ["ball", "cat"], ["scenes.cat.object=duck"], "scene.s. \\['cat'\\] defined otherwise"),
            ("knob", ["ball", "cat", "dragon"], ["align.rdga.lambda1=0.5"], "other seeds, profile or knobs")]:
        grid.prepare(tmp_path / name, grid.grid_params("ci", scenes, ["nclaw"], overrides))
        with pytest.raises(SystemExit, match=why):
            grid.restore_state(archive, tmp_path / name)
        assert not (tmp_path / name / "runs").exists()
    older = tmp_path / "older.tgz"  # a state of the format before scenes could be added
    with tarfile.open(archive) as src, tarfile.open(older, "w:gz") as tar:
        for m in src.getmembers():
            data = src.extractfile(m).read()
            if m.name == grid.STATE_PARAMS:
                made = json.loads(data)
                made.pop("scenes")
                data = json.dumps(made).encode()
                m.size = len(data)
            import io
            tar.addfile(m, io.BytesIO(data))
    with pytest.raises(SystemExit, match="older format"):
        grid.restore_state(older, tmp_path / "more")



def test_a_grid_over_part_of_a_state_reads_that_part_and_hands_on_the_rest(tmp_path, capsys):
    """Table 1's report from a state that holds Table 3's runs too (``--methods gca neuma nclaw``), or a machine that
    finishes two scenes (``--scenes ball``): only the grid's runs are unpacked where the grid reads (the report, the
    dispatcher); the rest waits in CARRIED, and a state saved from the subset holds all of it, so a full grid restored
    from that has every run back (nothing is lost by working on part of a state). Records of other runs stay out."""
    work = tmp_path / "w"
    params = grid.grid_params("ci", ["ball", "cat"], ["nclaw", "gca"], [])
    grid.prepare(work, params)
    files = [".grid/train@ball:nclaw.done", ".grid/evaluate@ball:gca.done", ".grid/train@ball:gca@seed1.done",
             "runs/ball/gca/train.json", "runs/ball/gca@seed1/law.pt", "runs/ball/nclaw/train.json",
             "runs/ball/velocity@seed1.json", "metrics/eval/ball/gca.json", "metrics/eval/ball/nclaw.json",
             ".grid/train@cat:nclaw.done", "runs/cat/nclaw/train.json", "metrics/eval/cat/nclaw.json"]
    _write(work, files)
    archive = tmp_path / "state.tgz"
    grid.save_state(work, archive)
    part = tmp_path / "part"  # ball's NCLaw only
    grid.prepare(part, grid.grid_params("ci", ["ball"], ["nclaw"], []))
    assert grid.restore_state(archive, part) == 5  # its 3 run files, the launch estimate and the state's record
    assert grid.state_files(part) == sorted([".grid/train@ball:nclaw.done", "runs/ball/nclaw/train.json",
                                             "runs/ball/velocity@seed1.json", "metrics/eval/ball/nclaw.json"])
    assert "kept aside" in capsys.readouterr().out
    assert not (part / "runs/cat").exists() and not (part / "metrics/eval/ball/gca.json").exists()
    (part / "metrics/eval/ball/nclaw@seed1.json").write_text("{}")  # the subset's own new work
    again = tmp_path / "again.tgz"
    grid.save_state(part, again)
    whole = tmp_path / "whole"
    grid.prepare(whole, params)
    assert grid.restore_state(again, whole) == len(files) + 2
    assert sorted(grid.state_files(whole)) == sorted([*files, "metrics/eval/ball/nclaw@seed1.json"])
    assert not (whole / grid.CARRIED).exists()
    with tarfile.open(again) as tar:
        made = json.loads(tar.extractfile(grid.STATE_PARAMS).read())
        assert len(tar.getnames()) == len(set(tar.getnames()))  # no member twice
    assert made["methods"] == {"ball": ["nclaw", "gca"], "cat": ["nclaw", "gca"]} and set(made["scenes"]) == {"ball", "cat"}
    records = tmp_path / "records.tgz"  # histories of both scenes: the part takes ball's NCLaw's only
    _write(tmp_path / "r", ["runs/ball/nclaw/history.json", "runs/ball/gca/history.json", "runs/cat/nclaw/history.json"])
    with tarfile.open(records, "w:gz") as tar:
        tar.add(tmp_path / "r/runs", arcname="runs")
    assert grid.unpack_records(records, part) == 1 and (part / "runs/ball/nclaw/history.json").is_file()



def test_a_part_restored_again_or_grown_back_hands_on_nothing_stale(tmp_path):
    """Review of session 25: a second restore replaces the first's carried files (a newer state's re-evaluation is
    handed on, not the old one); a grid that grew back to a carried method made its runs again, and its save hands
    on its own files, not the carried copies; a scene without methods (calibration) the grid lacks keeps its marker
    and its definition in the saved state."""
    work = tmp_path / "w"
    params = grid.grid_params("ci", ["ball"], ["nclaw", "gca"], [])
    grid.prepare(work, params)
    _write(work, [".grid/train@ball:gca.done", "runs/ball/gca/law.pt", "metrics/eval/ball/nclaw.json"])
    _write(work, ["metrics/eval/ball/gca.json"], "old")
    old, new = tmp_path / "old.tgz", tmp_path / "new.tgz"
    grid.save_state(work, old)
    (work / "metrics/eval/ball/gca.json").write_text("re-evaluated")
    grid.save_state(work, new)
    part = tmp_path / "part"
    grid.prepare(part, grid.grid_params("ci", ["ball"], ["nclaw"], []))
    grid.restore_state(old, part)
    grid.restore_state(new, part)
    again = tmp_path / "again.tgz"
    grid.save_state(part, again)
    with tarfile.open(again) as tar:
        assert tar.extractfile("metrics/eval/ball/gca.json").read() == b"re-evaluated"
    grid.prepare(part, params)  # the same folder grown back to gca: it trained gca again (a new law, no evaluation)
    (part / "runs/ball/gca").mkdir(parents=True)
    (part / "runs/ball/gca/law.pt").write_text("NEW")
    grown = tmp_path / "grown.tgz"
    grid.save_state(part, grown)
    with tarfile.open(grown) as tar:
        names = tar.getnames()
        assert tar.extractfile("runs/ball/gca/law.pt").read() == b"NEW" and "metrics/eval/ball/gca.json" not in names
    calib = tmp_path / "calib"
    grid.prepare(calib, grid.grid_params("ci", ["ball", "calib_torus"], ["nclaw"], []))
    _write(calib, [".grid/evaluate@calib_torus.done", ".grid/train@ball:nclaw.done"])
    both = tmp_path / "both.tgz"
    grid.save_state(calib, both)
    ball = tmp_path / "ball"
    grid.prepare(ball, grid.grid_params("ci", ["ball"], ["nclaw"], []))
    grid.restore_state(both, ball)
    assert not (ball / ".grid/evaluate@calib_torus.done").exists()
    handed = tmp_path / "handed.tgz"
    grid.save_state(ball, handed)
    with tarfile.open(handed) as tar:
        made = json.loads(tar.extractfile(grid.STATE_PARAMS).read())
        assert ".grid/evaluate@calib_torus.done" in tar.getnames() and "calib_torus" in made["scenes"]

def test_member_in_names_each_state_file_by_its_scene_and_method():
    methods = {"ball": ["gca", "nclaw"]}
    for name, ours in [(".grid/train@ball:gca@seed2.done", True), (".grid/evaluate@ball:neuma.done", False),
                       (".grid/evaluate@calib_torus.done", False), (".grid/evaluate@ball.done", True),
                       (".grid/train@ball:gca@seed1+nclaw@seed1.done", True),
                       (".grid/train@ball:gca@seed1+neuma@seed1.done", False), (".grid/train@cat:gca.done", False),
                       ("runs/ball/velocity@seed1.json", True), ("runs/cat/velocity.json", False),
                       ("runs/ball/no_rdga@seed1/law.pt", False), ("runs/ball/gca/law.pt", True),
                       ("metrics/eval/ball/nclaw@seed2.json", True), ("metrics/eval/ball/neuma.json", False),
                       ("metrics/eval/ball/gca@seed1/strip.png", True), (grid.STATE_PARAMS, True), ("params.yaml", True)]:
        assert grid.member_in(name, methods) is ours, name

def test_grid_main_goes_on_from_a_restored_state(tmp_path, monkeypatch):
    """The command line: a second work directory restored from the first's state runs only what is left (the
    finished scene's inputs not remade) and saves its own state at the end."""
    seen = []

    def fake_run(jobs, engine, work, log, deadline, job_env=None, stamp="", **machine):
        seen.append(sorted(n for n in jobs if not grid.dispatch.is_done(work, n)))
        return {n: "done" for n in jobs}
    monkeypatch.setattr(grid.dispatch, "run", fake_run)
    argv = ["--scenes", "ball", "--methods", "gca", "nclaw", "--profile", "ci", "--stages", "assets", "particles",
            "ground_truth", "preprocess", "train", "evaluate"]
    first, second = tmp_path / "a", tmp_path / "b"
    grid.main(["--work", str(first), *argv])
    assert "inputs@ball" in seen[0] and "evaluate@ball:gca" in seen[0]  # assets to preprocess: one chain job
    _write(first, [".grid/train@ball:nclaw.done", ".grid/train@ball:gca.done", ".grid/evaluate@ball:gca.done",
                   ".grid/evaluate@ball:nclaw.done",
                   "runs/ball/gca/train.json", "metrics/eval/ball/gca.json"])
    archive = tmp_path / "state.tgz"
    grid.main(["--work", str(first), *argv, "--save-state", str(archive)])
    grid.main(["--work", str(second), *argv, "--restore-state", str(archive), "--save-state", str(tmp_path / "b.tgz")])
    assert seen[-1] == []  # everything done elsewhere: not even the inputs run
    assert (second / "metrics/eval/ball/gca.json").is_file() and (tmp_path / "b.tgz").is_file()
    (second / ".grid/train@ball:gca.done").unlink()  # negative control: a run left remakes its inputs
    grid.main(["--work", str(second), *argv])
    assert seen[-1] == ["inputs@ball", "train@ball:gca"]


def _bundle_env(**more) -> dict:
    """table_bundle.sh's environment for its CPU twin at the CI profile (ball, NCLaw, two seeds, two slots)."""
    import os

    return {**os.environ, "PROFILE": "ci", "PRIORS": "", "SCENES": "ball", "METHODS": "nclaw", "SEEDS": "[0,1]",
            "SLOTS": "2", "LIMIT": "590", **more}


@pytest.fixture(scope="module")
def nclaw_bundle(tmp_path_factory):
    """One table_bundle.sh call (DETACH=0) that runs the CI grid of ball x NCLaw x two seeds from nothing: its stdout
    and its state.tgz (shared by the bundle tests: each such call costs ~65 s of CI)."""
    import subprocess

    root = tmp_path_factory.mktemp("nclaw_bundle")
    first = subprocess.run(["sh", "benchmarks/table_bundle.sh"], cwd=ROOT, capture_output=True, text=True, timeout=600,
                           env=_bundle_env(STATE=str(root / "none.tgz"), W=str(root / "a"), OUT=str(root / "out_a"),
                                           DETACH="0"))
    subprocess.run(["tar", "xzf", str(root / "out_a/all.tgz"), "state.tgz"], cwd=root, check=True)
    return first, root / "state.tgz"


def test_table_bundle_goes_on_from_its_state_on_another_machine(tmp_path, nclaw_bundle):
    """benchmarks/table_bundle.sh, the GPU path's CPU twin at the CI profile: a first call runs the grid and returns
    its state in all.tgz (``tar xzf all.tgz state.tgz`` finds it); a call on "another machine" (a fresh work
    folder) restores it and remakes no input, only the report; the table is there."""
    import subprocess

    first, state = nclaw_bundle
    assert "nothing left to run" in first.stdout and "cut off" not in first.stdout, first.stdout + first.stderr
    second = subprocess.run(["sh", "benchmarks/table_bundle.sh"], cwd=ROOT, capture_output=True, text=True, timeout=600,
                            env=_bundle_env(STATE=str(state), W=str(tmp_path / "b"), OUT=str(tmp_path / "out_b")))
    assert "state files restored" in second.stdout and "nothing left to run" in second.stdout, second.stdout
    assert "done  report" in second.stdout and "done  inputs@ball" not in second.stdout
    assert not (tmp_path / "b/grid/data").exists()  # no input remade
    assert (tmp_path / "b/grid/runs/ball/nclaw@seed1/train.json").is_file()
    assert any((tmp_path / "b/grid/reports/ci").glob("table1*"))


def _end_session(pid_file: Path) -> None:
    """Signal every process of the process session that ``pid_file``'s process leads (a detached grid, its
    ``timeout`` and its jobs), so a failed test leaves none running."""
    import os
    import signal

    try:
        sid = int(pid_file.read_text())
    except (OSError, ValueError):
        return
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid:  # after ") ": state, ppid, pgrp, session
            with contextlib.suppress(OSError):
                os.kill(int(stat.parent.name), signal.SIGKILL)


def test_table_bundle_keeps_one_grid_across_calls_of_a_machine(tmp_path, nclaw_bundle):
    """DETACH=1 (the GPU machine's default, session 26), on a state with NCLaw's runs done: the first call starts the
    machine's grid in a process session of its own (it outlives the call) and returns at its LIMIT with a snapshot of
    it that holds the restored runs; the next call starts no second grid but waits on the same one and returns its
    final state with GCA's runs. A grid that ended and whose final state no call returned gives it again and starts
    nothing; once returned, a further call starts a new grid (negative controls of the liveness check)."""
    import subprocess

    env = _bundle_env(METHODS="nclaw gca", STATE=str(nclaw_bundle[1]), W=str(tmp_path / "a"), DETACH="1",
                      MACHINE_S="1200")  # on the state of an earlier machine: NCLaw's runs

    def call(limit: int, out: str, **more):
        return subprocess.run(["sh", "benchmarks/table_bundle.sh"], cwd=ROOT, capture_output=True, text=True,
                              timeout=600, env={**env, "LIMIT": str(limit), "OUT": str(tmp_path / out), **more})

    def names(archive: Path) -> list[str]:
        with tarfile.open(archive) as tar:
            tar.extract("state.tgz", archive.parent / "x")
        with tarfile.open(archive.parent / "x/state.tgz") as tar:
            return tar.getnames()

    pid = tmp_path / "a/grid.pid"
    try:
        first = call(75, "o1")  # returns after LIMIT - 45 s, GCA still training
        assert "grid started" in first.stdout and "this call returns a snapshot" in first.stdout, first.stdout
        snap = names(tmp_path / "o1/all.tgz")
        assert "runs/ball/nclaw@seed1/train.json" in snap and ".grid/evaluate@ball:gca@seed1.done" not in snap
        assert all(grid.STATE_RE.match(n) for n in snap if n != grid.STATE_PARAMS)
        second = call(590, "o2")
        assert "grid goes on (pid" in second.stdout and "grid started" not in second.stdout, second.stdout
        assert "grid rc=0 (the machine's grid has ended" in second.stdout and "nothing left to run" in second.stdout
        assert (tmp_path / "a/grid.log").read_text().count("through local") == 1  # one grid over both calls
        assert ".grid/evaluate@ball:gca@seed1.done" in names(tmp_path / "o2/all.tgz")
        (tmp_path / "a/final/delivered").unlink()  # as if the grid ended after the last call's wait
        third = call(60, "o3")
        assert "its final state (again" in third.stdout and "grid started" not in third.stdout, third.stdout
        assert ".grid/evaluate@ball:gca@seed1.done" in names(tmp_path / "o3/all.tgz")
        fourth = call(60, "o4")  # returned: a new grid (it finds nothing left)
        assert "grid started" in fourth.stdout, fourth.stdout
    finally:
        _end_session(pid)


def test_table_bundle_starts_no_run_the_machine_would_cut_off(tmp_path):
    """MACHINE_S (on the GPU machine: its 30-min lease): with less left than a run's expected time, the bundle's grid
    makes the inputs but starts no training (a run cut off by the machine resumes on no other) and says what is left
    to do; the first call writes the machine's start beside the work folder."""
    import os
    import subprocess

    env = {**os.environ, "PROFILE": "ci", "PRIORS": "", "SCENES": "ball", "METHODS": "nclaw", "SEEDS": "[0]",
           "SLOTS": "2", "LIMIT": "590", "STATE": str(tmp_path / "none.tgz"), "MACHINE_S": "100",
           "W": str(tmp_path / "a"), "OUT": str(tmp_path / "out")}
    call = subprocess.run(["sh", "benchmarks/table_bundle.sh"], cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env=env)
    log = (tmp_path / "a/grid/.grid/grid.log").read_text()
    assert "done  inputs@ball" in log and "start train@" not in log, call.stdout + log  # the chain, assets to preprocess
    assert "'todo': 3" in log and "run the same command again" in log  # train, evaluate, report
    assert (tmp_path / "a/machine_start").is_file()


def test_table_bundle_saves_the_state_of_a_grid_cut_off_by_its_timeout(tmp_path):
    """A grid the bundle's timeout cuts off (session 19: a deadline stop held past it, twice, and both H100 calls came
    back without a state) still returns its state: the bundle saves it from what is on disk. A grid that hangs in
    its --before step stands in for the late stop; its state then restores on another machine."""
    import os
    import subprocess

    hang = tmp_path / "hang.sh"
    hang.write_text("#!/bin/sh\nsleep 100\n")
    hang.chmod(0o755)
    env = {**os.environ, "PROFILE": "ci", "PRIORS": "", "SCENES": "ball", "METHODS": "params", "SEEDS": "[0,1]",
           "SLOTS": "2", "LIMIT": "45", "STATE": str(tmp_path / "none.tgz"), "W": str(tmp_path / "a"),
           "OUT": str(tmp_path / "out"), "EXTRA": f"--before {hang}"}
    cut = subprocess.run(["sh", "benchmarks/table_bundle.sh"], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env=env)
    assert "grid rc=124" in cut.stdout and "the grid was cut off before its state: saved" in cut.stdout, cut.stdout
    subprocess.run(["tar", "xzf", str(tmp_path / "out/all.tgz"), "state.tgz"], cwd=tmp_path, check=True)
    assert grid.restore_state(tmp_path / "state.tgz", tmp_path / "a" / "grid") >= 0  # a valid state of this grid
    with tarfile.open(tmp_path / "state.tgz") as tar:  # METHODS=params: ball's own methods in params.yaml
        made = json.loads(tar.extractfile(grid.STATE_PARAMS).read())
    assert made["methods"]["ball"] == yaml.safe_load((ROOT / "params.yaml").read_text())["scenes"]["ball"]["methods"]
    # (negative control, in the test above: a grid that ends by itself saves its own state, and the bundle does not)


def test_the_grid_tells_its_runs_how_they_share_the_gpu(tmp_path, monkeypatch):
    """Each job's environment names the grid's slots per GPU and whether MPS runs (train.json records them: Table 4
    says when its times are packed); one slot reads as alone."""
    seen = []

    def fake_run(jobs, engine, work, log, deadline, job_env=None, stamp="", **machine):
        seen.append(dict(job_env(None, 0)))
        return {n: "done" for n in jobs}
    monkeypatch.setattr(grid.dispatch, "run", fake_run)
    argv = ["--scenes", "ball", "--methods", "nclaw", "--profile", "ci", "--stages", "assets"]
    grid.main(["--work", str(tmp_path / "a"), *argv, "--slots", "8"])
    grid.main(["--work", str(tmp_path / "b"), *argv, "--slots", "1"])
    assert (seen[0]["GCA_RUNS_PER_GPU"], seen[0]["GCA_MPS"]) == ("8", "0")  # --mps not asked
    assert seen[1]["GCA_RUNS_PER_GPU"] == "1"


def _table1_steps() -> dict[str, int]:
    """MPM steps per rollout of Table 1's scenes at the paper profile (what :func:`grid.scene_steps` reads there)."""
    return {"ball": 800, "duck": 800, "pawn": 400, "cat": 400, "fish": 500, "bottle": 500}


def test_the_lighter_units_jobs_start_below_normal_and_the_heaviest_and_the_inputs_at_normal():
    """Session 47: the table ends with its heaviest runs (ball and duck: 800 steps) alone on a part-empty GPU; at
    MPS's below-normal priority for the lighter (scene, seed) units' jobs the GPU serves the heaviest first. One
    priority a unit (its NCLaw fit and every method alike: Table 4's pairs stay comparable); inputs never go below."""
    steps = _table1_steps()
    left = [f"train@{s}:{m}" for s in steps for m in ("nclaw", "neuma", "gca")]
    jobs = [*left, *(n.replace("train@", "evaluate@") for n in left), "assets@pawn", "report"]
    works = grid.unit_work(jobs, steps)
    low = {n for n in jobs if grid.below_normal(n, works, left)}
    assert low == {f"{stage}@{s}:{m}" for stage in ("train", "evaluate") for s in ("pawn", "cat", "fish", "bottle")
                   for m in ("nclaw", "neuma", "gca")}
    assert works == {"ball@seed0": 3600.0, "duck@seed0": 3600.0, "pawn@seed0": 1800.0,
                                           "cat@seed0": 1800.0, "fish@seed0": 2250.0, "bottle@seed0": 2250.0}
    assert grid.run_work("train@ball:gca", steps) == 4.5 * 800 and grid.run_work("train@pawn:nclaw", steps) is None
    assert grid.run_work("train@pawn:neuma@seed1+gca@seed1", steps) == (4.0 + 4.5) * 400  # a batch: its runs' sum
    assert grid.run_work("train@capture1:gca", steps) == 4.5 * 800  # a scene without steps: the largest
    seeds = ["train@pawn:gca@seed1", "train@ball:gca@seed1"]  # seed 1's units beside seed 0's
    both = grid.unit_work([*jobs, *seeds], steps)
    assert grid.below_normal("evaluate@pawn:nclaw@seed1", both, [*left, *seeds])
    assert not grid.below_normal("train@ball:nclaw@seed1", both, [*left, *seeds])
    # once the heaviest are done, what is left decides: fish's 2250 x 0.75 = 1687.5 < the pawn's 1800, all normal
    rest = [n for n in left if "@ball" not in n and "@duck" not in n]
    assert not any(grid.below_normal(n, works, rest) for n in jobs)
    assert not any(grid.below_normal(n, works, left, share=0.0) for n in jobs)
    assert not grid.below_normal("evaluate@ball:gca", works, [])  # nothing left to yield to
    alone = grid.unit_work(["train@pawn:nclaw"], steps)  # NCLaw alone: no work
    assert alone == {} and not grid.below_normal("train@pawn:nclaw", alone, left)
    assert grid.trains_any("train@ball:gca") and not grid.trains_any("train@ball:nclaw")
    assert grid.trains_any("train@ball:nclaw@seed1+gca@seed1") and grid.trains_any("assets@ball")


def test_a_priority_calls_times_teach_no_estimate(tmp_path):
    """Review, session 47: a run timed in a call that gave MPS priorities is no equal share of its GPU (a below-normal
    run slower, a normal one beside it faster), so ``--machine-left``'s estimates leave it out, and so a run stopped
    and resumed at another priority ("mixed", ``gca.pipeline.train.merged_sharing``); the same record without the
    field counts (negative control)."""
    for scene, priority in (("ball", "normal"), ("pawn", None), ("cat", "below_normal"), ("duck", "mixed")):
        _write(tmp_path, [f"runs/{scene}/gca/train.json"])
        record = {"status": "ok", "train_seconds": 100.0, **({"mps_priority": priority} if priority else {})}
        (tmp_path / f"runs/{scene}/gca/train.json").write_text(json.dumps(record))
    assert grid.finished_train_seconds(tmp_path) == {"gca": {"pawn": 100.0}}


def test_the_grid_starts_its_lighter_runs_below_normal_under_mps_only(tmp_path, monkeypatch):
    """The command line: under MPS each job's environment carries CUDA's client priority as :func:`grid.below_normal`
    says, and the log names each such job; ``--no-mps-priority``, ``--machine-left`` (its lease check counts equal
    shares) and no MPS leave every job at normal (negative controls). The runs' records say which they were."""
    seen: dict[str, dict] = {}

    machine = {}

    def fake_run(jobs, engine, work, log, deadline, job_env=None, stamp="", **kw):
        machine.update(kw)
        for name, job in jobs.items():
            seen[name] = dict(job_env(job, 0))
        return {n: "done" for n in jobs}

    @contextlib.contextmanager
    def fake_mps(enable, log):
        yield enable
    monkeypatch.setattr(grid.dispatch, "run", fake_run)
    monkeypatch.setattr(grid, "mps_daemon", fake_mps)
    argv = ["--scenes", "ball", "pawn", "--methods", "nclaw", "gca", "--profile", "paper", "--stages", "train",
            "evaluate", "--gpus", "0", "--slots", "4"]
    prio = "CUDA_MPS_CLIENT_PRIORITY"
    pawn = {f"{stage}@pawn:{m}" for stage in ("train", "evaluate") for m in ("nclaw", "gca")}
    for extra, expect_low in ((["--mps"], pawn), (["--mps", "--no-mps-priority"], set()),
                              (["--mps", "--machine-left", "3000"], set()), ([], set())):
        seen.clear()
        grid.main(["--work", str(tmp_path / "w"), *argv, *extra])
        assert {n for n, env in seen.items() if env.get(prio) == "1"} == expect_low, extra
        assert all(prio not in env for n, env in seen.items() if n not in expect_low)
        assert {n for n, env in seen.items() if env.get("GCA_MPS") == "1"} == (set(seen) if "--mps" in extra else set())
        assert {n for n, env in seen.items() if env.get("GCA_MPS_PRIORITY") == "1"} == (set(seen) if expect_low else set())
        assert (machine["may_wait"] is None) == ("--machine-left" in extra)  # a lease keeps the reservation whole
    log = (tmp_path / "w" / ".grid" / "grid.log").read_text()
    assert "prio  train@pawn:gca: below normal" in log and "prio  train@ball:gca" not in log
    assert "every job at normal priority: --machine-left" in log
    # the ball's training done: the pawn is the heaviest left, and nothing goes below (the markers are read)
    for m in ("nclaw", "gca"):
        (tmp_path / "w" / ".grid" / f"train@ball:{m}.done").write_text("done\n")
    seen.clear()
    grid.main(["--work", str(tmp_path / "w"), *argv, "--mps"])
    assert not any(env.get(prio) == "1" for env in seen.values())
