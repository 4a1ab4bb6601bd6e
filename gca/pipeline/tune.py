"""Tune the learned methods' knobs on the calibration scenes only (issue 22 items 1-2; the protocol:
:mod:`gca.pipeline.tuning`; the GPU command and its cost: tuning/README.md).

    python -m gca.pipeline.tune --work /tmp/tune --profile paper [--methods gca neuma pacnerf_depth]
        [--set tuning.trials=8 ...] [--priors models/prior] [--deadline 540] [--shard 0/4] [--record tuning/record.json]

1. The work directory gets params.yaml restricted to ``tuning.scenes`` (each ``calibration: true``, else refused;
   their objects and prior families only), ``train.seeds = tuning.seeds``, ``train.iterations =
   tuning.iterations``, and the code linked; the stage commands of dvc.yaml (assets, particles, prior,
   ground_truth, preprocess) make the calibration scenes' inputs there (a finished one is not redone).
2. Every (method, trial, scene, seed) unit: the launch velocity (once per scene and seed, from that seed's
   observations), :func:`gca.pipeline.train.train_method` and :func:`gca.pipeline.evaluate.evaluate_trained`
   with the trial's knob values, its CD and term shares into ``<work>/tuning/<method>/trial<i>/<scene>@seed<k>.json``.
   A unit done is not redone (resumable); ``--shard k/n`` runs every n-th unit (one process per GPU), or, with
   ``--claim DIR``, processes launched together take the next unclaimed unit as they free up (units cut off
   first);
   ``--deadline`` [s] starts no unit its measured cost would not finish in time; under a stop deadline
   (``GCA_STOP_AT``) units start until ``TAIL_START_S`` before it, one cut off there resumes next launch
   (:func:`no_start`). A unit's checkpoint stays until its result is written: stopped after its training, it
   resumes at its end.
3. When every unit is there: the record (``--record``, default ``tuning/record.json``) and the params.yaml change
   to apply (printed); else the units left, and the command to repeat.

A tuning spread over machines that forget their disks (one bounded GPU command per session): ``--save-state TGZ``
writes what the next call needs (units done, launch velocities, checkpoints of units in progress; not the inputs),
``--restore-state TGZ`` unpacks it into a fresh work directory first (``benchmarks/tune_bundle.sh``).
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path

import yaml

from gca import config, stamp, stop
from gca.config import ConfigError, resolve
from gca.io import pack_files, read_json, unpack_files, write_json
from gca.pipeline import cli, dispatch, grid
from gca.pipeline.track import git_commit
from gca.pipeline.tuning import (TuningConfig, apply_values, check_scenes, choose, param_values, params_change,
                                 score, trial_values)

ROOT = grid.ROOT
PREPARE_STAGES = ["assets", "particles", "prior", "ground_truth", "preprocess"]


def load_config(params_path: Path, profile: str | None, overrides: list[str]) -> tuple[dict, dict, TuningConfig]:
    """(raw params with ``profile`` and the overrides, their resolution, the typed ``tuning`` section)."""
    raw = config.read_yaml(params_path)
    raw["profile"] = profile or raw.get("profile", "paper")
    grid.apply_overrides(raw, overrides)
    resolved = resolve(raw, raw["profile"])
    resolved["profile"] = raw["profile"]
    cfg = config.build(TuningConfig, config.section(resolved, "tuning"), "tuning")
    check_scenes(resolved, cfg.scenes)
    return raw, resolved, cfg


def work_params(raw: dict, cfg: TuningConfig) -> dict:
    """``raw`` restricted to the calibration scenes (and their objects and prior families), at the tuning budget."""
    out = json.loads(json.dumps(raw))
    out["scenes"] = {s: dict(raw["scenes"][s]) for s in cfg.scenes}
    objects = {spec["object"] for spec in out["scenes"].values()}
    out["objects"] = {k: v for k, v in raw["objects"].items() if k in objects}
    families = {spec["prior"] for spec in out["scenes"].values()}
    out["prior"]["families"] = {k: v for k, v in raw["prior"]["families"].items() if k in families}
    out["train"]["seeds"] = list(cfg.seeds)
    out["train"]["iterations"] = cfg.iterations
    return out


def default_jobs() -> int:
    """Stage processes run at once by :func:`prepare_inputs`: a quarter of the CPU cores, at least 1 (the 2-core CI
    machine runs them one by one; the 16-core GPU machine 4, one chain per calibration scene)."""
    return max(1, (os.cpu_count() or 1) // 4)


def prepare_inputs(work: Path, params: dict, priors: Path | None, log=print, workers: int = 1) -> None:
    """Run the stage commands that make the calibration scenes' inputs in ``work`` (each once per params), up to
    ``workers`` at once, through the grid's dispatcher (:func:`gca.pipeline.dispatch.run`, its local engine: each
    job once its inputs are done, a job done under these params not again, each stage's log named when it fails;
    the scenes' chains are independent, so a failure stops only its own chain). Exits with the failed stages and
    their logs' tails."""
    grid.prepare(work, params)
    stamp = hashlib.sha256((work / "params.yaml").read_bytes()).hexdigest()[:16]
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    jobs = grid.link(grid.expand(dvc, params, PREPARE_STAGES))
    if priors is not None:
        for family in params["prior"]["families"]:
            target = work / "models/prior" / f"{family}.pt"
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(priors / f"{family}.pt", target)
            jobs.pop(f"prior@{family}", None)
        for job in jobs.values():
            job.after = {a for a in job.after if a in jobs}
    jobs = grid.chain_undone(jobs, params, work, stamp)
    run_stages(jobs, work, stamp, workers, log)


