"""The CI smoke pipeline at the CI profile, in a fresh copy of the repository: every stage command of
`dvc.yaml` run through the job engine (`python -m gca.pipeline.grid --repo`: submitit's local executor, two jobs at
once, training split into jobs of a scene's runs), then `dvc commit` of what the jobs wrote.

The copy keeps two scenes (the elastomer ball and the plasticine cat: together they have every method
of every table, so every stage and every method runs) and the objects and priors they need.
Then: the assembling `dvc repro` runs nothing (the jobs wrote where `dvc repro` puts its outputs), DVC's
run cache restores deleted outputs, and changing one object's param invalidates only the stages that
depend on it.
"""

import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCENES = ("ball", "cat")
REPORTS = ["table1_synthetic_cd", "table2_real_to_sim_cd", "table3_ablation_cd", "table4_efficiency",
           "table5_explicit", "table6_ood", "table_law_level"]



def _run(args, cwd, env):
    out = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=3000)
    assert out.returncode == 0, (f"{' '.join(args)} failed:\n{_error_first(out.stderr)}\n"
                                 f"--- stdout tail ---\n{out.stdout[-3000:]}")
    return out.stdout + out.stderr


def _error_first(stderr: str) -> str:
    """A failed stage's traceback first (progress bars dropped), then the rest of stderr's tail: a CI
    log that shows only the start of the message still names the error."""
    stderr = stderr.replace("Traceback (most recent call last):", "\nTraceback (most recent call last):")
    lines = [ln.rsplit("\r", 1)[-1] for ln in stderr.splitlines()]
    lines = [ln for ln in lines if not re.search(r"\d+%\|", ln)]
    start = max((i for i, ln in enumerate(lines) if ln.startswith("Traceback")), default=None)
    trace = "\n".join(lines[start:start + 60]) if start is not None else "(no traceback in stderr)"
    return f"--- last traceback ---\n{trace}\n--- stderr tail ---\n" + "\n".join(lines)[-3000:]


