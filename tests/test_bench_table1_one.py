"""benchmarks/table1_one.sh's PART=start / PART=watch on the CPU, with a stand-in grid module (GRID_MODULE): one grid
run across device calls. Start returns while the grid runs (its stdio on files, so a caller reading the script's
pipes is not held), watch reports it running, then its end (rc, seconds, the log and the collected results), a second
start and a watch without a start are refused."""

import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

FAKE = '''
import os, pathlib, sys, time
args = sys.argv[1:]
work = pathlib.Path(args[args.index("--work") + 1])
if "--collect" in args:
    out = pathlib.Path(args[args.index("--collect") + 1])
    (out / "grid_results.tar.gz").write_bytes(b"collected")
    if "--save-state" in args:
        pathlib.Path(args[args.index("--save-state") + 1]).write_bytes(b"state of " + str(work).encode())
    sys.exit(0)
(work / "argv.txt").write_text("\\n".join(args))
print("[grid 00:00:00] 3 jobs (3 to run) through local", flush=True)
time.sleep(float(os.environ["FAKE_S"]))
print("[grid 00:00:04] done train:ball:gca", flush=True)
sys.exit(int(os.environ.get("FAKE_RC", "0")))
'''


def _run(part: str, tmp: Path, **env) -> subprocess.CompletedProcess:
    e = {**os.environ, "PART": part, "W": str(tmp / "w"), "OUT": str(tmp / "out"), "GRID_MODULE": "fakegrid",
         "PYTHONPATH": f"{tmp}{os.pathsep}{ROOT}", "GCA_COMMIT": "abc1234", "FAKE_S": "4",
         "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", **env}
    return subprocess.run(["sh", "benchmarks/table1_one.sh"], cwd=ROOT, env=e, capture_output=True, text=True,
                          timeout=120)


def test_one_grid_runs_across_calls(tmp_path):
    (tmp_path / "fakegrid.py").write_text(FAKE)
    t = time.monotonic()
    started = _run("start", tmp_path, DEADLINE="1500", GRID_ARGS="--set train.seeds=[0,1,2]", FAKE_S="6")
    assert started.returncode == 0, started.stdout + started.stderr
    assert "grid started in the background" in started.stdout
    assert time.monotonic() - t < 5.5 or not (tmp_path / "w" / "bg.rc").exists()  # returned before the grid ended
    running = _run("watch", tmp_path, WATCH_S="0")
    assert running.returncode == 0 and "grid running:" in running.stdout
    out = tmp_path / "out"  # a running grid's snapshot: a machine lost before its end leaves what had finished
    assert (out / "state.tgz").read_bytes() == b"state of " + str(tmp_path / "w").encode()
    assert (out / "grid_results.tar.gz").read_bytes() == b"collected" and (out / "grid.log").is_file()
    (out / "state.tgz").unlink()
    again = _run("start", tmp_path)
    assert again.returncode == 2 and "started in" in again.stdout  # one grid a work folder
    ended = _run("watch", tmp_path, WATCH_S="60")
    assert ended.returncode == 0, ended.stdout + ended.stderr
    assert "grid ended: rc=0" in ended.stdout and "done train:ball:gca" in ended.stdout
    assert (out / "grid_results.tar.gz").read_bytes() == b"collected"
    assert (out / "state.tgz").is_file()  # taken again at the end (a grid stopped at its deadline goes on from it)
    assert "done train:ball:gca" in (out / "grid.log").read_text()
    assert "grid ended: rc=0" in (out / "timing.txt").read_text()
    argv = (tmp_path / "w" / "argv.txt").read_text().splitlines()
    assert argv[argv.index("--deadline") + 1] == "1500"
    assert argv[argv.index("--set") + 1] == "train.seeds=[0,1,2]"  # GRID_ARGS' words, not globbed


def test_watch_reports_a_failed_grid_and_refuses_without_a_start(tmp_path):
    (tmp_path / "fakegrid.py").write_text(FAKE)
    alone = _run("watch", tmp_path)
    assert alone.returncode == 2 and "no grid started" in alone.stdout
    assert _run("start", tmp_path, FAKE_S="0.5", FAKE_RC="3").returncode == 0
    ended = _run("watch", tmp_path, WATCH_S="60")
    assert "grid ended: rc=3" in ended.stdout


FAKE_PY = '''#!/bin/sh
echo "$*" >> "$CALLS"
case "$1" in benchmarks/harness.py) sleep 1; echo "warm-up ended" >> "$CALLS" ;; esac
'''


def _build(tmp: Path, **env) -> list[str]:
    """PART=build with python3 and nvidia-smi stood in by a script that logs its arguments: the commands it runs."""
    bin_ = tmp / "bin"
    bin_.mkdir()
    for name in ("python3", "nvidia-smi"):
        (bin_ / name).write_text(FAKE_PY)
        (bin_ / name).chmod(0o755)
    e = {**os.environ, "PART": "build", "W": str(tmp / "w"), "OUT": str(tmp / "out"), "CALLS": str(tmp / "calls"),
         "PATH": f"{bin_}{os.pathsep}{os.environ['PATH']}", **env}
    r = subprocess.run(["sh", "benchmarks/table1_one.sh"], cwd=ROOT, env=e, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    return (tmp / "calls").read_text().splitlines()


def test_build_warms_the_kernels_beside_gsplat_unless_told_not_to(tmp_path):
    calls = _build(tmp_path, WARM_ITERS="7")
    assert any("gca.render.backend --build" in c for c in calls)
    warm = [c for c in calls if c.startswith("benchmarks/harness.py")]
    assert len(warm) == 1 and "--scene pawn" in warm[0] and "train.iterations=7" in warm[0]
    assert calls[-1] == "warm-up ended"  # the build waits for the warm-up it started in the background
    (tmp_path / "calls").unlink()
    import shutil
    shutil.rmtree(tmp_path / "bin")
    assert not any(c.startswith("benchmarks/harness.py") for c in _build(tmp_path, WARM_ITERS="0"))  # control
