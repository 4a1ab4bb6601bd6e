"""benchmarks/carry_aside.sh: what the GPU calls do not read leaves the tree before them and comes back whole."""

import subprocess
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "carry_aside.sh"


def _tree(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_text() for p in sorted(root.rglob("*"))
            if p.is_file() and ".git" not in p.relative_to(root).parts and p.suffix != ".whl"}


def test_results_go_aside_and_come_back_whole(tmp_path):
    repo, hold = tmp_path / "repo", tmp_path / "hold"
    for rel in ("benchmarks/results/README.md", "benchmarks/results/priors_paper/jelly.pt",
                "benchmarks/results/table1_seeds/state.tgz", "benchmarks/results/table1_launch/state.tgz",
                "benchmarks/results/table1_launch/records.tgz", "reports/paper/claims.md", "reports/benchmark/ball.gif",
                "benchmarks/results/fast_s11/a.json",
                "benchmarks/results/x.json", "reports/ci/figures/f.png", "reports/ci/table1.md"):
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_text(rel)
    before = _tree(repo)
    run = lambda *a: subprocess.run(["sh", str(SCRIPT), *a], cwd=repo, env={"HOLD": str(hold), "PATH": "/usr/bin:/bin"},
                                    capture_output=True, text=True)  # noqa: E731
    assert run("out").returncode == 0
    assert sorted(_tree(repo)) == ["benchmarks/results/README.md", "benchmarks/results/priors_paper/jelly.pt",
                                   "benchmarks/results/table1_launch/state.tgz", "reports/ci/table1.md"]
    again = run("out")  # a second `out` before `back` would mix two sessions' files: refused
    assert again.returncode == 1 and "run 'back' first" in again.stdout
    assert run("back").returncode == 0 and _tree(repo) == before
    assert run("sideways").returncode == 2


def test_back_keeps_what_was_made_meanwhile(tmp_path):
    """A records.tgz made in the tree between `out` and `back` (session 25: the merge of a session's records) is newer:
    `back` keeps it and leaves the held copy in HOLD, saying so (it used to overwrite it); the rest comes back."""
    repo, hold = tmp_path / "repo", tmp_path / "hold"
    for rel in ("benchmarks/results/table1_launch/state.tgz", "benchmarks/results/table1_launch/records.tgz",
                "benchmarks/results/x.json"):
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_text("old")
    (repo / "reports").mkdir()
    run = lambda *a: subprocess.run(["sh", str(SCRIPT), *a], cwd=repo, env={"HOLD": str(hold), "PATH": "/usr/bin:/bin"},
                                    capture_output=True, text=True)  # noqa: E731
    assert run("out").returncode == 0
    (repo / "benchmarks/results/table1_launch/records.tgz").write_text("new")
    back = run("back")
    assert back.returncode == 0 and "kept benchmarks/results/table1_launch/records.tgz" in back.stdout, back.stdout
    assert (repo / "benchmarks/results/table1_launch/records.tgz").read_text() == "new"
    assert (hold / "launch/records.tgz").read_text() == "old"  # not lost either
    assert (repo / "benchmarks/results/x.json").read_text() == "old"  # the rest came back


def test_lean_also_moves_tests_captures_and_reports_ci_and_says_the_carry(tmp_path):
    """LEAN=1 (table_bundle.sh's calls, which run no pytest): tests/, captures/, reports/ci, NOTES.md and the grid logs
    leave too and come back whole (reports/ci before its figures: they went aside apart); in a git checkout `out` says the carry's size
    against 64 MiB, OVER when the tree and the wheels pass it (session 35: 64.8 MiB, a refused call)."""
    repo, hold = tmp_path / "repo", tmp_path / "hold"
    for rel in ("benchmarks/results/table1_launch/state.tgz", "benchmarks/results/x.json", "tests/test_a.py",
                "captures/example/scan.ply", "reports/ci/figures/f.png", "reports/ci/table1.md", "gca/a.py",
                "benchmarks/NOTES.md", "benchmarks/results/table1_launch/logs/s36.grid.log"):
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_text(rel)
    (repo / ".whl").mkdir()
    (repo / ".whl/big.whl").write_bytes(b"0" * (65 * 2 ** 20))  # untracked here; the size counts it as a carried wheel
    env = {"HOLD": str(hold), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "GIT_CONFIG_NOSYSTEM": "1"}
    subprocess.run(["git", "init", "-q"], cwd=repo, check=True, env=env)
    (repo / ".gitignore").write_text(".whl/\n")
    subprocess.run(["git", "add", "-A"], cwd=repo, check=True, env=env)
    before = _tree(repo)
    run = lambda *a, **e: subprocess.run(["sh", str(SCRIPT), *a], cwd=repo, env={**env, **e}, capture_output=True,
                                         text=True)  # noqa: E731
    out = run("out", LEAN="1")
    assert out.returncode == 0, out.stderr
    assert sorted(p for p in _tree(repo) if not p.startswith(".")) == [
        "benchmarks/results/table1_launch/state.tgz", "gca/a.py"]
    assert "of 64: OVER" in out.stdout and "65.0 MiB" in out.stdout, out.stdout
    back = run("back")
    assert back.returncode == 0 and "moved back" in back.stdout, back.stdout + back.stderr
    assert _tree(repo) == before
    (repo / ".whl/big.whl").write_bytes(b"0")  # under the limit: no OVER (the control)
    out = run("out")
    assert out.returncode == 0 and "MiB of 64" in out.stdout and "OVER" not in out.stdout, out.stdout
    assert (repo / "tests/test_a.py").is_file()  # without LEAN, tests stay
    assert run("back").returncode == 0 and _tree(repo) == before
    assert run("out", LEAN="1").returncode == 0
    (repo / "tests").mkdir()
    (repo / "tests/new.py").write_text("new")  # made meanwhile: `back` keeps it and leaves the older tests/ in HOLD
    kept = run("back")
    assert "kept ./tests" in kept.stdout and (hold / "lean/tests/test_a.py").is_file(), kept.stdout
    refused = run("out", LEAN="1")  # which refuses the next `out`: nothing nested or overwritten in HOLD
    assert refused.returncode == 1 and "run 'back' first" in refused.stdout, refused.stdout
    assert (repo / "tests/new.py").is_file() and not (hold / "lean/tests/tests").exists()
