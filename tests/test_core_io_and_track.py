"""gca.io atomic writes and gca.pipeline.track: tracking failures warn, never fail a stage."""

import json

import pytest

from gca import io
from gca.pipeline import track


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "out.json"
    io.write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with io.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert json.loads(target.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


def test_atomic_dir_replaces_whole_directory(tmp_path):
    target = tmp_path / "scene"
    with io.atomic_path(target, is_dir=True) as tmp:
        (tmp / "a.txt").write_text("1")
    with io.atomic_path(target, is_dir=True) as tmp:
        (tmp / "b.txt").write_text("2")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]


@pytest.mark.parametrize("cut", ["between the renames", "while the previous version is deleted"])
def test_a_stop_inside_a_folder_swap_leaves_one_complete_version_and_nothing_parked(tmp_path, monkeypatch, cut):
    """Issue 24 item 7: SIGTERM (``gca.stop.Terminated``) inside the swap of a folder: cut between parking the
    previous version and renaming the new one in, the previous version is put back; cut while the parked one
    is deleted, the new version stays and the parked one is deleted all the same. No ``.scene.old<pid>`` is
    left either way (before, both cuts left it, and the first one no output)."""
    import shutil
    from pathlib import Path

    from gca import stop

    target = tmp_path / "scene"
    with io.atomic_path(target, is_dir=True) as tmp:
        (tmp / "old.txt").write_text("previous")
    rename, rmtree, cuts = Path.rename, shutil.rmtree, []

    def rename_cut(self, to):
        if cut == "between the renames" and Path(to) == target and not cuts:
            cuts.append(self)
            raise stop.Terminated()
        return rename(self, to)

    def rmtree_cut(path, *args, **kwargs):
        if cut == "while the previous version is deleted" and ".old" in Path(path).name and not cuts:
            cuts.append(path)
            (Path(path) / "old.txt").unlink()  # part of it deleted
            raise stop.Terminated()
        return rmtree(path, *args, **kwargs)

    monkeypatch.setattr(Path, "rename", rename_cut)
    monkeypatch.setattr(io.shutil, "rmtree", rmtree_cut)
    with pytest.raises(stop.Terminated):
        with io.atomic_path(target, is_dir=True) as tmp:
            (tmp / "new.txt").write_text("next")
    assert cuts, "the cut was not reached"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    expected = ["old.txt"] if cut == "between the renames" else ["new.txt"]
    assert sorted(p.name for p in target.iterdir()) == expected


def test_write_json_is_byte_stable_and_maps_nonfinite_to_null(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    io.write_json(a, {"y": float("nan"), "x": [1.0, float("inf")]})
    io.write_json(b, {"x": [1.0, float("inf")], "y": float("nan")})
    assert a.read_bytes() == b.read_bytes()
    assert json.loads(a.read_text()) == {"x": [1.0, None], "y": None}


def test_save_torch_is_byte_stable_and_atomic(tmp_path):
    """The same object saved twice gives the same bytes (torch.save to a *name* embeds the random temporary
    name in the archive: DVC's run cache then missed every stage after the prior); a failure keeps the old file."""
    import torch

    obj = {"w": torch.arange(6.0).reshape(2, 3), "meta": {"family": "jelly"}}
    a, b = io.save_torch(obj, tmp_path / "a.pt"), io.save_torch(obj, tmp_path / "sub" / "b.pt")
    assert a.read_bytes() == b.read_bytes()
    assert torch.equal(torch.load(a, weights_only=True)["w"], obj["w"])
    with pytest.raises(AttributeError, match="Can't pickle"):
        io.save_torch({"bad": lambda: 0}, a)  # not picklable: the write fails ...
    assert a.read_bytes() == b.read_bytes()  # ... and leaves the old file as it was
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pt", "sub"]


def test_stage_run_logs_params_metrics_and_tags(tmp_path, monkeypatch):
    import mlflow

    monkeypatch.setenv("DVC_EXP_NAME", "exp-xyz")
    with track.stage_run("particles", {"sim": {"dt": 1e-3}}, scene="duck", method="gca") as run:
        assert run.active
        run.log_metrics({"loss": 1.5, "nested": {"cd": 0.2}, "skip": "text"})
    runs = mlflow.search_runs(experiment_names=["gca/particles"])
    assert len(runs) == 1
    row = runs.iloc[0]
    assert row["params.sim.dt"] == "0.001"
    assert row["metrics.nested.cd"] == pytest.approx(0.2)
    assert row["tags.scene"] == "duck" and row["tags.method"] == "gca"
    assert row["tags.dvc_exp_name"] == "exp-xyz"
    assert row["tags.stage"] == "particles"


def test_tracking_failure_only_warns(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "bogus-scheme://nowhere")
    ran = []
    with pytest.warns(RuntimeWarning, match="mlflow"):
        with track.stage_run("assets", {"a": 1}) as run:
            run.log_metrics({"x": 1.0})
            ran.append(True)
    assert ran == [True]


def test_the_commit_given_by_the_sender_wins(monkeypatch):
    """On the GPU machine the checkout is a copied tree whose .git (if any) is not the code sent: training, evaluation and
    tuning records say the commit they were sent as; here, without it, git's HEAD; with no git at all, unknown."""
    import subprocess

    monkeypatch.delenv("GCA_COMMIT", raising=False)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=track.ROOT, capture_output=True, text=True).stdout.strip()
    assert track.git_commit().startswith(head)
    monkeypatch.setenv("GCA_COMMIT", "abc1234")
    assert track.git_commit() == "abc1234 (given)"

    def no_git(*a, **k):
        raise OSError("git: not found")

    monkeypatch.setattr(subprocess, "run", no_git)
    monkeypatch.delenv("GCA_COMMIT")
    assert track.git_commit() == "unknown"