def run_stages(jobs: dict, work: Path, stamp: str, workers: int, log=print) -> None:
    """``jobs`` (``grid.Job``, ``after`` linked) through :func:`dispatch.run` on this machine, ``workers`` at once (on
    GPU 0 where there is one: the inputs' renders use it); exits naming each failed job, its log and its tail."""
    engine = dispatch.local_engine(work / ".grid" / "submitit" / "%j", 1, max(1, workers), timeout_min=24 * 60,
                                   max_requeue=0)
    lines: list[str] = []

    def say(msg: str) -> None:
        lines.append(msg)
        log(f"tune: {msg}")
    state = dispatch.run(jobs, engine, work, say, poll_s=0.2, stamp=stamp)
    failed = sorted(n for n, s in state.items() if s == dispatch.FAILED)
    if failed:
        why = "\n".join(ln for ln in lines if ln.startswith("FAIL  "))
        raise SystemExit(f"{why}\ntune: the inputs' stage(s) {failed} failed (their logs above); the stages done are "
                         "kept: run the same command again once fixed")


def unit_path(work: Path, method: str, trial: int, scene: str, seed: int) -> Path:
    return work / "tuning" / method / f"trial{trial}" / f"{scene}@seed{seed}.json"


def unit_run_dir(work: Path, method: str, trial: int, scene: str, seed: int) -> Path:
    """The unit's training folder (its checkpoint while in progress): ``tuning/<method>/trial<i>/<scene>/<run name>``."""
    from gca.train.config import run_dir_name

    return work / "tuning" / method / f"trial{trial}" / scene / run_dir_name(method, seed)


def _stamp(params: dict, extra) -> str:
    """A hash of every params section but ``tuning`` (the trial's knob values are already set in ``params``) and
    ``extra``: what a unit's result, checkpoint or shared launch velocity was made under (gca.stamp)."""
    return stamp.fingerprint(params, sorted(k for k in params if k != "tuning"), extra=extra)


def unit_stamp(params: dict, cfg: TuningConfig, method: str, values: dict, scene: str, seed: int) -> str:
    """The stamp of one unit: the params with the trial's values applied, the method, scene and seed."""
    return _stamp(apply_values(params, cfg, method, values), ["unit", method, scene, seed])


def done_unit(path: Path, expected: str) -> dict | None:
    """The unit's result when ``path`` holds one made under the stamp ``expected`` (another trial setup, another
    profile or other params give another stamp: that result is not this unit's), else None."""
    if not path.is_file():
        return None
    result = read_json(path)
    return result if stamp.matches(result, expected) else None


