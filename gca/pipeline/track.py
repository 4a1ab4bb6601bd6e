"""MLflow mirroring of stage runs. The metrics JSON a stage writes is the truth; this only mirrors it.

Tracking never breaks a stage: every MLflow failure is turned into a warning and the stage goes on
(its metrics JSON is written by the stage regardless, before or after the tracking context).

Defaults: ``MLFLOW_TRACKING_URI`` when set, else ``sqlite:///mlflow.db`` in the working directory.
Tags: stage, scene, method, table, seed (training runs), git commit and ``DVC_EXP_NAME`` (set by ``dvc exp run``).

Comparison in the UI (issue 22, item 7):

- every training run logs its method's *effective* configuration (:func:`method_params`: ``method.terms``, the
  RDGA switches its terms set applied to ``align.rdga``, CPR's config or ``off``, its adapt mode and LoRA), so
  "show diff only" separates the ablations even though their ``align.*`` params are identical;
- each table's experiment holds every row of that table: a run lives in the experiment of its method's first
  table (``gca/table1`` for gca, with the training history), and the evaluate stage logs a *mirror* run (its
  params and final metrics, tag ``mirror_of`` = the primary run id) into the experiment of each other table
  the method belongs to (:func:`mirror_runs`);
- Chamfer distances are also logged in millimetres (``chamfer_mean_mm``; :func:`with_millimetres`), since the
  compare view rounds metrics to three decimals.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping

from gca.config import flatten

DEFAULT_URI = "sqlite:///mlflow.db"
ROOT = Path(__file__).resolve().parents[2]  # the checkout the package runs from
_MAX_PARAM_LEN = 6000  # MLflow rejects longer param values


def git_commit() -> str:
    """The commit of the code running: ``$GCA_COMMIT`` when whoever sent the tree says it (the GPU machine's copy of
    the tree carries a stale ``.git``, session 17: its HEAD is not the code sent; ``benchmarks/gpu_wheels.sh``
    requires it there), else HEAD of the checkout this package is imported from (``+dirty`` with uncommitted
    changes to tracked files), else ``unknown``. Recorded by training, evaluation and tuning, and the MLflow tag
    ``git_commit``."""
    given = os.environ.get("GCA_COMMIT", "").strip()
    if given:
        return f"{given} (given)"
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                               text=True, timeout=10).stdout.strip()
        if out.returncode == 0:
            return out.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return "unknown"


class Run:
    """A possibly-disabled MLflow run; every method warns instead of raising."""

    def __init__(self, mlflow_module: Any | None):
        self._mlflow = mlflow_module

    @property
    def run_id(self) -> str | None:
        """The MLflow run id (None when tracking is off)."""
        try:
            return self._mlflow.active_run().info.run_id if self._mlflow else None
        except Exception:  # noqa: BLE001
            return None

    @property
    def active(self) -> bool:
        return self._mlflow is not None

    def _call(self, what: str, fn, *args, **kwargs) -> None:
        if self._mlflow is None:
            return
        try:
            fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - tracking must never fail a stage
            warnings.warn(f"mlflow {what} failed ({type(exc).__name__}: {exc}); metrics JSON is unaffected",
                          RuntimeWarning, stacklevel=3)

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        """Log numeric metrics (nested keys are flattened with '.'; non-numbers are skipped)."""
        flat = {k: float(v) for k, v in flatten(metrics).items()
                if isinstance(v, (int, float)) and not isinstance(v, bool) and v == v}
        if flat and self._mlflow is not None:
            self._call("log_metrics", self._mlflow.log_metrics, flat, step=step)

    def log_params(self, params: Mapping[str, Any]) -> None:
        """Log extra params (e.g. :func:`method_params`); a value already logged the same is fine."""
        if params and self._mlflow is not None:
            self._call("log_params", self._mlflow.log_params, _flat_params(params))

    def log_artifact(self, path: str | os.PathLike) -> None:
        if self._mlflow is not None and Path(path).exists():
            fn = self._mlflow.log_artifacts if Path(path).is_dir() else self._mlflow.log_artifact
            self._call("log_artifact", fn, str(path))


def method_params(method, rdga=None, cpr=None, lora=None) -> dict[str, Any]:
    """The effective configuration of ``method`` (a :class:`gca.train.methods.Method`) as MLflow params:
    its declared terms, law, adapt mode, views; the RDGA config its terms switch (``rdga`` with
    ``Method.rdga_switches`` applied, or ``off``); CPR's config (``cpr``, or ``off`` without the ``cpr`` term;
    ``cpr_remove_target``); LoRA's rank and alpha where it adapts by LoRA."""
    import dataclasses

    out: dict[str, Any] = {"method.name": method.name, "method.terms": ",".join(method.terms) or "none",
                           "method.law": method.law, "method.adapt": method.adapt, "method.views": method.views,
                           "method.tables": ",".join(method.tables)}
    switches = method.rdga_switches()
    if switches is None:
        out["method.rdga"] = "off"
    elif rdga is not None:
        out.update({f"method.rdga.{k}": v for k, v in dataclasses.asdict(dataclasses.replace(rdga, **switches)).items()})
    else:
        out.update({f"method.rdga.{k}": v for k, v in switches.items()})
    if not method.uses("cpr"):
        out["method.cpr"] = "off"
    else:
        out["method.cpr.remove_target"] = method.cpr_remove_target
        if cpr is not None:
            out.update({f"method.cpr.{k}": v for k, v in dataclasses.asdict(cpr).items()})
    if method.adapt == "lora" and lora is not None:
        out.update({f"method.lora.{k}": v for k, v in dataclasses.asdict(lora).items()})
    elif method.adapt != "lora":
        out["method.lora"] = "off"
    return out


