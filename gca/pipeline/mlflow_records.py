"""A grid's records into MLflow, after the fact (issue 22 item 7 for runs made where MLflow is absent).

The GPU machine has no mlflow (``../shared/gpu/README.md``: it travels as wheels only where it must), so the
paper-profile runs of ``benchmarks/table_bundle.sh`` log nothing while they run: each stage warns and goes on,
and the truth stays in the JSON records (``gca.pipeline.track``'s module doc). This logs those records into the
MLflow store here exactly as the stages would have: one training run per (scene, method, seed) in the
experiment of the method's first table, with the method's effective configuration, the history per iteration
and the loss curve; the evaluation's final metrics (Chamfer also in mm) and media added to it; a mirror run in
each other table of the method. Tag ``git_commit`` is the commit the record names (``train.json``'s ``commit``;
"not recorded" for runs made before session 20), and ``import_key`` / ``import_digest`` make it idempotent: a
record logged before is skipped, a record that changed (an evaluation added later) replaces its runs.

    python -m gca.pipeline.grid --work W --scenes ... --restore-state STATE.tgz --records RECORDS.tgz --mlflow-import

(the grid builds ``W/params.yaml`` and checks the state was made under it, then calls :func:`import_grid`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from gca.config import read_yaml, section
from gca.io import read_json
from gca.pipeline.dispatch import job_runs
from gca.pipeline.settings import Settings
from gca.pipeline.track import method_params, mirror_runs, stage_run, train_run_args, with_millimetres
from gca.pipeline.train import seed_runs
from gca.stamp import fingerprint
from gca.train.methods import get_method


def _existing(key: str) -> list:
    """MLflow runs (every experiment) tagged ``import_key = key``."""
    import mlflow

    return mlflow.search_runs(search_all_experiments=True, filter_string=f"tags.import_key = '{key}'",
                              output_format="list")


def _finished(work: Path, scene: str, name: str) -> bool:
    """Whether run ``name`` of ``scene`` has its training job's ``.done`` marker (``.grid/train@<scene>:<runs>.done``,
    one run or a batch). A ``train.json`` without one was written by a run its call stopped before the stage ended:
    it trains again on the next machine (session 25: bottle no_global seed 2)."""
    return any(name in job_runs(path.stem)[1] for path in (work / ".grid").glob(f"train@{scene}:*.done"))


def import_run(settings: Settings, work: Path, scene: str, method, seed: int, name: str) -> str:
    """Log one run's records (``work/runs/<scene>/<name>/`` and ``work/metrics/eval/<scene>/<name>.json``);
    returns ``"logged"``, ``"unchanged"`` (logged before from the same records), ``"not trained"`` or
    ``"unfinished"`` (a ``train.json`` without its job's marker: :func:`_finished`)."""
    import mlflow

    run_dir, eval_json = work / "runs" / scene / name, work / "metrics" / "eval" / scene / f"{name}.json"
    if not (run_dir / "train.json").is_file():
        return "not trained"
    if not _finished(work, scene, name):
        return "unfinished"
    train = read_json(run_dir / "train.json")
    evaluation = read_json(eval_json) if eval_json.is_file() else None
    history_file = run_dir / "history.json"
    history = read_json(history_file).get("history", []) if history_file.is_file() else []
    key = f"{scene}/{name}"
    digest = fingerprint({}, (), extra={"train": train, "eval": evaluation, "history": len(history)})
    before = _existing(key)
    if before and all(r.data.tags.get("import_digest") == digest for r in before):
        return "unchanged"
    for r in before:  # an older import of this run (and its mirrors): replaced
        mlflow.delete_run(r.info.run_id)
    args = train_run_args(scene, method, seed, name, settings.scene(scene).material)
    own = {"import_key": key, "import_digest": digest, "git_commit": str(train.get("commit", "not recorded")),
           "imported_from": "records"}
    with stage_run("train", settings.params, **{**args, "tags": {**args["tags"], **own}}) as run:
        run.log_params(method_params(method, settings.rdga, settings.cpr, settings.lora))
        for record in history:
            run.log_metrics({k: v for k, v in record.items() if k != "iteration"}, step=int(record["iteration"]))
        if (run_dir / "loss.png").is_file():
            run.log_artifact(run_dir / "loss.png")
        if evaluation is None:
            return "logged"
        final = with_millimetres({k: v for k, v in evaluation.items() if k != "chamfer_per_frame"})
        run.log_metrics(final)
        for media in ("strip.png", "rollout.gif", "cd_time.png"):
            if (eval_json.parent / name / media).is_file():
                run.log_artifact(eval_json.parent / name / media)
        primary = run.run_id
    mirror_runs(settings.params, final, method.tables[1:], primary, scene=scene, method=method.name,
                run_name=args["run_name"], tags={**args["tags"], **own},
                extra_params=method_params(method, lora=settings.lora))
    return "logged"


def import_grid(work: Path, log: Callable[[str], None] = print) -> dict[str, int]:
    """:func:`import_run` for every (scene, method, seed) of ``work/params.yaml``; returns the count per outcome.
    Logs into ``MLFLOW_TRACKING_URI`` (else ``sqlite:///mlflow.db`` in the working directory)."""
    import mlflow  # noqa: F401 - here it is required: say so at once, not per run

    counts: dict[str, int] = {}
    for scene in read_yaml(work / "params.yaml")["scenes"]:
        settings = Settings.load(f"train@{scene}", work / "params.yaml")  # as that scene's train stage read them
        methods = [get_method(m) for m in section(settings.params, f"scenes.{scene}.methods")]
        for method, seed, name in seed_runs(settings, methods):
            outcome = import_run(settings, work, scene, method, seed, name)
            counts[outcome] = counts.get(outcome, 0) + 1
            log(f"mlflow: {scene}/{name}: {outcome}")
    return counts