def units_of(cfg: TuningConfig, methods: list[str]) -> list[tuple[str, int, str, int]]:
    """Every (method, trial, scene, seed), trials outermost within a method (a deadline leaves whole trials)."""
    return [(m, i, s, k) for m in methods for i in range(cfg.trials) for s in cfg.scenes for k in cfg.seeds]


def launch_velocity(work: Path, params: dict, scene: str, seed: int, device: str) -> Path:
    """The launch velocity of (scene, seed), fitted once to that seed's observations (the knobs do not touch it)."""
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import estimate_scene_velocity, observed_inputs, velocity_path

    shared = velocity_path(work / "tuning" / "velocity" / scene, seed)
    expected = _stamp(params, ["velocity", scene, seed])
    if not (shared.is_file() and stamp.matches(read_json(shared), expected)):
        base = Settings(params)
        shared.parent.mkdir(parents=True, exist_ok=True)
        estimate_scene_velocity(base, scene, observed_inputs(base, scene, grid.scene_inputs(work, scene, params), seed),
                                shared, device)
        write_json(shared, {**read_json(shared), stamp.KEY: expected})
    return shared


def run_unit(work: Path, params: dict, cfg: TuningConfig, method_name: str, trial: int, values: dict, scene: str,
             seed: int, device: str) -> dict:
    """Train and evaluate one (method, trial, scene, seed) with the trial's knob values; its result record."""
    from gca.pipeline.evaluate import evaluate_trained
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import train_method, velocity_path
    from gca.scenes import truth
    from gca.train.methods import get_method

    inputs = grid.scene_inputs(work, scene, params)
    shared = launch_velocity(work, params, scene, seed, device)
    settings = Settings(apply_values(params, cfg, method_name, values))
    method = get_method(method_name)
    run_dir = unit_run_dir(work, method_name, trial, scene, seed)
    runs_dir = run_dir.parent
    run_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(shared, velocity_path(runs_dir, seed))
    velocity = tuple(read_json(shared)[k] for k in ("v0", "w0"))
    expected = unit_stamp(params, cfg, method_name, values, scene, seed)
    stamp.guard_checkpoint(run_dir / "checkpoint.pt", expected)  # a killed unit resumes only its own setup
    train = trained(lambda: train_method(settings, scene, method, inputs, velocity, run_dir, device=device, seed=seed,
                                         keep_checkpoint=True))  # cleared by main() once the unit's result is written
    body = settings.load_body(inputs.particles, inputs.gaussians, device)
    with truth.bind(inputs.scene_dir, work / "data/gt" / scene):
        metrics = evaluate_trained(settings, scene, method, inputs, body, runs_dir, runs_dir / "eval", device, seed)
    return {"method": method_name, "trial": trial, "scene": scene, "seed": seed, "values": dict(values),
            "status": metrics["status"], "chamfer_mean": metrics.get("chamfer_mean"),
            "term_shares": train.get("term_shares", {}), "train_seconds": train["train_seconds"],
            "iterations": train["iterations"], "commit": train["commit"], "device": train["device"],
            stamp.KEY: expected}


def trained(train) -> dict:
    """``train()``'s result. A stop (SIGTERM, ``GCA_STOP_FILE``, ``GCA_STOP_AT``) during it waits for the iteration's
    end and its checkpoint (:func:`gca.stop.deferred`); one that came after the last iteration stops here, before the
    unit's evaluation. The unit's checkpoint (its last iteration's, a finished training's; a diverged one's: its last
    periodic one) stays until :func:`main` has written the unit's result, so a unit stopped after its training, here
    or in its evaluation, resumes from it (at its training's end) rather than from scratch."""
    with stop.deferred(stop_at_end=False):
        result = train()
    stop.check()
    return result


TAIL_START_S = 60.0  # under a stop deadline, the least time left [s] worth starting a unit in: its setup and, cut
# off, its resume next launch cost ~10-30 s on the GPU (process, inputs, kernels), the rest is training kept


