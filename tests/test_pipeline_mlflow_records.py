"""A grid's records logged into MLflow after the fact (gca.pipeline.mlflow_records, grid --mlflow-import): the GPU
machine has no mlflow, so its runs reach the UI only this way, logged as the stages would have logged them."""

from __future__ import annotations

import json

import pytest

from gca.pipeline import grid

mlflow = pytest.importorskip("mlflow")

GRID = ["--scenes", "ball", "--methods", "gca", "nclaw", "--profile", "ci", "--set", "train.seeds=[0,1]"]


def _made_elsewhere(work, cd_gca: float):
    """A grid work dir as a GPU machine leaves it: gca seeds 0-1 trained (seed 0 evaluated), nclaw seed 0 evaluated;
    nclaw seed 1 stopped by its call's deadline as it wrote its train.json (no .done marker: unfinished)."""
    grid.prepare(work, grid.grid_params("ci", ["ball"], ["gca", "nclaw"], ["train.seeds=[0,1]"]))
    runs, evals = work / "runs/ball", work / "metrics/eval/ball"
    (work / ".grid").mkdir(exist_ok=True)
    for job in ("gca", "nclaw+gca@seed1"):  # one run, and a batch of two (--runs-per-job)
        (work / f".grid/train@ball:{job}.done").write_text("60.0\n\n")
    for name, commit in (("gca", "abc1234 (given)"), ("gca@seed1", "abc1234 (given)"), ("nclaw", None),
                         ("nclaw@seed1", None)):
        (runs / name).mkdir(parents=True)
        train = {"scene": "ball", "method": name.split("@")[0], "status": "ok", "train_seconds": 60.0}
        if commit:
            train["commit"] = commit
        (runs / name / "train.json").write_text(json.dumps(train))
    history = [{"iteration": i, "loss": 10.0 - i, "share/global/norm": 0.1 * i} for i in range(3)]
    (runs / "gca/history.json").write_text(json.dumps({"history": history}))
    evals.mkdir(parents=True)
    for name, cd in (("gca", cd_gca), ("nclaw", 0.03)):
        (evals / f"{name}.json").write_text(json.dumps({"status": "ok", "chamfer_mean": cd,
                                                        "chamfer_per_frame": [cd, cd]}))
    (evals / "gca").mkdir()
    (evals / "gca/strip.png").write_bytes(b"\x89PNG")


def _import(tmp_path, tag: str, cd_gca: float) -> None:
    made = tmp_path / f"made_{tag}"
    _made_elsewhere(made, cd_gca)
    state = tmp_path / f"state_{tag}.tgz"
    grid.save_state(made, state)
    results = grid.collect(made, tmp_path / f"results_{tag}")  # holds the history (the state does not)
    assert grid.main(["--work", str(tmp_path / f"here_{tag}"), *GRID, "--restore-state", str(state),
                      "--records", str(results), "--mlflow-import"]) == {}


def _keyed(key: str) -> list:
    return mlflow.search_runs(search_all_experiments=True, filter_string=f"tags.import_key = '{key}'",
                              output_format="list")


def test_a_grids_records_reach_mlflow_as_the_stages_log_them_once(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    _import(tmp_path, "first", 0.0123)
    # gca x 2 seeds, nclaw's seed 0; its seed 1 (a nuisance draw of its own) was not made there
    assert "mlflow: {'logged': 3, 'unfinished': 1}" in capsys.readouterr().out
    table1 = mlflow.search_runs(experiment_names=["gca/table1"], output_format="list")
    primary = {r.info.run_name: r for r in table1 if "mirror_of" not in r.data.tags}
    assert sorted(primary) == ["ball/gca", "ball/gca@seed1", "ball/nclaw"]
    gca = primary["ball/gca"]
    assert gca.data.tags["git_commit"] == "abc1234 (given)" and gca.data.tags["seed"] == "0"
    assert primary["ball/nclaw"].data.tags["git_commit"] == "not recorded"  # a record from before session 20
    assert gca.data.params["method.name"] == "gca" and "method.terms" in gca.data.params  # its effective config
    assert gca.data.metrics["chamfer_mean_mm"] == pytest.approx(12.3)
    steps = mlflow.MlflowClient().get_metric_history(gca.info.run_id, "loss")
    assert [(m.step, m.value) for m in steps] == [(0, 10.0), (1, 9.0), (2, 8.0)]
    assert "chamfer_mean" not in primary["ball/gca@seed1"].data.metrics  # trained, not evaluated: no metrics
    # every other table of gca lists the row: a mirror pointing at the primary run
    mirrors = [r for r in _keyed("ball/gca") if r.data.tags.get("mirror_of") == gca.info.run_id]
    assert len(mirrors) == 6 and {r.data.tags["table"] for r in mirrors} == {"table2", "table3", "table4", "table5",
                                                                          "table6", "law"}
    # the same records again: nothing new
    _import(tmp_path, "again", 0.0123)
    assert "mlflow: {'unchanged': 3, 'unfinished': 1}" in capsys.readouterr().out
    assert len(_keyed("ball/gca")) == 7
    # a record that changed (an evaluation made again) replaces its runs, mirrors included
    _import(tmp_path, "changed", 0.02)
    assert "'logged': 1" in capsys.readouterr().out
    now = _keyed("ball/gca")
    assert len(now) == 7 and all(r.data.metrics["chamfer_mean_mm"] == pytest.approx(20.0) for r in now)


def test_records_archives_may_hold_only_plain_files(tmp_path):
    import tarfile

    bad = tmp_path / "bad.tgz"
    with tarfile.open(bad, "w:gz") as tar:
        link = tarfile.TarInfo("runs/ball/gca/history.json")
        link.type, link.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tar.addfile(link)
    with pytest.raises(SystemExit, match="bad.tgz: 'runs/ball/gca/history.json' is not a records file"):
        grid.unpack_records(bad, tmp_path / "work")
    assert not (tmp_path / "work").exists()
    escape = tmp_path / "escape.tgz"  # a folder entry is passed over, but not one that leaves the work folder
    with tarfile.open(escape, "w:gz") as tar:
        up = tarfile.TarInfo("runs/../../x")
        up.type = tarfile.DIRTYPE
        tar.addfile(up)
    with pytest.raises(SystemExit, match="is not a records file"):
        grid.unpack_records(escape, tmp_path / "work")
