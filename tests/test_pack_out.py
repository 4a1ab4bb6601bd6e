"""benchmarks/gpu_wheels.sh pack_out: what a device call returns fits the device's limits (files of at most 16 MiB)."""

import os
import subprocess
from pathlib import Path

WHEELS = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu_wheels.sh"


def _pack(out: Path, part: int | None = None) -> None:
    env = {"PATH": "/usr/bin:/bin"} | ({"PACK_PART": str(part)} if part else {})
    subprocess.run(["sh", "-c", f". {WHEELS}; pack_out {out}"], env=env, check=True)


def test_a_large_output_comes_back_in_parts_with_the_state_beside_them(tmp_path):
    out = tmp_path / "out"
    (out / "metrics/eval/ball").mkdir(parents=True)
    media = os.urandom(300_000)  # incompressible, like the evaluations' gifs
    (out / "metrics/eval/ball/rollout.gif").write_bytes(media)
    (out / "state.tgz").write_bytes(b"state")
    _pack(out, part=100_000)
    names = sorted(p.name for p in out.iterdir())
    assert "all.tgz" not in names and "state.tgz" in names and len(names) >= 4  # 3+ parts of <= 100 kB, and the state
    assert all((out / n).stat().st_size <= 100_000 for n in names)
    whole = tmp_path / "all.tgz"
    whole.write_bytes(b"".join((out / n).read_bytes() for n in names if n.startswith("all.tgz.")))
    subprocess.run(["tar", "xzf", str(whole), "-C", str(tmp_path)], check=True)
    assert (tmp_path / "metrics/eval/ball/rollout.gif").read_bytes() == media  # the parts join back whole
    assert (tmp_path / "state.tgz").read_bytes() == b"state"  # inside too: `tar xzf all.tgz state.tgz` still works


def test_a_small_output_stays_one_archive(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "grid.log").write_text("log")
    _pack(out)
    assert sorted(p.name for p in out.iterdir()) == ["all.tgz"]  # no state made: none beside it
