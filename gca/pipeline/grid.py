"""The pipeline's stage commands for a scene x method grid, run through a job engine (``gca.pipeline.dispatch``).

What ``dvc repro`` runs, as separate jobs: the stage commands are read from ``dvc.yaml`` and expanded for
the scenes, their objects and prior families; the order comes from the stages' deps and outs. A scene's
``train`` stage is split into one job per (method, seed) run (each seed's first estimates its launch velocity, the
seed's others reuse it with ``--velocity``; ``--runs-per-job N`` puts N runs in one job), so one scene's runs
train on several GPUs at once. A scene's input stages (assets, particles, ground_truth, preprocess, then its first
seed's launch-velocity fit where the prior is made already) run as one job in one process (:func:`chain_inputs`,
``gca.pipeline.chain``; ``--no-chain``: one job each). Each job runs through the engine (``--engine``): ``local`` (submitit's local
executor: one process per GPU slot, ``--slots`` jobs per GPU, pinned with ``CUDA_VISIBLE_DEVICES``) or
``slurm`` (one SLURM job of one GPU per stage command, ordered by ``afterok`` dependencies). The outputs
land where ``dvc repro`` puts them:

- ``--work DIR``: a work directory made here (no dvc needed: a GPU machine), params.yaml restricted to
  ``--scenes``, the code linked; the ``report`` stage reads the results as it always does.

      python -m gca.pipeline.grid --work /tmp/t1 --scenes ball duck pawn cat fish bottle \
          --methods gca neuma nclaw --profile paper --gpus 4 --slots 2 --deadline 540 \
          --before "python3 -c 'from gsplat.cuda._backend import _C'"

- ``--repo DIR``: in place in a DVC repository with its own params.yaml; ``--commit`` ends with
  ``dvc commit -f`` of every finished stage, so ``dvc repro`` afterwards restores them and computes nothing.

      python -m gca.pipeline.grid --repo . --engine slurm --partition gpu --timeout-min 240 --commit

Resumable: a finished job leaves ``<work>/.grid/<job>.done`` and is not run again; training resumes from
its checkpoint (also after the engine's requeue at a time limit or a preemption). ``--deadline`` [s]
bounds the command: it submits no job that its estimated cost would not finish in time, except training
jobs (resumable: submitted while ``dispatch.RESUMABLE_MIN_S`` remain), and at the deadline stops the jobs
still running (on this machine by its stop file first, a signal only if it has not ended ``dispatch.STOP_REQUEST_S``
later: a training job checkpoints at its iteration's end; the command then waits for them to end, at most
1.5 x ``dispatch.STOP_GRACE_S`` + 10 s past the deadline), so a long grid runs
as a few commands of bounded length (repeat the command until it reports every job done). A failed job
is logged with its log path, its dependents are skipped, the others go on. ``--priors DIR`` takes
``<family>.pt`` from an earlier run instead of pretraining. ``--save-state``/``--restore-state`` carry a
``--work`` grid to another machine (the runs' results and laws, the evaluations' JSON, no checkpoint; inputs are
remade only where a job left reads them): ``benchmarks/table_bundle.sh`` runs a table that way on one GPU across sessions.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Callable

import yaml

from gca import gpu_slot
from gca.pipeline import dispatch, timeline
from gca.stamp import fingerprint
from gca.pipeline.dispatch import critical_path, gpu_ids  # noqa: F401 (this module's API before the engine)

ROOT = Path(__file__).resolve().parents[2]  # the checkout: params.yaml, dvc.yaml, stages/

# Estimated cost of a job [GPU-minutes, paper profile, one H100, alone]: for priorities (longest path
# first) and --deadline. From benchmarks/NOTES.md; a job that takes longer only delays the grid. The trained
# methods' ratios to GCA from the tuning's 24 units each under 8-way MPS (tuning/record.json: mean train_seconds GCA
# 628, NeuMA 562, PAC-NeRF-style 579); multi-view rows render three views: ~1.3x their monocular row (a guess).
# The report: 11-14 s on the H200 with its process start (session 48; 0.3 had its deadline estimate at 23 s).
COST = {"assets": 0.4, "particles": 0.8, "prior": 6.0, "ground_truth": 0.6, "preprocess": 0.1,
        "train": 0.6, "train:gca": 4.5, "train:neuma": 4.0, "train:neuma_multiview": 5.5,
        "train:pacnerf_depth": 4.2, "train:pacnerf_depth_aligned": 4.2, "train:pacnerf_multiview": 5.5,
        "train:gca_full_ft": 6.0, "evaluate": 0.8, "report": 0.2, "demo": 1.0}


def train_cost(method: str) -> float:
    """:data:`COST` of training ``method``: its own entry, else GCA's for a method that trains (Table 3's
    ablations are GCA with terms off), else ``train`` (NCLaw: the stage's start-up only)."""
    from gca.train.methods import METHODS

    if f"train:{method}" in COST:
        return COST[f"train:{method}"]
    return COST["train:gca"] if method in METHODS and METHODS[method].trains else COST["train"]


@dataclasses.dataclass
class Job:
    """One stage command. ``deps``/``outs``: paths relative to the work directory."""

    name: str
    cmd: str
    deps: list[str]
    outs: list[str]
    cost: float
    after: set[str] = dataclasses.field(default_factory=set)  # names of jobs that must finish first
    members: list[str] = dataclasses.field(default_factory=list)  # a chain's jobs (:func:`chain_inputs`), else none


def _walk(node, dotted: str):
    """``node[a][b]...`` for ``dotted = "a.b..."``."""
    for k in dotted.split("."):
        node = node[k]
    return node


def _interpolate(text: str, params: dict, key: str | None = None, item=None) -> str:
    """dvc.yaml's ``${...}``: ``${key}``/``${item.x}`` of a foreach, anything else from params."""
    def one(m: re.Match) -> str:
        ref = m.group(1)
        if key is not None and ref == "key":
            return key
        if key is not None and ref.startswith("item."):
            return str(_walk(item, ref[len("item."):]))
        return str(_walk(params, ref))
    return re.sub(r"\$\{([^}]+)\}", one, text)


def _foreach_items(spec: str, params: dict) -> dict:
    """The mapping a ``foreach: ${a.b}`` ranges over, from params."""
    m = re.fullmatch(r"\$\{([^}]+)\}", spec.strip())
    if not m:
        raise ValueError(f"dvc.yaml: foreach {spec!r} is not a ${{...}} reference")
    return _walk(params, m.group(1))


def _paths(entries) -> list[str]:
    out = []
    for e in entries or []:
        out.extend(e.keys() if isinstance(e, dict) else [e])
    return [str(p) for p in out]


def expand(dvc: dict, params: dict, stages: list[str] | None = None) -> dict[str, Job]:
    """The stage jobs of ``dvc.yaml`` for ``params`` (its foreach over objects, families and scenes),
    with ``${profile}`` and the other top-level params substituted; ``stages``: keep only these."""
    jobs = {}
    for name, stage in dvc["stages"].items():
        if stages is not None and name not in stages:
            continue
        if "foreach" in stage:
            items = _foreach_items(stage["foreach"], params).items()
            body = stage["do"]
        else:
            items, body = [(None, None)], stage
        for key, item in items:
            sub = lambda t, key=key, item=item: _interpolate(t, params, key, item)  # noqa: E731
            job_name = f"{name}@{key}" if key is not None else name
            jobs[job_name] = Job(job_name, sub(" ".join(body["cmd"].split())), [sub(p) for p in _paths(body.get("deps"))],
                                 [sub(p) for p in _paths(body.get("outs"))] + [sub(p) for p in _paths(body.get("metrics"))],
                                 COST.get(name, 1.0))
    return jobs


def split_train(jobs: dict[str, Job], params: dict) -> dict[str, Job]:
    """``train@<scene>`` -> one job per (method, seed of ``train.seeds``): ``train@<scene>:<run>`` with the run's
    name (``gca``, ``gca@seed1``); the first job of each seed (the cheapest method's) estimates that seed's launch
    velocity from its own observations (``velocity.json``, ``velocity@seed<k>.json``), the seed's other jobs
    reuse it."""
    from gca.pipeline.train import velocity_path

    def runs_of(name: str, job: Job, scene: str, runs, seeds: str) -> dict[str, Job]:
        run_dir = re.search(r"--out (\S+)", job.cmd).group(1)
        out, firsts = {}, {}  # firsts: seed -> the job that estimates its launch velocity (from its own observations)
        for method, s, run in runs:
            m = method.name
            first = firsts.get(s)
            velocity = velocity_path(Path(run_dir), s).as_posix()
            cmd = f"{job.cmd} --methods {m}" + seeds.format(s)
            if first is not None:
                cmd += f" --velocity {velocity}"
            j = Job(f"{name}:{run}", cmd, list(job.deps), [f"{run_dir}/{run}"] + ([] if first else [velocity]),
                    train_cost(m))
            if first is not None:
                j.after.add(first)
            firsts.setdefault(s, j.name)
            out[j.name] = j
        return out

    return _per_run(jobs, params, "train@", runs_of,
                    order=lambda methods: sorted(methods, key=train_cost))


def split_evaluate(jobs: dict[str, Job], params: dict) -> dict[str, Job]:
    """``evaluate@<scene>`` -> one job per trained run (:func:`split_train`'s): ``evaluate@<scene>:<run>``, after
    that run's training only (its deps name the run's folder and its seed's launch velocity, not the scene's whole
    ``runs/<scene>``), writing ``metrics/eval/<scene>/<run>.json`` and its media folder. So a run is evaluated as
    soon as it is trained (no scene-wide tail at the end of a table), a short job is cut less often by a deadline,
    and a grid grown by methods (Table 3's rows after Table 1's) evaluates only the new runs."""
    from gca.pipeline.train import velocity_path

    def runs_of(name: str, job: Job, scene: str, runs, seeds: str) -> dict[str, Job]:
        if not runs:  # a calibration scene: its (empty) evaluation folder is still the stage's output
            return {name: job}
        runs_dir = re.search(r"--runs (\S+)", job.cmd).group(1)
        eval_dir = re.search(r"--out (\S+)", job.cmd).group(1)
        n_methods = len(params["scenes"][scene]["methods"])
        out = {}
        for method, s, run in runs:
            deps = [d for d in job.deps if d != runs_dir] + [f"{runs_dir}/{run}", velocity_path(Path(runs_dir), s).as_posix()]
            out[f"{name}:{run}"] = Job(f"{name}:{run}", f"{job.cmd} --methods {method.name}" + seeds.format(s), deps,
                                       [f"{eval_dir}/{run}.json", f"{eval_dir}/{run}"], job.cost / n_methods)
        return out

    return _per_run(jobs, params, "evaluate@", runs_of)


def _per_run(jobs: dict[str, Job], params: dict, prefix: str, runs_of, order=list) -> dict[str, Job]:
    """``jobs`` with each per-scene job of stage ``prefix`` (``train@``, ``evaluate@``) replaced by
    ``runs_of(name, job, scene, runs, seeds)``: ``runs`` the scene's ``(method, seed, run name)``
    (:func:`gca.pipeline.train.seed_runs`, its methods in ``order(methods)``), ``seeds`` the command's seed option
    as a format string of the seed (empty when ``train.seeds`` has one seed)."""
    from gca.config import resolve
    from gca.train.methods import get_method
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import seed_runs

    resolved = Settings(resolve(params, params["profile"]))
    seeds = " --seeds {}" if len(resolved.train.seeds) > 1 else ""
    out = {}
    for name, job in jobs.items():
        if not name.startswith(prefix):
            out[name] = job
            continue
        scene = name.split("@", 1)[1]
        methods = [get_method(m) for m in order(params["scenes"][scene]["methods"])]
        out.update(runs_of(name, job, scene, seed_runs(resolved, methods), seeds))
    return out


def split_runs(jobs: dict[str, Job], params: dict) -> dict[str, Job]:
    """:func:`split_train` then :func:`split_evaluate`: one training job and one evaluation job per run."""
    return split_evaluate(split_train(jobs, params), params)


def _under(path: str, root: str) -> bool:
    return path == root or path.startswith(root.rstrip("/") + "/")


def link(jobs: dict[str, Job]) -> dict[str, Job]:
    """Job B runs after job A when one of B's deps is (under) one of A's outs or A's out is under B's dep."""
    for b in jobs.values():
        for a in jobs.values():
            if a is not b and any(_under(d, o) or _under(o, d) for d in b.deps for o in a.outs):
                b.after.add(a.name)
    return jobs


OBJECT_CHAIN = ("assets", "particles")  # an object's input stages, one after the other
SCENE_CHAIN = ("ground_truth", "preprocess")  # then its scene's


def velocity_job(jobs, scene: str) -> str | None:
    """The training job that estimates ``scene``'s launch velocity for its first seed (:func:`split_train`: the seed's
    cheapest run, NCLaw's in Table 1, with ``runs/<scene>/velocity.json`` among its outs); None where there is none."""
    for name, job in jobs.items():
        if name.startswith(f"train@{scene}:") and any(o.endswith(f"{scene}/velocity.json") for o in job.outs):
            return name
    return None


def input_chains(params: dict, jobs=None) -> list[tuple[str, list[str]]]:
    """The grid's chains of input jobs, ``(name, member jobs in order)``: ``inputs@<scene>`` for a scene whose object
    no other scene of the grid has (its object's :data:`OBJECT_CHAIN` then its :data:`SCENE_CHAIN`); where scenes share
    an object, ``object@<object>`` (its object stages, once) and each scene's ``inputs@<scene>`` (its scene stages).
    A scene's chain ends with its first seed's launch-velocity job (:func:`velocity_job` among ``jobs``): the ~30-s
    fit every run of that seed waits on, a training job started by its own process otherwise (session 47)."""
    by_object: dict[str, list[str]] = {}
    scenes = params.get("scenes") if isinstance(params, dict) else None
    for scene, spec in (scenes if isinstance(scenes, dict) else {}).items():  # --repo: maybe not this project's
        if isinstance(spec, dict) and isinstance(spec.get("object"), str):
            by_object.setdefault(spec["object"], []).append(scene)
    chains = []
    for obj, scenes in by_object.items():
        head = [f"{stage}@{obj}" for stage in OBJECT_CHAIN]
        tails = {s: [f"{stage}@{s}" for stage in SCENE_CHAIN] + [v for v in [velocity_job(jobs or {}, s)] if v]
                 for s in scenes}
        if len(scenes) == 1:
            chains.append((f"inputs@{scenes[0]}", head + tails[scenes[0]]))
        else:
            chains += [(f"object@{obj}", head)] + [(f"inputs@{s}", tail) for s, tail in tails.items()]
    return chains


def chain_undone(jobs: dict[str, Job], params: dict, work: Path, stamp: str) -> dict[str, Job]:
    """:func:`chain_inputs` of ``jobs`` in work folder ``work``: the jobs whose ``.done`` marker holds ``stamp`` count
    done (the grid's and the tuning's calibration inputs, ``gca.pipeline.tune.prepare_inputs``)."""
    return chain_inputs(jobs, params, {n for n in jobs if dispatch.is_done(work, n, stamp)}, stamp)


def chain_inputs(jobs: dict[str, Job], params: dict, done=frozenset(), stamp: str = "") -> dict[str, Job]:
    """``jobs`` (linked) with each of :func:`input_chains`' chains of jobs not ``done`` put in one job that runs them
    one after the other in one process (``gca.pipeline.chain``; ``stamp``: what its members' ``.done`` markers hold):
    a data stage on the H200 spent ~10 s starting (imports, CUDA, warp) for 1.4-11.4 s of work, four of them one
    after the other before a scene's first training (NOTES session 47). A member joins its chain only while each
    job it waits on is in the chain or waited on by the chain already (so the chain's job waits on nothing its
    members make); a chain of one job is left as it was. The jobs after a member wait on the chain's job instead. A
    launch-velocity fit in a chain runs at MPS's normal priority whatever its unit's (:func:`below_normal` judges
    per-run jobs; the fit runs before any training, on a GPU the inputs leave mostly idle)."""
    from gca.pipeline import chain

    out = dict(jobs)
    renamed: dict[str, str] = {}
    for name, names in input_chains(params, jobs):
        members: list[Job] = []
        needs: set[str] = set()
        for m in names:
            if m not in jobs or m in done:
                continue
            inside = {j.name for j in members}
            waits = {a for a in jobs[m].after if a in jobs and a not in done}  # a job not here is up to date
            if members and not waits <= inside | needs:
                break
            members.append(jobs[m])
            needs |= waits - inside
        if len(members) < 2:
            continue
        inside = [j.name for j in members]
        for m in inside:
            del out[m]
            renamed[m] = name
        out[name] = Job(name, chain.command([(j.name, j.cmd) for j in members], stamp),
                        list(dict.fromkeys(d for j in members for d in j.deps)),
                        list(dict.fromkeys(o for j in members for o in j.outs)), sum(j.cost for j in members),
                        set().union(*(j.after for j in members)) - set(inside), inside)
    for n, job in out.items():  # a copy where it changes: the jobs given stay as they were
        after = {renamed.get(a, a) for a in job.after} - {n}
        if after != job.after:
            out[n] = dataclasses.replace(job, after=after)
    return out


def members_state(state: dict[str, str], jobs: dict[str, Job], done: Callable[[str], bool] = lambda m: False) -> dict[str, str]:
    """A grid's job states with each chain's (:func:`chain_inputs`) given to its members, a member that ``done(m)``
    says finished (its own ``.done`` marker: the members before a failed or stopped one) done (``dvc commit`` of a
    stage whose jobs are all done)."""
    out = {}
    for name, s in state.items():
        members = jobs[name].members if name in jobs else []
        out.update({m: dispatch.DONE if done(m) else s for m in members} if members else {name: s})
    return out


def batch_runs(jobs: dict, runs_per_job: int) -> dict:
    """Training jobs of :func:`split_train` (one per run) put together ``runs_per_job`` at a time: the runs
    of one scene and one seed after the first (which estimates the launch velocity), in their order, as one
    ``--methods a b ...`` command (where starting a process costs more than the parallelism gains: a
    CPU); so are the evaluation jobs of :func:`split_evaluate`, all runs of a scene and seed. Jobs not linked yet
    (``after``: only the velocity job)."""
    if runs_per_job <= 1:
        return jobs
    out, groups = {}, {}
    for name, job in jobs.items():
        m = re.search(r"--methods (\S+)", job.cmd)
        runs = (name.startswith("train@") and job.after) or (name.startswith("evaluate@") and ":" in name)
        if not runs or m is None:
            out[name] = job
            continue
        seed = re.search(r"--seeds (\S+)", job.cmd)
        key = (name.split(":", 1)[0], seed.group(1) if seed else None)
        group = groups.setdefault(key, [])
        if not group or len(group[-1]) == runs_per_job:
            group.append([])
        group[-1].append(job)
    for batches in groups.values():
        for batch in batches:
            first = batch[0]
            methods = " ".join(re.search(r"--methods (\S+)", j.cmd).group(1) for j in batch)
            name = "+".join([first.name] + [j.name.split(":", 1)[1] for j in batch[1:]])
            deps = list(dict.fromkeys(d for j in batch for d in j.deps))  # an evaluation reads each run's folder
            out[name] = type(first)(name, re.sub(r"--methods \S+", f"--methods {methods}", first.cmd), deps,
                                    [o for j in batch for o in j.outs], sum(j.cost for j in batch), set(first.after))
    return out


def repo_jobs(repo: Path, stages: list[str] | None, runs_per_job: int = 1, changed: set[str] | None = None) -> dict:
    """The jobs of a DVC repository's ``dvc.yaml`` with its own ``params.yaml`` (nothing rewritten);
    ``changed``: keep only the jobs of these stages (what ``dvc status`` lists) and the jobs after them; the
    others are up to date."""
    params = yaml.safe_load((repo / "params.yaml").read_text())
    jobs = expand(yaml.safe_load((repo / "dvc.yaml").read_text()), params, stages)
    if any(n.startswith(("train@", "evaluate@")) for n in jobs):
        jobs = batch_runs(split_runs(jobs, params), runs_per_job)
    jobs = link(jobs)
    if changed is None:
        return jobs
    keep = {n for n in jobs if n.split(":", 1)[0] in changed}
    for n in list(keep):
        keep |= dispatch.dependents(jobs, n)
    return {n: j for n, j in jobs.items() if n in keep}


def dvc_changed(repo: Path) -> set[str] | None:
    """The stages ``dvc status`` lists in ``repo`` (changed or never run); None without dvc."""
    out = subprocess.run([sys.executable, "-m", "dvc", "status", "--json"], cwd=repo, capture_output=True, text=True)
    if out.returncode != 0:
        return None
    return set(json.loads(out.stdout.strip().splitlines()[-1] if out.stdout.strip() else "{}"))


def inputs_stamp(repo: Path) -> str:
    """Digest of ``params.yaml`` and ``dvc.yaml``: a job finished under other params is not done."""
    import hashlib

    return hashlib.sha256(b"".join((repo / f).read_bytes() for f in ("params.yaml", "dvc.yaml"))).hexdigest()[:16]


def grid_params(profile: str, scenes: list[str], methods: list[str] | None, overrides: list[str]) -> dict:
    """params.yaml restricted to ``scenes`` (and the objects and prior families they need)."""
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    raw["profile"] = profile
    unknown = [s for s in scenes if s not in raw["scenes"]]
    if unknown:
        raise SystemExit(f"params.yaml: unknown scene(s) {unknown}; valid: {sorted(raw['scenes'])}")
    raw["scenes"] = {s: dict(raw["scenes"][s]) for s in scenes}
    if methods:
        for s in scenes:
            raw["scenes"][s]["methods"] = list(methods)
    objects = {spec["object"] for spec in raw["scenes"].values()}
    raw["objects"] = {k: v for k, v in raw["objects"].items() if k in objects}
    families = {spec["prior"] for spec in raw["scenes"].values()}
    raw["prior"]["families"] = {k: v for k, v in raw["prior"]["families"].items() if k in families}
    raw["demo"]["captures"] = {k: v for k, v in raw["demo"].get("captures", {}).items() if k in raw["scenes"]}
    return apply_overrides(raw, overrides)


def apply_overrides(params: dict, overrides: list[str]) -> dict:
    """Set each ``dotted.key=yaml_value`` in ``params`` (in place; missing sections are created)."""
    for item in overrides:
        key, _, value = item.partition("=")
        *head, last = key.split(".")
        node = params
        for k in head:
            node = node.setdefault(k, {})
        node[last] = yaml.safe_load(value)
    return params


def scene_inputs(work: Path, scene_name: str, params: dict, prior_dir: Path | None = None):
    """The :class:`gca.pipeline.train.SceneInputs` of a scene in a grid (or pipeline) work directory: its data
    where ``dvc repro`` puts them, the prior from ``prior_dir`` (default ``<work>/models/prior``)."""
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import SceneInputs

    scene = Settings(params).scene(scene_name)
    return SceneInputs(work / f"data/scenes/{scene_name}", work / f"data/prep/{scene_name}",
                       work / f"data/particles/{scene.object}.npz", work / f"data/assets/{scene.object}/gaussians.ply",
                       (prior_dir or work / "models/prior") / f"{scene.prior}.pt")


def prepare(work: Path, params: dict) -> None:
    """The work directory as a checkout: the code linked, its own params.yaml, and the tuning record it cites
    (``tuning.record``, the report's tuning page) linked as a file: not the checkout's ``tuning/`` folder, where a
    tuning's work directory (made here too) would then write its units."""
    work.mkdir(parents=True, exist_ok=True)
    for name in ("stages", "gca", "dvc.yaml"):
        target = work / name
        if not target.exists():
            target.symlink_to(ROOT / name)
    cited = str((params.get("tuning") or {}).get("record") or "")
    if cited and (ROOT / cited).is_file() and not (work / cited).exists():
        (work / cited).parent.mkdir(parents=True, exist_ok=True)
        (work / cited).symlink_to(ROOT / cited)
    (work / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    (work / ".grid").mkdir(exist_ok=True)


#: an evaluation's media (``metrics/<eval|demo|...>/<scene>/<run>/*.gif|png|mp4``): :func:`collect` puts them in an
#: archive of their own, so the results' archive stays small
MEDIA = re.compile(r"^metrics/.+/[^/]+/[^/]+/[^/]+\.(gif|png|mp4)$")
#: the media archive's bytes at most: the device tool brings back files of at most 16 MiB (session 56: a three-seed
#: table's 54 rollout GIFs took one archive over it, and its report, metrics and laws stayed on the machine)
MEDIA_CAP = 15 * 2 ** 20


def collect(work: Path, out: Path) -> Path:
    """The small results of a grid in one archive, ``grid_results.tar.gz``: metrics, reports, train/eval summaries,
    the learned laws (~40 kB each: a run can be evaluated again elsewhere), priors, logs; and the evaluations' media
    (:data:`MEDIA`) beside it in ``grid_media.tar.gz``, the PNGs first, then the GIFs, added while their bytes stay
    under :data:`MEDIA_CAP` (the rest left out, counted in a printed line). Also of a grid that runs meanwhile
    (:func:`_listed`, ``gca.io.add_file``). Beside them ``timeline.png``, when each job ran
    (:mod:`gca.pipeline.timeline`). Returns the results' archive."""
    from gca.io import add_file

    out.mkdir(parents=True, exist_ok=True)
    path = out / "grid_results.tar.gz"
    keep = re.compile(r"^(metrics/.*|reports/.*|models/prior/.*|runs/[^/]+/velocity(@seed[0-9]+)?\.json|"
                      r"runs/[^/]+/[^/]+/(train|history)\.json|runs/[^/]+/[^/]+/(loss\.png|law\.pt)|\.grid/(?!carried/).*|params\.yaml)$")
    results, media = [], []
    for item in _listed(work):
        if keep.match(item[1]) and item[2] < 8 * 2 ** 20:
            (media if MEDIA.match(item[1]) else results).append(item)
    with tarfile.open(path, "w:gz") as tar:
        for f, rel, _ in results:
            add_file(tar, f, rel)  # passes over a file gone since the listing
    # the still images first (a run's strip and CD curve, ~90 kB), then the animations (~250-370 kB a GIF)
    media.sort(key=lambda item: (not item[1].endswith(".png"), item[1]))
    if media:
        added, left = 0, []
        with tarfile.open(out / "grid_media.tar.gz", "w:gz") as tar:
            for f, rel, size in media:
                if added + size > MEDIA_CAP:
                    left.append(rel)
                    continue
                add_file(tar, f, rel)
                added += size
        if left:
            print(f"[grid] media: {len(left)} of {len(media)} files left out of grid_media.tar.gz (over "
                  f"{MEDIA_CAP // 2 ** 20} MiB), e.g. {left[0]}")
    log = work / ".grid" / "grid.log"
    if log.is_file():  # where the grid's time went: gca.pipeline.timeline's plot beside the archive
        try:
            timeline.from_log(log, out / "timeline.png")
        except Exception as err:  # noqa: BLE001 (a plot is no result: a log without grid lines yet, matplotlib's
            print(f"[grid] timeline: no plot ({type(err).__name__}: {err})")  # own errors; the archive stands)
    return path


# What a --work grid needs to go on elsewhere (another machine, a later session), kept small (it travels with the
# checkout, under the device tool's 64-MiB carry with the GPU wheels: ~45 kB a run): the finished training and
# evaluation jobs' markers, each run's result and learned law, the launch velocities, the evaluations' JSON (what
# the tables read). Not a run's checkpoint (of a run cut off mid-training): another machine remakes the inputs,
# which differ in float32 noise, so the checkpoint's stamp would not match there and the run would train afresh
# (session 20); carried, it made the lease check take seven such runs for resumable (session 22: they started in a
# call that could not finish them). Older states that hold checkpoints still restore, without them. Not the inputs
# (assets, particles, ground truth, preprocessing: remade from params, only where a job still needs them,
# :func:`needed`), nor what nothing downstream reads: histories, loss curves, evaluation media, the MLflow store (each
# call returns them: --collect, the bundle).
STATE_RE = re.compile(r"^(\.grid/(train|evaluate)@[^/]+\.done|runs/[^/]+/velocity(@seed[0-9]+)?\.json|"
                      r"runs/[^/]+/[^/]+/(train\.json|law\.pt|checkpoint\.pt(\..+)?)|metrics/eval/[^/]+/[^/]+\.json)$")
CHECKPOINT_RE = re.compile(r"(^|/)checkpoint\.pt(\..+)?$")  # a run's checkpoint and its stamp: never in a state
STATE_PARAMS = ".grid/state_params.json"  # what the state was made under: the params' digest and each scene's methods


def _made_under(work: Path) -> dict:
    """The grid's params.yaml as a state records it. A grid may grow by methods (Table 3's rows after Table 1's) and
    by scenes (Tables 2, 5, 6 after them: one state, one report, one claims table), so the record is: ``digest``, of
    everything that is not a scene's (the scenes, their objects, prior families and demo captures taken out);
    ``scenes``, each scene's own digest (its spec but ``methods``, its object, its prior family, its capture);
    ``methods``, each scene's methods. The train knobs that change only how the same numbers are computed
    (:data:`gca.train.config.EXECUTION_ONLY`, at their rounding-equal values) are not recorded."""
    from gca.config import resolve
    from gca.train.config import EXECUTION_ONLY

    params = yaml.safe_load((work / "params.yaml").read_text())
    train = params.get("train") or {}
    for knob, equal_at in EXECUTION_ONLY.items():  # a {paper: a, ci: b} switch judged at the grid's profile
        if knob in train and (equal_at is None or resolve(train[knob], params.get("profile", "paper")) in equal_at):
            del train[knob]
    scenes = params.pop("scenes")
    objects = params.pop("objects", {})
    families = (params.get("prior") or {}).pop("families", {})
    captures = (params.get("demo") or {}).pop("captures", {})
    methods = {name: list(spec.get("methods", [])) for name, spec in scenes.items()}
    own = {name: fingerprint({}, (), extra={"scene": {k: v for k, v in spec.items() if k != "methods"},
                                            "object": objects.get(spec.get("object")),
                                            "prior": families.get(spec.get("prior")), "capture": captures.get(name)})
           for name, spec in scenes.items()}
    return {"digest": fingerprint({}, (), extra=params), "scenes": own, "methods": methods}  # gca.stamp's hash


def state_files(work: Path) -> list[str]:
    """:data:`STATE_RE`'s files in ``work`` (relative, sorted; files of 64 MiB or more and checkpoints,
    :data:`CHECKPOINT_RE`, are left out)."""
    return [rel for _, rel, size in _listed(work)
            if STATE_RE.match(rel) and not CHECKPOINT_RE.search(rel) and size < 64 * 2 ** 20]


def _listed(work: Path, tries: int = 3) -> list[tuple[Path, str, int]]:
    """(path, path relative to ``work``, size [B]) of each plain file (not a link) under ``work``, sorted. Also of a
    grid that runs meanwhile (table_bundle.sh's snapshots): a file gone between the listing and its size is passed
    over, and a listing that a folder removed midway broke (``rglob`` raises; a temporary folder of
    ``gca.io.atomic_path``) is made again."""
    for attempt in range(tries):
        try:
            paths = sorted(work.rglob("*"))
            break
        except FileNotFoundError:
            if attempt == tries - 1:
                raise
    out = []
    for f in paths:
        try:
            if f.is_file() and not f.is_symlink():
                out.append((f, f.relative_to(work).as_posix(), f.stat().st_size))
        except FileNotFoundError:
            continue
    return out


CARRIED = ".grid/carried"  # a restored state's files of scenes or methods this grid lacks (restore_state): not
# unpacked where the grid reads, handed on unchanged by save_state, so a grid over a subset of a state never drops
# the rest of it


def member_in(name: str, methods: dict[str, list[str]]) -> bool:
    """Whether a state or records member ``name`` is this grid's: its scene is one of ``methods`` ({scene: that
    scene's methods}, :func:`_made_under`) and each run it names is of one of them (``train@ball:gca@seed1.done``,
    ``runs/ball/gca@seed1/...``, ``metrics/eval/ball/gca@seed1.json`` or ``.../gca@seed1/strip.png``; a scene's
    launch estimate ``runs/ball/velocity@seed1.json`` is the scene's alone). Anything else is the grid's."""
    marker = re.match(r"^\.grid/(?:train|evaluate)@([^:/]+?)(?::(.+))?\.done$", name)
    parts = name.split("/")
    if marker:  # a scene-level marker (a calibration scene's ``evaluate@calib_torus``) is the scene's
        scene, runs = marker.group(1), marker.group(2).split("+") if marker.group(2) else []
    elif parts[0] == "runs" and len(parts) >= 3:
        scene, runs = parts[1], [] if len(parts) == 3 else [parts[2]]
    elif parts[:2] == ["metrics", "eval"] and len(parts) >= 4:
        scene, runs = parts[2], [parts[3].removesuffix(".json")]
    else:
        return True
    return scene in methods and all(run.split("@", 1)[0] in methods[scene] for run in runs)


def save_state(work: Path, archive: Path) -> int:
    """The grid's state (:func:`state_files` and what it was made under, :func:`_made_under`) in the gzipped tar
    ``archive`` (atomically), with what a restored state held for scenes or methods this grid lacks (:data:`CARRIED`,
    unchanged, and their part of the record); returns the file count."""
    from gca.io import pack_files, write_json

    made, carried = _made_under(work), work / CARRIED
    made_here = {scene: list(names) for scene, names in made["methods"].items()}
    files: list = [*state_files(work), STATE_PARAMS]
    if (carried / STATE_PARAMS).is_file():
        theirs = json.loads((carried / STATE_PARAMS).read_text())
        for scene, digest in theirs["scenes"].items():
            made["scenes"].setdefault(scene, digest)
        for scene, names in theirs["methods"].items():
            mine = made["methods"].setdefault(scene, [])
            mine += [m for m in names if m not in mine]
        files += [(carried / rel, rel) for rel in state_files(carried)  # what the grid lacks only: a grid that
                  if rel not in files and not member_in(rel, made_here)]  # grew back made its own again
    write_json(work / STATE_PARAMS, made)
    return pack_files(work, files, archive)


def restore_state(archive: Path, work: Path) -> int:
    """Unpack a :func:`save_state` archive into the prepared ``work`` (a file already there is kept); returns the
    count unpacked. The grid may have grown since by methods (only the new methods' runs are trained and evaluated)
    and by scenes (a new scene runs from nothing), or be a subset of it (``--methods gca neuma nclaw`` for Table 1's
    report from a state with Table 3's runs, ``--scenes ball duck`` for a machine that finishes those): the files
    of scenes or methods the grid lacks (:func:`member_in`) go to :data:`CARRIED`, where nothing reads them, and
    :func:`save_state` hands them on. Refused, with nothing written, when made under other params (seeds, profile or
    knobs but :data:`gca.train.config.EXECUTION_ONLY`'s; a scene of both defined otherwise here), or when it holds anything but state files. A checkpoint in an older state is not unpacked (:data:`CHECKPOINT_RE`:
    it would not resume on this machine's remade inputs, and the lease check would take its run for resumable)."""
    from gca.io import unpack_files

    if not archive.is_file():
        raise SystemExit(f"{archive}: no grid state there (written by --save-state)")
    with tarfile.open(archive, "r:gz") as tar:
        try:
            made = json.loads(tar.extractfile(STATE_PARAMS).read())
        except KeyError:
            raise SystemExit(f"{archive}: not a grid state (no {STATE_PARAMS})") from None
    here = _made_under(work)
    if "scenes" not in made:
        raise SystemExit(f"{archive}: a grid state of an older format (before session 19: it cannot grow by scenes); "
                         "use a new state file for this grid")
    if made["digest"] != here["digest"]:
        raise SystemExit(f"{archive}: made under other params than {work / 'params.yaml'} (other seeds, profile or "
                         "knobs); use a new state file for this grid")
    other = sorted(n for n, d in made["scenes"].items() if n in here["scenes"] and here["scenes"][n] != d)
    if other:
        raise SystemExit(f"{archive}: made under other params than {work / 'params.yaml'}: scene(s) {other} defined "
                         "otherwise (their spec, object, prior family or capture); use a new state file for this grid")
    lacked = {s: sorted(set(m) - set(here["methods"].get(s, []))) for s, m in made["methods"].items()}
    lacked = {s: m for s, m in lacked.items() if m or s not in here["scenes"]}  # a scene without methods too
    ours = lambda name: member_in(name, here["methods"])  # noqa: E731
    allowed = lambda name: name == STATE_PARAMS or bool(STATE_RE.match(name))  # noqa: E731
    try:  # a scene with new methods needs only their runs evaluated (one evaluation job per run: split_evaluate)
        n = unpack_files(archive, work, allowed, "grid state", skip=lambda name: bool(CHECKPOINT_RE.search(name))
                         or not ours(name))
        shutil.rmtree(work / CARRIED, ignore_errors=True)  # this archive's rest replaces an earlier restore's
        if lacked:
            aside = unpack_files(archive, work / CARRIED, allowed, "grid state",
                                 skip=lambda name: bool(CHECKPOINT_RE.search(name)) or (ours(name) and name != STATE_PARAMS))
            print(f"[grid] {archive}: {max(aside - 1, 0)} state files of runs this grid lacks ({lacked}) kept aside in "
                  f"{work / CARRIED}; --save-state hands them on")
    except ValueError as exc:
        raise SystemExit(str(exc)) from exc
    return n


def first_methods(methods) -> Callable[[str], bool] | None:
    """``dispatch.run``'s ``first``: whether a training job trains a run of one of ``methods`` (None: no order)."""
    if not methods:
        return None
    wanted = set(methods)
    return lambda name: name.startswith("train@") and any(
        run.split("@", 1)[0] in wanted for run in dispatch.job_runs(name)[1])


def evaluate_missing(work: Path, key: str, measured: str = "chamfer_mean") -> list[str]:
    """Evaluations done before ``key`` was measured (a metric added since: session 21's
    ``chamfer_mean_true_launch``): the ``evaluate@<scene>:<run>[+<run>...]`` jobs with a run whose metrics JSON
    measured ``measured`` but lacks ``key`` lose their ``.done`` marker, so the grid evaluates those runs again (the
    laws are kept; only their metrics are remade), and so does the report. Idempotent: an evaluation that recorded
    ``key`` (the stage writes it, None where not measured), or one without ``measured`` (a diverged rollout, a
    capture scene), stays done. Returns the jobs undone."""
    undone = []
    for marker in sorted((work / ".grid").glob("evaluate@*:*.done")):
        scene, runs = dispatch.job_runs(marker.stem)
        for run in runs:
            path = work / "metrics" / "eval" / scene / f"{run}.json"
            record = json.loads(path.read_text()) if path.is_file() else {}
            if measured in record and key not in record:
                marker.unlink()
                undone.append(marker.stem)
                break
    if undone:
        (work / ".grid" / "report.done").unlink(missing_ok=True)
    return undone


RECORDS_RE = re.compile(r"^(runs/[^/]+/[^/]+/(history\.json|loss\.png)|metrics/eval/[^/]+/[^/]+/[^/]+\.(png|gif))$")


def unpack_records(archive: Path, work: Path) -> int:
    """Unpack what the MLflow import reads beyond the state (:data:`RECORDS_RE`: histories, loss curves, evaluation
    media) of this grid's runs (:func:`member_in`) from ``archive`` into ``work`` (a file there is kept); other
    members are passed over."""
    from gca.io import unpack_files

    try:
        methods = _made_under(work)["methods"] if (work / "params.yaml").is_file() else None  # a grid over part of
        # the state: the other runs' records stay out
        return unpack_files(archive, work, lambda name: True, "records", skip=lambda name: not RECORDS_RE.match(name)
                            or (methods is not None and not member_in(name, methods)))
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(str(exc)) from exc


JOB_START_S = dispatch.JOB_START_S  # one source: the dispatcher's lease check counts the same start [s]


PACKING_OFFSET = 2.2  # runs' worth of a run's work that does not slow down with sharing the GPU: a run's time under
# k-way MPS goes as (PACKING_OFFSET + k); fit to the ball's 1.64, 2.6 and 4.4 s per iteration solo, 4- and 8-way
# (benchmarks/NOTES.md, session 16): (2.2 + 4) / (2.2 + 8) = 0.61 against 0.59 measured


def packed_seconds(seconds: float, ran: float, at: float) -> float:
    """Seconds of a run that took ``seconds`` sharing the GPU ``ran``-way (its marker's ``sharing``), were it
    packed ``at``-way (:data:`PACKING_OFFSET`)."""
    return seconds * (PACKING_OFFSET + at) / (PACKING_OFFSET + ran)


def finished_train_seconds(work: Path, slots: int | None = None) -> dict[str, dict[str, float]]:
    """``{method: {scene: the longest train_seconds}}`` of the runs in ``work/runs`` that finished ``ok`` (a diverged
    one stops early); with ``slots``, each as if packed ``slots``-way (:func:`packed_seconds`, from the sharing its
    training job's marker records: ``dispatch.record_sharing``; none recorded: taken as packed so). Session 21: a
    run timed 5-way (310 s) set the expectation of runs that then ran 8-way and outlasted the machine. A run timed
    in a call that gave MPS priorities (``mps_priority`` in its record: :func:`below_normal`; ``"mixed"`` for one
    stopped and resumed at another, ``gca.pipeline.train.merged_sharing``) is left out: its time is no equal share of
    the GPU."""
    shares = {}
    if slots:
        for path in (work / ".grid").glob("train@*:*.done"):
            scene, runs = dispatch.job_runs(path.stem)
            ran = dispatch.sharing(work, path.stem)
            for run in runs:
                shares[(scene, run)] = ran
    out: dict[str, dict[str, float]] = {}
    for path in (work / "runs").glob("*/*/train.json"):
        record = json.loads(path.read_text())
        if record.get("status") == "ok" and not record.get("mps_priority"):  # a priority call's times are not equal
            # shares (a below-normal run slower, a normal one beside it faster): no estimate learns from them
            scenes = out.setdefault(path.parent.name.split("@", 1)[0], {})
            scene = path.parent.parent.name
            seconds = float(record.get("train_seconds") or 0.0)
            ran = shares.get((scene, path.parent.name))
            if ran:
                seconds = packed_seconds(seconds, ran, slots)
            scenes[scene] = max(scenes.get(scene, 0.0), seconds)
    return out


def expected_train_s(work: Path, job: str, default: float, finished: dict | None = None,
                     steps: dict[str, int] | None = None) -> float:
    """Expected seconds of training job ``train@<scene>:<run>[+<run>...]``: per run, the longest ``train_seconds`` of
    the runs of its scene and method that finished ``ok`` in ``work`` (``finished``: :func:`finished_train_seconds`
    of it, read here when not given); else its method's time on other scenes scaled to this one
    (:func:`_scaled_elsewhere`, with ``steps``: :func:`scene_steps`); else, for a method none of whose runs
    finished (Table 3's ablations after Table 1), GCA's time on this scene (or scaled from elsewhere) times the
    method's :func:`train_cost` over GCA's (uncapped: full fine-tuning 1.33x); else ``default`` times that ratio capped
    at 1 (NCLaw, which does not train: ~0.13); plus
    :data:`JOB_START_S` for the job (``train_seconds`` counts the iterations only). Session 23: without GCA's
    times, every ablation was expected at ``default`` and a machine with 840 s left started none."""
    finished = finished_train_seconds(work) if finished is None else finished
    scene, runs = dispatch.job_runs(job)
    total = JOB_START_S
    for run in runs:
        method = run.split("@", 1)[0]
        if finished.get(method):
            total += _seconds_on(finished, method, scene, steps)
        elif finished.get("gca"):
            total += _seconds_on(finished, "gca", scene, steps) * train_cost(method) / COST["train:gca"]
        else:
            total += default * min(1.0, train_cost(method) / COST["train:gca"])
    return total


def _seconds_on(finished: dict[str, dict[str, float]], method: str, scene: str,
                steps: dict[str, int] | None = None) -> float:
    """Seconds of ``method`` (finished somewhere) on ``scene``: its own time there, else :func:`_scaled_elsewhere`."""
    times = finished[method]
    return times[scene] if scene in times else _scaled_elsewhere(finished, method, scene, steps)


def _trains(method: str) -> bool:
    """Whether ``method``'s training times say anything of a scene's cost: NCLaw does not train (its
    ``train_seconds`` are ~1e-3 s of bookkeeping); a method this module does not know is taken as training."""
    from gca.train.methods import METHODS

    return method not in METHODS or METHODS[method].trains


def _scaled_elsewhere(finished: dict[str, dict[str, float]], method: str, scene: str,
                      steps: dict[str, int] | None = None) -> float:
    """Seconds of ``method`` on ``scene``, where it has finished only on other scenes: the largest of (1) its slowest
    time anywhere, (2) with ``steps`` (MPM steps per rollout, :func:`scene_steps`), the median of its times on the
    other scenes scaled by ``steps[scene] / steps[s]`` (a training's cost grows with its steps: session 31's solo GCA
    took 0.24-0.29 s per step on the six Table 1 scenes), and (3) its time on a scene s times ``t(other, scene) /
    t(other, s)`` for the other methods that train (:func:`_trains`) and finished on both. [s]

    A central estimate, not a bound: a scene with more steps than any finished one and a higher cost per step than
    their median (GCA: 0.82-1.27 s per step at 8-way over eight scenes) can take longer. Session 36, on the state
    before its wave (wolf: 1000 steps): GCA on wolf was expected at 1469 s at 8-way (NCLaw's near-zero times as the
    ratio of (3)); now 1161, against 1015 for the run as measured (its seconds packed to 8-way as the grid packs them,
    :func:`finished_train_seconds`, plus the job's start); pudding 941 against 871."""
    times = finished[method]
    guesses = [max(times.values())]
    if steps and steps.get(scene):
        scaled = [t * steps[scene] / steps[s] for s, t in times.items() if steps.get(s)]
        if scaled:
            guesses.append(statistics.median(scaled))
    for other, their in finished.items():
        if other != method and _trains(other) and their.get(scene):
            guesses += [t * their[scene] / their[s] for s, t in times.items() if their.get(s)]
    return max(guesses)


PRIORITY_SHARE = 0.75  # a (scene, seed) unit whose heaviest run's work is under this share of the heaviest unit with
# training left starts its jobs at CUDA MPS's below-normal client priority (unit_work, below_normal): Table 1's
# 20-frame scenes (400-500 steps) beside the ball and the duck (800) at the paper profile. Session 47, 12 processes
# under MPS (benchmarks/bench_runs_packed.py): four long ones at normal beside eight short ones below it ended in 30.8
# s against 43.4 with all at normal, the span 6.5 % shorter


def run_work(job: str, steps: dict[str, int]) -> float | None:
    """The work of the runs a per-run job trains or evaluates (``train@<scene>:<run>[+<run>...]``, ``evaluate@...``)
    [cost GPU-minutes x MPM steps per rollout]: per run that trains, its method's :func:`train_cost` times the scene's
    steps (``steps``: :func:`scene_steps`; a scene without an entry, a capture: the largest there, 1 without any). None
    for any other job, and for a job none of whose runs trains (NCLaw's is its scene's launch-velocity fit, which the
    scene's other runs wait on)."""
    if dispatch.RUN_JOB_RE.match(job) is None:
        return None
    scene, runs = dispatch.job_runs(job)
    methods = [m for m in (r.split("@", 1)[0] for r in runs) if _trains(m)]
    if not methods:
        return None
    return sum(train_cost(m) for m in methods) * (steps.get(scene) or max(steps.values(), default=1))


def trains_any(job: str) -> bool:
    """Whether per-run job ``job`` has a run that trains (:func:`run_work` is not None); any other job: True. Without
    a machine's lease the slot reservation keeps no job without one waiting (``dispatch.run``'s ``may_wait``): NCLaw's
    velocity fit, ~30 s, which its unit's runs wait on (session 47)."""
    return dispatch.RUN_JOB_RE.match(job) is None or run_work(job, {}) is not None


def unit_work(jobs, steps: dict[str, int]) -> dict[str, float]:
    """Each (scene, seed) unit's work (``dispatch.unit_of``): the largest :func:`run_work` among its per-run jobs in
    ``jobs`` (names), done or not; a unit of no run that trains (NCLaw alone) is not listed."""
    out: dict[str, float] = {}
    for n in jobs:
        u, w = dispatch.unit_of(n), run_work(n, steps)
        if u is not None and w is not None:
            out[u] = max(out.get(u, 0.0), w)
    return out


def below_normal(job: str, works: dict[str, float], left, share: float = PRIORITY_SHARE) -> bool:
    """Whether ``job`` starts at CUDA MPS's below-normal client priority (``gca.gpu_slot.MPS_PRIORITY_ENV``): it is a
    per-run job of a (scene, seed) unit whose work (``works``: :func:`unit_work` of the grid's jobs, made once) is
    under ``share`` of the heaviest unit with a training job in ``left`` (the grid's training jobs not done). One
    priority a unit: its
    methods' times stay comparable (Table 4's pairs) and its launch-velocity fit goes at its runs' priority. Inputs and
    the report never are: every run waits on them. Under MPS the GPU then serves the heaviest units first and the
    lighter ones fill in what they leave, so the table does not end with its heaviest runs alone on a part-empty GPU
    (session 47). A failed heavy training still counts as left for the rest of the call (its ``.done`` never comes)."""
    unit = dispatch.unit_of(job)
    if unit not in works:
        return False
    heaviest = max((works[u] for n in left if (u := dispatch.unit_of(n)) in works), default=0.0)
    return works[unit] < share * heaviest


def scene_steps(work: Path) -> dict[str, int]:
    """MPM steps of one rollout of each scene of ``work/params.yaml`` at its profile (simulated frames x substeps,
    :func:`gca.scenes.config.scene_video`), for :func:`_scaled_elsewhere` and :func:`unit_work`. A capture scene (its
    timing comes from its video) is left out, and so is a scene whose entry does not build; none when the file is
    absent or is not this project's (``--repo``: another DVC repository's params, without ``scenes`` and ``video`` of these shapes). The
    stages check the params; an estimate only falls back to the runs' own times."""
    from gca.config import ConfigError
    from gca.pipeline import schema  # the typed configs: only where an estimate needs them
    from gca.scenes.config import scene_video

    path = work / "params.yaml"
    if not path.is_file():
        return {}
    not_ours = (ConfigError, yaml.YAMLError, TypeError, ValueError, AttributeError, KeyError)
    try:
        raw = schema.read_yaml(path)
        if not isinstance(raw, dict) or not isinstance(raw.get("scenes"), dict) or "video" not in raw:
            return {}
        profile = raw.get("profile", "paper")
        params = {**schema.resolve(raw, profile), "profile": profile}
        video = schema.build_section(params, "video")
    except not_ours:
        return {}
    out = {}
    for name, spec in params["scenes"].items():
        if isinstance(spec, dict) and "capture" not in spec:
            try:
                timing = scene_video(video, schema.scene_config(spec, f"{path}: scenes.{name}"))
            except not_ours:
                continue
            out[name] = timing.n_frames * timing.substeps
    return out


def _expected_in(work: Path, default: float, slots: int | None = None) -> Callable[[str], float]:
    """:func:`expected_train_s` for ``dispatch.run``, which asks each poll for every training run it holds back: the
    finished runs' times are read again only when a training marker appeared or grew since (a job's end, then its
    sharing: ``dispatch.record_sharing``); the scenes' steps (:func:`scene_steps`) once."""
    memo: dict = {"steps": scene_steps(work)}

    def expected(job: str) -> float:
        key = sorted((p.name, p.stat().st_size) for p in (work / ".grid").glob("train@*.done"))
        if memo.get("key") != key:
            memo.update(key=key, finished=finished_train_seconds(work, slots))
        return expected_train_s(work, job, default, memo["finished"], memo["steps"])

    return expected


def needed(jobs: dict, done: set[str]) -> set[str]:
    """The jobs to run: every job not done whose results a grid state carries (training, evaluation:
    :data:`STATE_RE`) or that nothing reads from (the grid's ends), and the jobs not done that one of those reads
    from. After a restored state (training and evaluation done elsewhere), a scene whose jobs are all done does
    not remake its inputs."""
    readers: dict[str, set[str]] = {n: set() for n in jobs}
    for name, job in jobs.items():
        for a in job.after:
            if a in readers:
                readers[a].add(name)
    memo: dict[str, bool] = {}

    def need(name: str) -> bool:
        if name not in memo:
            memo[name] = name not in done and (not readers[name] or bool(STATE_RE.match(f".grid/{name}.done"))
                                               or any(need(r) for r in readers[name]))
        return memo[name]

    return {n for n in jobs if need(n)}


MPS_CONTROL = "nvidia-cuda-mps-control"


@contextlib.contextmanager
def mps_daemon(enable: bool, log: Callable[[str], None]):
    """CUDA MPS for the jobs of one grid command: started where it may be (root, the control binary on
    PATH), stopped at the end; otherwise the grid says why and runs without it. Yields whether MPS runs.

    MPS lets several processes' kernels share the GPU at once instead of time-slicing (measured on an
    H100, four ball trainings: 1.6x the throughput of one without MPS, 2.9x with it; issue 20). A daemon
    that was already running is used and left running.
    """
    if not enable:
        yield False
        return
    binary = shutil.which(MPS_CONTROL)
    if binary is None:
        log(f"--mps: {MPS_CONTROL} is not on PATH: no CUDA MPS, the jobs time-slice the GPU")
        yield False
        return
    if os.geteuid() != 0:
        log(f"--mps: not root, so the MPS daemon cannot be started here (an administrator runs `{MPS_CONTROL} -d`); "
            "the jobs time-slice the GPU")
        yield False
        return
    started = subprocess.run([binary, "-d"], capture_output=True, text=True)
    if started.returncode != 0:
        why = (started.stderr or started.stdout).strip() or f"exit status {started.returncode}"
        if "already running" in why.lower():
            log(f"--mps: an MPS daemon is already running: the jobs use it and it is left running ({why})")
            yield True
        else:
            log(f"--mps: `{MPS_CONTROL} -d` failed ({why}): the jobs time-slice the GPU")
            yield False
        return
    log(f"--mps: CUDA MPS daemon started (`{MPS_CONTROL} -d`)")
    try:
        yield True
    finally:
        stopped = subprocess.run([binary], input="quit\n", capture_output=True, text=True)
        log("--mps: MPS daemon stopped (`echo quit | " + MPS_CONTROL + "`)" if stopped.returncode == 0 else
            f"--mps: stopping the MPS daemon failed (exit status {stopped.returncode}): stop it with "
            f"`echo quit | {MPS_CONTROL}`")


def main(argv=None) -> dict[str, str]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    where = ap.add_mutually_exclusive_group(required=True)
    where.add_argument("--work", type=Path, help="a work directory made here for --scenes (params.yaml restricted to "
                                                 "them, the code linked; no dvc needed)")
    where.add_argument("--repo", type=Path, help="run in place in this DVC repository with its own params.yaml "
                                                 "(then --commit)")
    ap.add_argument("--scenes", nargs="+", help="--work: the scenes")
    ap.add_argument("--methods", nargs="+", help="--work: default each scene's methods in params.yaml")
    ap.add_argument("--profile", default="paper", help="--work: the profile")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="--work: dotted.key=yaml_value")
    ap.add_argument("--stages", nargs="+", help="dvc.yaml stages (default --work: all but demo; --repo: all)")
    ap.add_argument("--priors", type=Path, help="--work: folder of <family>.pt from an earlier run (no prior jobs)")
    ap.add_argument("--runs-per-job", type=int, default=1,
                    help="training runs of a scene per job after its first (default 1: one job per run)")
    ap.add_argument("--commit", action="store_true", help="--repo: then `dvc commit -f` every stage whose jobs all "
                                                          "finished, so `dvc repro` recomputes none of them")
    ap.add_argument("--collect", type=Path, help="write grid_results.tar.gz (small results) into this folder")
    ap.add_argument("--first-methods", nargs="+", metavar="METHOD",
                    help="launch the (scene, seed) units with a training run of these methods left before all others "
                         "(a table finished first, the rest filling the slots: Table 3's ablations, then Tables 2, 5, 6)")
    ap.add_argument("--collect-only", action="store_true",
                    help="only --collect (and --save-state) what --work holds, also while a grid runs there")
    ap.add_argument("--restore-state", type=Path, metavar="TGZ",
                    help="--work: first unpack a --save-state archive (the runs and evaluations done elsewhere)")
    ap.add_argument("--save-state", type=Path, metavar="TGZ",
                    help="--work: at the end write the runs' results and laws and the evaluations' JSON "
                         "to this archive (the state another machine goes on from with --restore-state)")
    ap.add_argument("--records", type=Path, action="append", default=[], metavar="TGZ",
                    help="--work: also unpack the histories, loss curves and evaluation media of these archives "
                         "(--collect's grid_results.tar.gz, a results folder's records.tgz), for --mlflow-import")
    ap.add_argument("--evaluate-missing", metavar="KEY", action="append", default=[],
                    help="--work: evaluate again the runs whose metrics lack KEY (a metric added since they were "
                         "evaluated, e.g. chamfer_mean_true_launch), then the report; idempotent across calls")
    ap.add_argument("--mlflow-import", action="store_true",
                    help="--work: run no job; log the runs' records (after --restore-state, --records) into MLflow "
                         "as the stages would have (gca.pipeline.mlflow_records: the GPU machine has no mlflow)")
    ap.add_argument("--before", help="a command run once before the jobs (e.g. compile a JIT extension the "
                                     "jobs share: concurrent first builds can corrupt its cache)")
    ap.add_argument("--machine-left", type=float, metavar="S",
                    help="seconds this machine has left (a lease beyond this command's --deadline): a training run "
                         "starts only if its expected time fits (a run cut off by the machine resumes on no other: "
                         "remade inputs differ in float32 noise); evaluations and runs with a checkpoint go on")
    ap.add_argument("--expected-train-s", type=float, default=900.0, metavar="S",
                    help="--machine-left: a training run's expected seconds where none of its scene and method has "
                         "finished here (default 900: the slowest Table 1 GCA run under 8-way MPS, session 20)")
    ap.add_argument("--mps", action="store_true", help="run the jobs under CUDA MPS: start the daemon where "
                                                        "allowed (root), stop it at the end; says so where not. "
                                                        "The jobs of a (scene, seed) unit whose work is under "
                                                        f"{PRIORITY_SHARE:g} of the heaviest unit's with training left "
                                                        "start at MPS's below-normal client priority (not with "
                                                        "--machine-left)")
    ap.add_argument("--no-chain", action="store_true",
                    help="run each input stage as its own job (default: a scene's input stages, assets to preprocess "
                         "and, the prior there already, its first launch-velocity fit, as one job in one process)")
    ap.add_argument("--no-mps-priority", action="store_true",
                    help="--mps: every job at normal priority (the control of an A/B)")
    dispatch.add_engine_args(ap, slots=2)
    args = ap.parse_args(argv)
    work = (args.work or args.repo).resolve()
    if args.collect_only:  # also of a grid still running (table_bundle.sh: a call's snapshot of the machine's grid)
        if args.save_state is not None:
            print(f"[grid] state: {save_state(work, args.save_state)} files in {args.save_state}")
        if args.collect is not None:
            print(f"[grid] results: {collect(work, args.collect)}")
        return {}
    stamp = ""
    if args.repo is not None:  # what DVC finds up to date is not run; a job done under other params counts as not done
        changed = dvc_changed(work)
        jobs, stamp = repo_jobs(work, args.stages, args.runs_per_job, changed), inputs_stamp(work)
    else:
        if not args.scenes:
            ap.error("--work needs --scenes")
        params = grid_params(args.profile, args.scenes, args.methods, args.overrides)
        prepare(work, params)
        stages = args.stages or ["assets", "particles", "prior", "ground_truth", "preprocess", "train", "evaluate", "report"]
        jobs = expand(yaml.safe_load((ROOT / "dvc.yaml").read_text()), params, stages)
        if args.priors is not None:
            for family in params["prior"]["families"]:
                src = args.priors / f"{family}.pt"
                if not src.is_file():
                    raise SystemExit(f"{src}: no prior for family {family!r} (--priors)")
                dst = work / "models" / "prior" / f"{family}.pt"
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, dst)
                jobs.pop(f"prior@{family}", None)
        jobs = link(batch_runs(split_runs(jobs, params), args.runs_per_job))
        if "report" in jobs:  # report reads metrics/demo only when it exists: run without the demo stage
            jobs["report"].after = {a for a in jobs["report"].after if not a.startswith("demo")}
        if args.restore_state is not None:
            print(f"[grid] {restore_state(args.restore_state, work)} state files restored from {args.restore_state}")
        for archive in args.records:
            print(f"[grid] {unpack_records(archive, work)} record files unpacked from {archive}")
        for key in args.evaluate_missing:
            undone = evaluate_missing(work, key)
            if undone:
                print(f"[grid] {len(undone)} evaluations lack {key}: evaluated again ({', '.join(undone[:4])}"
                      + (", ..." if len(undone) > 4 else "") + ")")
        if args.mlflow_import:
            from gca.pipeline.mlflow_records import import_grid

            print(f"[grid] mlflow: {import_grid(work)}")
            return {}
        done = {n for n in jobs if dispatch.is_done(work, n)}
        keep = needed(jobs, done)
        jobs = {n: j for n, j in jobs.items() if n in keep or n in done}
    if not args.no_chain:
        chained = params if args.repo is None else yaml.safe_load((work / "params.yaml").read_text())
        jobs = chain_undone(jobs, chained, work, stamp)
    (work / ".grid").mkdir(parents=True, exist_ok=True)
    logfile = open(work / ".grid" / "grid.log", "a")

    def log(msg: str) -> None:
        line = f"[grid {time.strftime('%H:%M:%S')}] {msg}"
        print(line, flush=True)
        logfile.write(line + "\n")
        logfile.flush()

    if args.before:
        log(f"before: {args.before}")
        subprocess.run(args.before, shell=True, check=True, cwd=work,
                       env={**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"})
    engine = dispatch.engine_from_args(args, work / ".grid" / "submitit" / "%j")
    env = {} if os.environ.get("MLFLOW_TRACKING_URI") else {"MLFLOW_TRACKING_URI": f"sqlite:///{work / 'mlflow.db'}"}
    if engine.places:  # one machine: its cores shared by the slots (SLURM: --cpus-per-task)
        env["OMP_NUM_THREADS"] = os.environ.get("OMP_NUM_THREADS") or str(max(1, (os.cpu_count() or 1) // len(engine.places)))
    todo = sum(not dispatch.is_done(work, n, stamp) for n in jobs)
    where = (f"GPU(s) {args.gpus} x {args.slots} slots" if args.engine == "local" else "SLURM")
    log(f"{len(jobs)} jobs ({todo} to run) through {args.engine} on {where}"
        + (f", profile {args.profile}" if args.repo is None else f", in place in {work}"))
    t0 = time.monotonic()
    env[gpu_slot.RUNS_ENV] = str(args.slots if engine.places else 1)  # provenance of the runs' times (Table 4)
    with mps_daemon(args.mps, log) as mps_on:
        env[gpu_slot.MPS_ENV] = "1" if mps_on else "0"
        asked = mps_on and bool(engine.places) and not args.no_mps_priority
        prioritise = asked and args.machine_left is None
        if asked and not prioritise:
            log("--mps: every job at normal priority: --machine-left's lease check counts equal shares of the GPU")
        works = unit_work(jobs, scene_steps(work)) if prioritise else {}
        if prioritise:
            log(f"--mps: the jobs of a unit under {PRIORITY_SHARE:g} x the heaviest unit's with training left start at "
                f"below-normal priority ({gpu_slot.MPS_PRIORITY_ENV}={gpu_slot.MPS_BELOW_NORMAL}; --no-mps-priority: "
                "none)")
            env[gpu_slot.PRIORITY_GRID_ENV] = "1"  # every run of this call records it: no equal share's time

        def job_env(job, place) -> dict:
            """The jobs' environment, and MPS's below-normal priority for a lighter unit's job (:func:`below_normal`)."""
            if not prioritise:
                return env
            left = [n for n in jobs if n.startswith("train@") and not dispatch.is_done(work, n, stamp)]
            if not below_normal(job.name, works, left):
                return env
            log(f"prio  {job.name}: below normal")
            return {**env, gpu_slot.MPS_PRIORITY_ENV: gpu_slot.MPS_BELOW_NORMAL}

        state = dispatch.run(jobs, engine, work, log, args.deadline, job_env=job_env, stamp=stamp,
                             launch_until=args.machine_left,
                             expected_s=_expected_in(work, args.expected_train_s,
                                                     args.slots if engine.places else None),
                             packed_s=(lambda seconds, k: packed_seconds(seconds, args.slots, k))
                             if engine.places else None, first=first_methods(args.first_methods),
                             may_wait=trains_any if args.machine_left is None else None)
    counts = {s: sum(1 for v in state.values() if v == s) for s in ("done", "todo", "failed", "skipped")}
    log(f"after {time.monotonic() - t0:.0f} s: {counts}" + ("; run the same command again to go on" if counts["todo"]
                                                            else "; nothing left to run"))
    if counts["todo"] and args.deadline is not None and args.deadline < dispatch.RESUMABLE_MIN_S:
        log(f"--deadline {args.deadline:g} s is under {dispatch.RESUMABLE_MIN_S:g} s: no training job will ever be launched")
    for name in sorted(state):
        if state[name] != "done":
            log(f"  {state[name]:>8}  {name}")
    if args.commit and args.repo is not None:
        finished = dispatch.dvc_stages(members_state(state, jobs, lambda m: dispatch.is_done(work, m, stamp)))
        if finished:
            log(f"dvc commit -f {' '.join(finished)}")
            subprocess.run([sys.executable, "-m", "dvc", "commit", "-f", *finished], cwd=work, check=True)
    if args.save_state is not None and args.repo is None:
        log(f"state: {save_state(work, args.save_state)} files in {args.save_state}")
    if args.collect:
        log(f"results: {collect(work, args.collect)}")
    return state


if __name__ == "__main__":
    sys.exit(1 if {"failed", "skipped"} & set(main(sys.argv[1:]).values()) else 0)
