"""Fault injection (issue 24 item 7): a stage killed with SIGTERM or SIGKILL while it writes its output, then
run again, leaves no partial output and no litter, and ends with the same outputs as an uninterrupted run.

The stage is ``assets`` at the CI profile (a few seconds of work: its output folder is written atomically,
then its metrics JSON). Each kill is aimed at the moment the output's temporary folder exists (polled), so
it lands inside the write every time; three stage runs after the reference one bound the test's time.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _params(folder: Path) -> Path:
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    path = folder / "params.yaml"  # the sections the stage reads (so loading validates only those)
    path.write_text(yaml.safe_dump({"profile": "ci", "objects": {"ball": raw["objects"]["ball"]}}, sort_keys=False))
    return path


def _command(work: Path) -> list[str]:
    return [sys.executable, str(ROOT / "stages" / "assets.py"), "--object", "ball", "--out", "data/assets/ball",
            "--metrics", "metrics/assets/ball.json", "--params", "params.yaml"]


def _env(work: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("DVC_STAGE", "DVC_ROOT")}
    env["MLFLOW_TRACKING_URI"] = f"sqlite:///{work / 'mlflow.db'}"
    env["CI"] = "true"
    return env


def _run(work: Path) -> subprocess.CompletedProcess:
    return subprocess.run(_command(work), cwd=work, env=_env(work), capture_output=True, text=True, timeout=300)


def _interrupt(work: Path, sig: int) -> subprocess.CompletedProcess:
    """Start the stage and send ``sig`` once its output's temporary folder exists."""
    proc = subprocess.Popen(_command(work), cwd=work, env=_env(work), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    parent, deadline = work / "data" / "assets", time.monotonic() + 240
    while proc.poll() is None and time.monotonic() < deadline:
        if parent.is_dir() and any(p.name.startswith(".ball.tmp") for p in parent.iterdir()):
            proc.send_signal(sig)
            break
        time.sleep(0.02)
    out, err = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _tree(work: Path) -> dict[str, bytes]:
    return {str(p.relative_to(work)): p.read_bytes() for p in sorted((work / "data").rglob("*")) if p.is_file()} | \
        {str(p.relative_to(work)): p.read_bytes() for p in sorted((work / "metrics").rglob("*")) if p.is_file()}


def _hidden(work: Path) -> list[str]:
    return [str(p.relative_to(work)) for root in ("data", "metrics") if (work / root).exists()
            for p in (work / root).rglob(".*")]


def test_killed_stage_reruns_to_the_same_outputs_without_litter(tmp_path):
    reference, work = tmp_path / "reference", tmp_path / "work"
    for folder in (reference, work):
        folder.mkdir()
        _params(folder)
    done = _run(reference)
    assert done.returncode == 0, done.stderr
    expected = _tree(reference)
    assert sorted(expected) == ["data/assets/ball/gaussians.ply", "data/assets/ball/mesh.ply",
                                "data/assets/ball/preview.png", "metrics/assets/ball.json"]

    stopped = _interrupt(work, signal.SIGTERM)  # a clean stop: exit 143, nothing half-written, no litter
    assert stopped.returncode == 143, stopped.stderr
    assert stopped.stderr.strip().splitlines()[-1] == "assets: stopped by SIGTERM"
    assert _hidden(work) == [] and not (work / "data" / "assets" / "ball").exists()

    killed = _interrupt(work, signal.SIGKILL)  # no chance to clean: the temporary folder stays behind
    assert killed.returncode == -signal.SIGKILL
    litter = _hidden(work)
    assert litter and all(Path(p).name.startswith(".ball.tmp") for p in litter), litter
    assert not (work / "data" / "assets" / "ball").exists()

    again = _run(work)  # the re-run sweeps the litter (and says so) and writes the same outputs
    assert again.returncode == 0, again.stderr
    for path in litter:
        assert f"assets: removed the stale temporary {path} (an earlier run was killed)" in again.stderr, again.stderr
    assert _hidden(work) == []
    assert _tree(work) == expected
