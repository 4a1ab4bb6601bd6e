"""Issue 22, item 7: MLflow shows the comparison (effective method configuration, every table's experiment
lists every row, Chamfer in millimetres), against a local sqlite store (conftest)."""

import mlflow
import pytest

from gca.align.cpr import CPRConfig
from gca.align.rdga import RDGAConfig
from gca.laws.lora import LoRAConfig
from gca.pipeline import track
from gca.train.methods import METHODS


def _params(name):
    return track.method_params(METHODS[name], RDGAConfig(), CPRConfig(), LoRAConfig())


def test_ablations_differ_in_their_effective_configuration():
    gca, no_rdga, no_global, no_cpr = (_params(m) for m in ("gca", "no_rdga", "no_global", "no_cpr"))
    assert gca["method.rdga.enabled"] is True and gca["method.rdga.use_global"] is True
    assert no_rdga["method.rdga"] == "off" and "method.rdga.enabled" not in no_rdga  # was align.rdga.enabled=True
    assert no_global["method.rdga.use_global"] is False
    assert no_cpr["method.cpr"] == "off" and "method.cpr.lambda_e" in gca
    assert _params("rank_to_l1")["method.rdga.depth_term"] == "l1" and gca["method.rdga.depth_term"] == "rank"
    assert _params("gca_full_ft")["method.lora"] == "off" and gca["method.lora.rank"] == 16
    assert _params("cpr_target_removed")["method.cpr.remove_target"] is True
    # every pair of methods differs somewhere ("show diff only" never says "no parameters to display")
    names = list(METHODS)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert _params(a) != _params(b), (a, b)


def test_chamfer_in_millimetres():
    out = track.with_millimetres({"chamfer_mean": 0.0123, "chamfer_max": float("nan"), "psnr_train": 20.0,
                                  "chamfer_definition": "mean NN Euclidean [m]"})
    assert out["chamfer_mean_mm"] == pytest.approx(12.3) and "chamfer_max_mm" not in out and "psnr_train_mm" not in out
    sq = track.with_millimetres({"chamfer_mean": 1e-4, "chamfer_definition": "squared distances [m^2]"})
    assert sq["chamfer_mean_mm2"] == pytest.approx(100.0) and "chamfer_mean_mm" not in sq


def test_every_table_experiment_lists_the_row():
    method = METHODS["gca"]
    with track.stage_run("train", {"align": {"rdga": {"tau": 0.5}}}, experiment="gca/table1", scene="ball",
                         method="gca", table="table1") as run:
        run.log_params(_params("gca"))
        primary = run.run_id
    metrics = track.with_millimetres({"chamfer_mean": 0.004, "status_ok": 1.0})
    track.mirror_runs({"x": 1}, metrics, method.tables[1:], primary, scene="ball", method="gca", run_name="ball/gca")
    for table in method.tables[1:]:
        rows = mlflow.search_runs(experiment_names=[f"gca/{table}"])
        assert len(rows) == 1, table
        row = rows.iloc[0]
        assert row["tags.mirror_of"] == primary and row["tags.table"] == table
        assert row["params.method.terms"] == "silhouette,global,anchor,cpr"  # the primary's params, copied
        assert row["params.align.rdga.tau"] == "0.5"
        assert row["metrics.chamfer_mean_mm"] == pytest.approx(4.0)
    assert len(mlflow.search_runs(experiment_names=["gca/table1"])) == 1  # the primary is not duplicated there