def _copy_repo(dest: Path) -> None:
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split("\n")
    for rel in filter(None, files):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` by relative path (empty when it does not exist)."""
    return {f.relative_to(folder).as_posix(): f.read_bytes() for f in sorted(folder.rglob("*")) if f.is_file()}


def _ci_params(path: Path) -> None:
    raw = yaml.safe_load(path.read_text())
    raw["profile"] = "ci"
    raw["scenes"] = {s: raw["scenes"][s] for s in SCENES}
    raw["objects"] = {raw["scenes"][s]["object"]: raw["objects"][raw["scenes"][s]["object"]] for s in SCENES}
    raw["prior"]["families"] = {raw["scenes"][s]["prior"]: raw["prior"]["families"][raw["scenes"][s]["prior"]]
                                for s in SCENES}
    raw["demo"]["captures"] = {}  # the capture scene is cut with the others (tests/test_capture_e2e.py runs it)
    path.write_text(yaml.safe_dump(raw, sort_keys=False))


@pytest.fixture(scope="module")
def repo(tmp_path_factory):
    dest = tmp_path_factory.mktemp("repo")
    _copy_repo(dest)
    _ci_params(dest / "params.yaml")
    env = {**os.environ, "DVC_NO_ANALYTICS": "1", "MLFLOW_TRACKING_URI": f"sqlite:///{dest / 'mlflow.db'}",
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           "GIT_AUTHOR_NAME": "ci", "GIT_AUTHOR_EMAIL": "ci@localhost", "GIT_COMMITTER_NAME": "ci",
           "GIT_COMMITTER_EMAIL": "ci@localhost"}
    _run(["git", "init", "-q"], dest, env)
    _run(["git", "add", "-A"], dest, env)
    _run(["git", "commit", "-qm", "snapshot"], dest, env)
    # 2 CPU cores: two jobs at once; a scene's 13 training runs in 3 jobs (the velocity one, then 7 + 5)
    log = _run([sys.executable, "-m", "gca.pipeline.grid", "--repo", str(dest), "--engine", "local",
                "--gpus", "0", "--slots", "2", "--runs-per-job", "7", "--commit"], dest, env)
    assembled = _run([sys.executable, "-m", "dvc", "repro"], dest, env)
    return dest, env, log, assembled


def test_engine_runs_every_stage_and_writes_every_report(repo):
    dest, _, log, _ = repo
    # each scene's inputs (assets, particles, ground_truth, preprocess) as one chain job (grid.chain_inputs)
    for job in ["inputs@ball", "inputs@cat", "prior@jelly", "train@ball:nclaw", "evaluate@cat:gca+", "demo", "report"]:
        assert f"done  {job}" in log, log
    commit = next(ln for ln in log.splitlines() if "dvc commit -f " in ln)  # the chains' members, stage by stage
    assert {"assets@ball", "particles@cat", "ground_truth@ball", "preprocess@cat"} <= set(commit.split()), commit
    # the runs after each seed's velocity job go in batches (`--runs-per-job`; which runs share one follows their
    # cost order): every run of the scene is in one done training job
    batches = re.findall(r"done  train@cat:(\S+)", log)
    for method in ("no_global", "gca", "neuma", "gca_full_ft"):
        assert any(method in batch.split("+") for batch in batches), log
    assert "FAIL" not in log and "dvc commit -f " in log
    for name in REPORTS:
        assert (dest / "reports/ci" / f"{name}.md").is_file() and (dest / "reports/ci" / f"{name}.csv").is_file()
    assert (dest / "reports/ci" / "README.md").is_file()
    assert _tree(dest / "reports/paper") == _tree(ROOT / "reports/paper")  # a CI repro leaves paper-scale reports alone
    for scene in SCENES:
        methods = yaml.safe_load((dest / "params.yaml").read_text())["scenes"][scene]["methods"]
        for method in methods:
            record = json.loads((dest / "metrics/eval" / scene / f"{method}.json").read_text())
            # every method trains without diverging at the CI profile (73 of 73 in reports/ci): a divergence
            # here is a regression, not noise
            assert record["status"] == "ok" and record["profile"] == "ci", (scene, method, record["status"])
            assert all(map(math.isfinite, record["chamfer_per_frame"]))


def test_assembling_repro_recomputes_nothing(repo):
    """What the engine's jobs wrote, committed, is what `dvc repro` would have made: it runs no stage."""
    dest, env, _, assembled = repo
    assert "Running stage" not in assembled, assembled
    status = json.loads(_run([sys.executable, "-m", "dvc", "status", "--json"], dest, env).splitlines()[-1])
    assert status == {}, status


def test_run_cache_restores_deleted_outputs_without_running(repo):
    """What another DVC queue worker computed (or `dvc commit` recorded) is restored, not recomputed: the
    prior and the evaluation are run-cached (no plain `cache: false` out) and their files are byte-stable,
    so nothing after them runs again either."""
    dest, env, _, _ = repo
    (dest / "models/prior/jelly.pt").unlink()
    shutil.rmtree(dest / "metrics/eval/ball")
    log = _run([sys.executable, "-m", "dvc", "repro"], dest, env)
    assert "Stage 'prior@jelly' is cached - skipping run" in log, log
    assert "Stage 'evaluate@ball' is cached - skipping run" in log, log
    assert "Running stage" not in log, log
    assert (dest / "metrics/eval/ball/gca.json").is_file()


def test_one_object_param_invalidates_only_its_stages(repo):
    dest, env, _, _ = repo
    params = dest / "params.yaml"
    raw = yaml.safe_load(params.read_text())
    raw["objects"]["ball"]["seed"] += 100
    params.write_text(yaml.safe_dump(raw, sort_keys=False))
    status = json.loads(_run([sys.executable, "-m", "dvc", "status", "--json"], dest, env).splitlines()[-1])
    assert {"assets@ball", "particles@ball"} <= set(status), status
    assert not {"assets@cat", "particles@cat", "prior@jelly", "prior@plasticine"} & set(status), status