def no_start(elapsed: float, costs: list[float], deadline: float | None, stop_at: float | None, now: float) -> str:
    """Why this process starts no further unit ("" if it may start one). ``elapsed`` [s] since it started, ``costs``
    [s] of its units done, ``deadline`` (``--deadline``) [s since its start], ``stop_at`` (``GCA_STOP_AT``) and
    ``now`` [Unix s].

    Without a stop deadline a unit starts only if the longest one seen would end by ``deadline``. Under
    ``GCA_STOP_AT`` (the device bundles) a unit still training at the stop checkpoints its iteration and the next
    launch resumes it (:func:`trained`), so one starts while ``TAIL_START_S`` are left before the stop, whatever its
    length: session 43's shards that kept to ``--deadline`` left ~20 % of a call's GPU slots idle."""
    if stop_at is not None:
        left = stop_at - now
        return "" if left >= TAIL_START_S else f"{left:.0f} s left before {stop.STOP_AT_ENV}, under {TAIL_START_S:.0f}"
    if deadline and costs and elapsed + max(costs) > deadline:
        return f"deadline: {elapsed:.0f} s used, a unit takes up to {max(costs):.0f} s"
    return ""


def in_progress(work: Path, method: str, trial: int, scene: str, seed: int) -> bool:
    """Whether the unit has a checkpoint to resume: it was cut off in its training, or stopped after it (before its
    result was written: it then resumes at its training's end)."""
    return (unit_run_dir(work, method, trial, scene, seed) / "checkpoint.pt").is_file()


