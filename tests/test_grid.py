"""gca/pipeline/grid.py: the dvc.yaml stages expanded for a scene grid, ordered by deps/outs, scheduled."""

import argparse
import tarfile
import time
from pathlib import Path

import pytest
import yaml

from gca.pipeline import grid

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def jobs():
    params = grid.grid_params("ci", ["ball", "cat"], ["gca", "nclaw"], ["train.iterations=3"])
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    return params, grid.link(grid.split_train(grid.expand(dvc, params, ["assets", "particles", "prior", "ground_truth",
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
    assert {"assets@ball", "assets@cat", "prior@jelly", "prior@plasticine", "ground_truth@cat", "evaluate@ball",
            "report", "train@ball:nclaw", "train@ball:gca"} <= set(jobs)
    assert "prior@sand" not in jobs and "train@ball" not in jobs
    assert jobs["report"].cmd.split("--out ")[1].startswith("reports/ci ")
    assert jobs["assets@cat"].cmd.startswith("python stages/assets.py --object cat --out data/assets/cat")
    gca = jobs["train@ball:gca"]
    assert gca.cmd.endswith("--methods gca --velocity runs/ball/velocity.json")
    assert jobs["train@ball:nclaw"].cmd.endswith("--methods nclaw")  # the cheap one estimates the velocity


def test_seeds_split_training_into_one_job_per_run():
    params = grid.grid_params("ci", ["ball"], ["gca", "nclaw"], ["train.seeds=[0,2]"])
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    jobs = grid.link(grid.split_train(grid.expand(dvc, params, ["train", "evaluate"]), params))
    train = {n: j for n, j in jobs.items() if n.startswith("train@")}
    assert set(train) == {"train@ball:nclaw", "train@ball:gca", "train@ball:gca@seed2"}  # nclaw: one seed
    assert train["train@ball:gca@seed2"].cmd.endswith("--methods gca --seeds 2 --velocity runs/ball/velocity.json")
    assert train["train@ball:gca@seed2"].outs == ["runs/ball/gca@seed2"]
    assert train["train@ball:nclaw"].cmd.endswith("--methods nclaw --seeds 0")  # it estimates the velocity
    assert set(train) <= jobs["evaluate@ball"].after


def test_order_follows_deps_and_outs(jobs):
    _, jobs = jobs
    assert {"train@ball:nclaw", "prior@jelly", "ground_truth@ball", "preprocess@ball", "particles@ball",
            "assets@ball"} <= jobs["train@ball:gca"].after
    assert "prior@plasticine" not in jobs["train@ball:gca"].after
    assert {"train@cat:gca", "train@cat:nclaw"} <= jobs["evaluate@cat"].after
    assert {"evaluate@ball", "evaluate@cat"} <= jobs["report"].after
    prio = grid.critical_path(jobs)
    assert prio["prior@jelly"] > prio["train@ball:gca"] > prio["evaluate@ball"] > prio["report"] > 0


def _fake(name, code, after=()):
    return grid.Job(name, f"python -c {code!r}", [], [], 0.01, set(after))


def test_scheduler_skips_dependents_of_a_failure_and_resumes(tmp_path):
    (tmp_path / ".grid").mkdir()
    jobs = {"a": _fake("a", "open('a.txt','w').write('1')"), "bad": _fake("bad", "raise SystemExit(3)"),
            "b": _fake("b", "open('b.txt','w').write(open('a.txt').read())", ["a"]),
            "c": _fake("c", "print('never')", ["bad"]), "d": _fake("d", "print('never')", ["c", "b"])}
    lines = []
    state = grid.Scheduler(jobs, tmp_path, gpus=2, slots=1, deadline=None, log=lines.append).run()
    assert state == {"a": "done", "bad": "failed", "b": "done", "c": "skipped", "d": "skipped"}
    assert (tmp_path / "b.txt").read_text() == "1"
    assert any("FAIL  bad (exit 3)" in line for line in lines)
    (tmp_path / "a.txt").unlink()
    again = grid.Scheduler({k: v for k, v in jobs.items() if k in "ab"}, tmp_path, 1, 1, None, lines.append)
    assert again.state == {"a": "done", "b": "done"} and again.run() == {"a": "done", "b": "done"}
    assert not (tmp_path / "a.txt").exists()  # a finished job is not run again


def test_gpus_by_id_pins_jobs_to_those_gpus_only(tmp_path):
    (tmp_path / ".grid").mkdir()
    code = "import os; open({!r}, 'w').write(os.environ['CUDA_VISIBLE_DEVICES'])"
    jobs = {n: grid.Job(n, f"python -c {code.format(n + '.gpu')!r}", [], [], 0.01) for n in "abcd"}
    assert grid.gpu_ids("2,3") == [2, 3] and grid.gpu_ids("4") == 4 and grid.gpu_ids("0,") == [0]
    with pytest.raises(argparse.ArgumentTypeError, match="comma-separated"):
        grid.gpu_ids("1;2")
    state = grid.Scheduler(jobs, tmp_path, gpus=[2, 3], slots=1, deadline=None, log=lambda m: None).run()
    assert set(state.values()) == {"done"}
    assert {(tmp_path / f"{n}.gpu").read_text() for n in "abcd"} == {"2", "3"}


def test_deadline_launches_nothing_that_would_end_late(tmp_path):
    (tmp_path / ".grid").mkdir()
    slow = grid.Job("slow", "python -c pass", [], [], cost=10.0)  # 10 estimated minutes
    state = grid.Scheduler({"slow": slow}, tmp_path, 1, 1, deadline=60.0, log=lambda m: None).run()
    assert state == {"slow": "todo"}


def test_deadline_stops_running_jobs_and_the_next_command_resumes(tmp_path, monkeypatch):
    """A training job (resumable) is launched with less than its cost left, stopped at the deadline
    and left to do; the next command runs it again, which resumes where it left off."""
    (tmp_path / ".grid").mkdir()
    (tmp_path / "fake_train.py").write_text(
        "import os, time\nn = int(open('ckpt').read()) if os.path.exists('ckpt') else 0\n"
        "for i in range(n, 6):\n    open('ckpt', 'w').write(str(i + 1))\n    time.sleep(0.5)\n")
    job = grid.Job("train@s:gca", "python fake_train.py", [], [], cost=10.0)
    lines = []
    monkeypatch.setattr(grid, "RESUMABLE_MIN_S", 0.5)
    assert grid.Scheduler({job.name: job}, tmp_path, 1, 1, deadline=1.7, log=lines.append).run() == {job.name: "todo"}
    assert any(line.startswith(f"stop  {job.name} at the deadline") for line in lines)
    stopped_at = int((tmp_path / "ckpt").read_text())
    assert 1 <= stopped_at < 6 and not (tmp_path / ".grid" / f"{job.name}.done").exists()
    assert grid.Scheduler({job.name: job}, tmp_path, 1, 1, None, lines.append).run() == {job.name: "done"}
    assert (tmp_path / "ckpt").read_text() == "6"


def test_deadline_counts_jobs_that_ended_on_their_own_by_exit_status(tmp_path):
    """At the deadline a job that already exited is done (exit 0) or failed (else), never 'stopped'."""
    (tmp_path / ".grid").mkdir()
    jobs = {"train@s:ok": _fake("train@s:ok", "pass"), "train@s:bad": _fake("train@s:bad", "raise SystemExit(3)"),
            "train@s:slow": _fake("train@s:slow", "import time; time.sleep(60)")}
    lines = []
    sched = grid.Scheduler(jobs, tmp_path, 1, 3, deadline=None, log=lines.append)
    for name in jobs:
        sched.places.remove(0)
        sched._launch(name, 0)
    time.sleep(2.0)  # the quick ones end; nothing reaped them yet
    sched._stop_at_deadline()
    assert sched.state == {"train@s:ok": "done", "train@s:bad": "failed", "train@s:slow": "todo"}
    assert sched.places == [0, 0, 0] and not sched.running
    assert (tmp_path / ".grid" / "train@s:ok.done").is_file()
    assert sum(line.startswith("stop  ") for line in lines) == 1


def test_collect_keeps_the_small_results(tmp_path):
    for rel in ("metrics/eval/ball/gca.json", "reports/ci/table1_synthetic_cd.md", "runs/ball/gca/train.json",
                "runs/ball/gca/law.pt", "data/scenes/ball/meta.json", "models/prior/jelly.pt"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x")
    with tarfile.open(grid.collect(tmp_path, tmp_path / "out")) as tar:
        names = set(tar.getnames())
    assert names == {"metrics/eval/ball/gca.json", "reports/ci/table1_synthetic_cd.md", "runs/ball/gca/train.json",
                     "runs/ball/gca/law.pt", "models/prior/jelly.pt"}


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

    def fake_run(self):
        seen.append(calls.read_text())
        return {}
    monkeypatch.setattr(grid.Scheduler, "run", fake_run)
    grid.main(["--work", str(tmp_path / "w"), "--scenes", "ball", "--methods", "gca", "--profile", "ci",
               "--stages", "assets", "--mps"])
    assert seen == ["args=-d stdin=\n"] and calls.read_text().endswith("args= stdin=quit\n")
