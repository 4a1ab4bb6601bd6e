"""benchmarks/carry_aside.sh: what the GPU calls do not read leaves the tree before them and comes back whole."""

import subprocess
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "carry_aside.sh"


def _tree(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_text() for p in sorted(root.rglob("*")) if p.is_file()}


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
