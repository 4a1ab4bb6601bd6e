"""benchmarks/recover_velocities.py: runs of a pre-session-20 state get the launch velocity they trained with (from the
first earlier state holding their train.json), and their evaluations made since with another estimate are dropped."""

from __future__ import annotations

import io
import json
import sys
import tarfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import recover_velocities as rv  # noqa: E402


def _tgz(path: Path, files: dict) -> Path:
    with tarfile.open(path, "w:gz") as tar:
        for name, value in files.items():
            data = json.dumps(value).encode()
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


def test_runs_get_the_velocity_of_the_machine_they_trained_on(tmp_path):
    v = lambda x: {"v0": [x, 0.0, 0.0], "w0": [0.0, 0.0, 0.0]}  # noqa: E731
    m1 = _tgz(tmp_path / "m1.tgz", {"runs/ball/velocity.json": v(1.0), "runs/ball/nclaw/train.json": {}})
    m2 = _tgz(tmp_path / "m2.tgz", {"runs/ball/velocity.json": v(2.0), "runs/ball/nclaw/train.json": {},
                                    "runs/ball/gca/train.json": {}, "runs/ball/velocity@seed1.json": v(5.0),
                                    "runs/ball/gca@seed1/train.json": {"velocity": v(5.0)}})
    state = _tgz(tmp_path / "state.tgz", {
        "runs/ball/velocity.json": v(3.0),  # estimated again on machine 3
        "runs/ball/nclaw/train.json": {}, "runs/ball/gca/train.json": {"status": "ok"},
        "runs/ball/gca@seed1/train.json": {"velocity": v(5.0)},  # recorded since session 20: left alone
        ".grid/evaluate@ball:gca.done": 1, "metrics/eval/ball/gca.json": {"chamfer_mean": 0.1},  # with machine 3's
        ".grid/evaluate@ball:gca@seed1.done": 1})
    assert rv.recover(state, [m1, m2]) == {"ball/gca": "m2.tgz", "ball/nclaw": "m1.tgz"}
    files = rv._members(state)
    gca = json.loads(files["runs/ball/gca/train.json"])
    assert gca["velocity"] == v(2.0) and gca["status"] == "ok"
    assert gca["velocity_recovered_from"] == "m2.tgz:runs/ball/velocity.json"
    assert json.loads(files["runs/ball/nclaw/train.json"])["velocity"] == v(1.0)
    assert ".grid/evaluate@ball:gca.done" not in files and "metrics/eval/ball/gca.json" not in files
    assert ".grid/evaluate@ball:gca@seed1.done" in files  # its own velocity: its evaluation stands
    assert rv.recover(state, [m1, m2]) == {}  # once: nothing left to recover