def train_run_args(scene: str, method, seed: int, name: str, material: str | None = None) -> dict[str, Any]:
    """:func:`stage_run`'s keywords for the MLflow run of one training run (``name``: ``gca``, ``gca@seed1``): the
    experiment of the method's first table, tags scene / method / table / tables / seed (and the scene's material).
    The train and evaluate stages and the records' import (``gca.pipeline.mlflow_records``) log through it."""
    tags = {"tables": ",".join(method.tables), "seed": str(seed), **({"material": material} if material else {})}
    return {"scene": scene, "method": method.name, "table": method.tables[0], "experiment": f"gca/{method.tables[0]}",
            "run_name": f"{scene}/{name}", "tags": tags}


def with_millimetres(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """``metrics`` plus ``<key>_mm`` for every finite Chamfer number ``chamfer_*`` in metres (x 1e3; a squared
    definition, m^2, gets ``<key>_mm2``, x 1e6)."""
    squared = "squared" in str(metrics.get("chamfer_definition", "")).lower()
    out = dict(metrics)
    for key, value in metrics.items():
        if key.startswith("chamfer") and isinstance(value, (int, float)) and not isinstance(value, bool) \
                and value == value:
            out[f"{key}_mm2" if squared else f"{key}_mm"] = float(value) * (1e6 if squared else 1e3)
    return out


def mirror_runs(params: Mapping | None, metrics: Mapping[str, Any], tables: tuple[str, ...], primary_run_id: str | None,
                *, scene: str, method: str, run_name: str, tags: Mapping[str, str] | None = None,
                extra_params: Mapping[str, Any] | None = None) -> None:
    """Log a mirror of one finished run into ``gca/<table>`` for every table in ``tables``: the primary run's
    params where they can be read (the training run's: the method's effective configuration included), else
    ``params`` and ``extra_params``; its final ``metrics``; tag ``mirror_of``."""
    copied = None
    if primary_run_id and tables:
        try:
            import mlflow

            copied = dict(mlflow.get_run(primary_run_id).data.params)
        except Exception:  # noqa: BLE001 - tracking must never fail a stage
            copied = None
    for table in tables:
        with stage_run("evaluate", None if copied else params, experiment=f"gca/{table}", scene=scene, method=method,
                       table=table, run_name=run_name,
                       tags={**(tags or {}), "mirror_of": primary_run_id or "unknown"}) as run:
            run.log_params(copied or extra_params or {})
            run.log_metrics(metrics)


def _flat_params(params: Mapping) -> dict[str, str]:
    return {k: str(v)[:_MAX_PARAM_LEN] for k, v in flatten(params).items()}


@contextlib.contextmanager
def stage_run(stage: str, params: Mapping | None = None, *, experiment: str | None = None,
              scene: str | None = None, method: str | None = None, table: str | None = None,
              run_name: str | None = None, tags: Mapping[str, str] | None = None,
              resume_run_id: str | None = None) -> Iterator[Run]:
    """Open an MLflow run for one stage execution and yield a :class:`Run`.

    Args:
        stage: DVC stage name (tag ``stage``).
        params: resolved params; logged flattened (``sim.dt``).
        experiment: MLflow experiment name (default ``gca/<stage>``; paper tables use ``table``).
        scene, method, table: optional tags used to compare runs in ``mlflow ui``.
        run_name: default ``<stage>/<scene>/<method>`` with the parts that are set.
        resume_run_id: continue this run (e.g. evaluation adds final metrics to the training run of
            the same (scene, method, seed)); a new run is started if it cannot be resumed.
    """
    run = Run(None)
    try:
        import mlflow

        if not os.environ.get("MLFLOW_TRACKING_URI"):
            mlflow.set_tracking_uri(DEFAULT_URI)
        mlflow.set_experiment(experiment or f"gca/{stage}")
        all_tags = {"stage": stage, "git_commit": git_commit()}
        for key, value in (("scene", scene), ("method", method), ("table", table)):
            if value is not None:
                all_tags[key] = value
        if os.environ.get("DVC_EXP_NAME"):
            all_tags["dvc_exp_name"] = os.environ["DVC_EXP_NAME"]
        all_tags.update(tags or {})
        name = run_name or "/".join(p for p in (scene, method) if p) or stage
        try:
            mlflow.start_run(run_id=resume_run_id, tags=all_tags) if resume_run_id else None
        except Exception:  # noqa: BLE001 - e.g. another tracking store: start fresh
            resume_run_id = None
        if not resume_run_id:
            mlflow.start_run(run_name=name, tags=all_tags)
        run = Run(mlflow)
        if params and not resume_run_id:
            run._call("log_params", mlflow.log_params, _flat_params(params))
    except Exception as exc:  # noqa: BLE001
        warnings.warn(f"mlflow tracking disabled for stage {stage!r} ({type(exc).__name__}: {exc})",
                      RuntimeWarning, stacklevel=3)
        run = Run(None)
    try:
        yield run
    finally:
        if run.active:
            status = "FINISHED"
            import sys
            if sys.exc_info()[0] is not None:
                status = "FAILED"
            run._call("end_run", run._mlflow.end_run, status=status)