def claim_unit(claims: Path, method: str, trial: int, scene: str, seed: int) -> bool:
    """Claim the unit for this process: True when no other process of the same launch claimed it first (an
    exclusively created file ``claims/<method>.t<trial>.<scene>.s<seed>``; the launcher empties ``claims`` before it
    starts the processes, so a claim of a process killed in an earlier launch does not hold)."""
    claims.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(claims / f"{method}.t{trial}.{scene}.s{seed}", os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    os.write(fd, f"{os.getpid()}\n".encode())
    os.close(fd)
    return True


def state_files(work: Path) -> list[Path]:
    """What a tuning needs to go on in another work directory (another machine, a later session), relative to
    ``work``: every finished unit's result (``tuning/<method>/trial<i>/<scene>@seed<k>.json``), the shared launch
    velocities (``tuning/velocity/``) and the checkpoint (and its stamp) of every unit in progress. Not the inputs
    (remade by ``--prepare-only`` from params), nor the finished runs' folders (their result has what the record uses)."""
    tuning = work / "tuning"
    found = [*tuning.glob("*/trial*/*.json"), *tuning.glob("velocity/**/*.json"),
             *tuning.glob("*/trial*/*/*/checkpoint.pt"), *tuning.glob("*/trial*/*/*/checkpoint.pt.*")]
    return sorted(p.relative_to(work) for p in found if p.is_file())


def save_state(work: Path, archive: Path) -> int:
    """Write :func:`state_files` of ``work`` to the gzipped tar ``archive`` (atomically); returns the file count."""
    return pack_files(work, state_files(work), archive)


def restore_state(archive: Path, work: Path) -> int:
    """Unpack a :func:`save_state` archive into ``work`` (a file already there is kept: it is at least as new);
    returns the count unpacked. Refuses members outside ``tuning/``."""
    try:
        return unpack_files(archive, work, lambda name: name.startswith("tuning/"), "tuning state")
    except (FileNotFoundError, ValueError) as exc:
        raise ConfigError(str(exc)) from exc


def run_mlp_kernel(params: dict) -> str:
    """``train.mlp_kernel`` of resolved ``params`` (the dataclass default where unset): what the tuning's runs train
    with, which its record names (``benchmarks/precision_decision.py`` compares it)."""
    from gca.train.config import TrainConfig  # torch: only where a tuning runs

    return (params.get("train") or {}).get("mlp_kernel", TrainConfig.mlp_kernel)


def build_record(work: Path, params: dict, cfg: TuningConfig, methods: list[str], device: str,
                 overrides: list[str]) -> tuple[dict, int]:
    """The tuning record from the unit files in ``work`` and the number of units still missing."""
    from gca.eval.evaluate import device_name  # torch and warp: only where a record is built

    missing = 0
    record = {"protocol": "issue 22 items 1-2: tuning on calibration scenes only, the same budget for every method",
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "commit": git_commit(), "device": device_name(device), "unit_commits": {},  # what code and device made the units (a tuning spans sessions)
              "profile": params["profile"],
              "benchmark_version": str(params.get("benchmark", {}).get("version", "")),
              "overrides": list(overrides), "budget": cfg.budget(),
              # what the runs trained with where params.yaml's default differs by profile (benchmarks/precision_decision.py)
              "mlp_kernel": run_mlp_kernel(params),
              "search": {"kind": "latin_hypercube", "space": "log-uniform per knob", "sampler_seed": cfg.sampler_seed,
                         "trial_0": "the frozen params"},
              "objective": {"metric": "chamfer_mean (mean over calibration scenes and seeds; failed = inf)",
                            "constraint": "each RDGA term's mean norm share |g_T|/|g| >= share_floor_norm and mean "
                                          "cosine with the total >= share_floor_cos (methods with RDGA terms)",
                            "share_floor_norm": cfg.share_floor_norm, "share_floor_cos": cfg.share_floor_cos},
              "methods": {}}
    for method in methods:
        knobs = cfg.knobs(method)
        trials = []
        for i, values in enumerate(trial_values(cfg, method, params)):
            units = []
            for scene in cfg.scenes:
                for seed in cfg.seeds:
                    result = done_unit(unit_path(work, method, i, scene, seed),
                                       unit_stamp(params, cfg, method, values, scene, seed))
                    if result is not None:
                        units.append(result)
                        made = f"{result.get('commit', 'not recorded')} on {result.get('device', 'not recorded')}"
                        record["unit_commits"][made] = record["unit_commits"].get(made, 0) + 1
                    else:
                        missing += 1
            trials.append({"trial": i, "values": values, "params": param_values(params, cfg, method, values),
                           "units": units, "score": score(cfg, method, units)})
        entry = {"knobs": [{"name": k.name, "keys": list(k.keys), "range": [k.low, k.high], "factor": k.factor}
                           for k in knobs], "trials": trials}
        if all(t["score"]["complete"] for t in trials):
            best = choose(trials)
            entry["chosen"] = {"trial": best, "values": trials[best]["values"], "params": trials[best]["params"],
                               "feasible": trials[best]["score"]["feasible"],
                               "objective": trials[best]["score"]["objective"]}
        record["methods"][method] = entry
    return record, missing


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="work directory (created; resumable)")
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml", help="params file (default: the checkout's)")
    ap.add_argument("--profile", choices=config.PROFILES, help="scale profile (default: params.yaml's)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a params key (YAML value), e.g. tuning.trials=2; recorded")
    ap.add_argument("--methods", nargs="*", help="tuned methods (default: every key of tuning.methods)")
    ap.add_argument("--priors", type=Path, help="take <family>.pt from this folder instead of pretraining")
    ap.add_argument("--deadline", type=float,
                    help="seconds: start no unit that would not finish by then (under GCA_STOP_AT: start units until "
                         "TAIL_START_S before it; one cut off there resumes next launch)")
    ap.add_argument("--shard", default="0/1", help="k/n: run every n-th unit from the k-th (one process per GPU)")
    ap.add_argument("--claim", type=Path, metavar="DIR",
                    help="processes launched together take units as they free up, each claimed by a file in DIR "
                         "(empty it before the launch) instead of every n-th by --shard: none idles while units are left")
    ap.add_argument("--record", type=Path, default=ROOT / "tuning" / "record.json", help="the tuning record written")
    ap.add_argument("--device", default=None, help="cuda or cpu (default: cuda when visible)")
    ap.add_argument("--no-prepare", action="store_true", help="the work directory's inputs exist: run no stage")
    ap.add_argument("--prepare-only", action="store_true", help="make the inputs and launch velocities, then stop")
    ap.add_argument("--jobs", type=int, default=default_jobs(),
                    help="stage processes at once while preparing the inputs (default: a quarter of the CPU cores)")
    ap.add_argument("--restore-state", type=Path, metavar="TGZ",
                    help="first unpack a --save-state archive into --work (units done elsewhere, checkpoints)")
    ap.add_argument("--save-state", type=Path, metavar="TGZ",
                    help="at the end write the units done, launch velocities and checkpoints to this archive")
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    start = time.monotonic()
    from gca.pipeline.train import check_mlp_kernel, default_device

    device = args.device or default_device()
    raw, resolved, cfg = load_config(args.params, args.profile, args.overrides)
    check_mlp_kernel(run_mlp_kernel(resolved), device)  # before any input is made
    if cfg.record:
        raise ConfigError(
            f"{args.params}: cites the tuning record {cfg.record} (tuning.record): its knobs hold that tuning's choice, "
            "and a tuning's trials and unit stamps are drawn from the params before it, so every unit would be "
            "redone. To re-make or extend that tuning, pass --params with the params.yaml of its commit (`git show "
            "<record's commit>:params.yaml > base.yaml`); to tune anew around the chosen values, --set \"tuning.record=''\"")
    methods = args.methods or list(cfg.methods)
    for m in methods:
        cfg.knobs(m)
    k, _, n = args.shard.partition("/")
    shard, shards = int(k), int(n or 1)
    if not 0 <= shard < shards:
        raise ConfigError(f"--shard {args.shard}: expected k/n with 0 <= k < n")
    params_raw = work_params(raw, cfg)
    params = resolve(params_raw, params_raw["profile"])
    params["profile"] = params_raw["profile"]
    from gca.pipeline import schema
    schema.validate(params, "tune")
    if args.restore_state is not None:
        print(f"tune: {restore_state(args.restore_state, args.work)} files restored from {args.restore_state}")
    if not args.no_prepare:
        prepare_inputs(args.work, params_raw, args.priors, workers=max(1, args.jobs))
    if args.prepare_only:
        for scene in cfg.scenes:
            for seed in cfg.seeds:
                launch_velocity(args.work, params, scene, seed, device)
        print(f"tune: inputs and launch velocities of {', '.join(cfg.scenes)} ready in {args.work}")
        return {}
    todo = [u for j, u in enumerate(units_of(cfg, methods)) if j % shards == shard]
    if args.claim is not None:  # units cut off (in or after training) first: they finish soonest, free their checkpoints
        todo.sort(key=lambda u: not in_progress(args.work, *u))
    trials = {m: trial_values(cfg, m, params) for m in methods}
    costs = []
    for j, (method, trial, scene, seed) in enumerate(todo):
        path = unit_path(args.work, method, trial, scene, seed)
        checkpoint = unit_run_dir(args.work, method, trial, scene, seed) / "checkpoint.pt"
        if done_unit(path, unit_stamp(params, cfg, method, trials[method][trial], scene, seed)) is not None:
            stamp.clear_checkpoint(checkpoint)  # one a stop left between the result's write and its clearing
            continue
        why_not = no_start(time.monotonic() - start, costs, args.deadline, stop.deadline(), time.time())
        if why_not:
            print(f"tune: {why_not}; stopping (repeat the command)")
            break
        if args.claim is not None and not claim_unit(args.claim, method, trial, scene, seed):
            continue  # another process of this launch runs it
        t0 = time.monotonic()
        result = run_unit(args.work, params, cfg, method, trial, trials[method][trial], scene, seed, device)
        write_json(path, result)
        stamp.clear_checkpoint(checkpoint)
        costs.append(time.monotonic() - t0)
        cd = result["chamfer_mean"]
        print(f"tune {method} trial {trial}/{cfg.trials - 1} {scene} seed {seed}: {result['status']} "
              f"CD={cd if cd is None else f'{cd:.4g}'} in {costs[-1]:.0f} s ({j + 1}/{len(todo)} units of this shard)",
              flush=True)
    record, missing = build_record(args.work, params, cfg, methods, device, args.overrides)
    write_json(args.work / "tuning" / "record.partial.json", record)
    if args.save_state is not None:
        print(f"tune: {save_state(args.work, args.save_state)} state files saved to {args.save_state}")
    if missing:
        print(f"tune: {missing} units left (all shards); repeat the command (done units are kept)")
        return record
    args.record.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.record, record)
    try:
        shown = args.record.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        shown = str(args.record)
    print(f"tune: wrote {args.record}; the params.yaml change to apply (and cite):\n{params_change(record, shown)}")
    return record


if __name__ == "__main__":
    sys.exit(cli.run(main))
