"""The pipeline's stage commands for a scene x method grid, scheduled over the GPUs of one machine.

What ``dvc repro`` runs, without dvc (the GPU machine has none): the stage commands are read from
``dvc.yaml`` and expanded for the chosen scenes, their objects and prior families; the order comes
from the stages' deps and outs; each job runs as its own process pinned to one GPU
(``CUDA_VISIBLE_DEVICES``), ``--slots`` jobs per GPU at once (packing, ``pack.py``). The outputs land
where ``dvc repro`` puts them, inside ``--work``, so the ``report`` stage reads them as it always does.
A scene's ``train`` stage is split per method (the first method estimates the launch velocity, the
others reuse it with ``--velocity``) so one scene's methods train on several GPUs at once.

    python -m gca.pipeline.grid --work /tmp/t1 --scenes ball duck pawn cat fish bottle \
        --methods gca neuma nclaw --profile paper --gpus 4 --slots 2 --deadline 540 \
        --before "python3 -c 'from gsplat.cuda._backend import _C'"

Resumable: a finished job leaves ``<work>/.grid/<job>.done`` and is not run again; training resumes
from its checkpoint. ``--deadline`` [s] bounds the command: it launches no job that its estimated cost
would not finish in time, except training jobs (resumable: launched while ``RESUMABLE_MIN_S`` remain),
and at the deadline stops the jobs still running (SIGTERM; a training job loses at most
``train.checkpoint_every`` iterations), so a long grid runs as a few commands of bounded length
(repeat the command until it reports every job done). A failed job is logged with its output's tail, its dependents are skipped, the
others go on. ``--priors DIR`` takes ``<family>.pt`` from an earlier run instead of pretraining.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Callable

import yaml

ROOT = Path(__file__).resolve().parents[2]  # the checkout: params.yaml, dvc.yaml, stages/

# Estimated cost of a job [GPU-minutes, paper profile, one H100, alone]: for priorities (longest path
# first) and --deadline. From benchmarks/NOTES.md; a job that takes longer only delays the grid.
COST = {"assets": 0.4, "particles": 0.8, "prior": 6.0, "ground_truth": 0.6, "preprocess": 0.1,
        "train": 0.6, "train:gca": 4.5, "train:neuma": 2.7, "train:neuma_multiview": 4.0,
        "train:gca_full_ft": 6.0, "evaluate": 0.8, "report": 0.3, "demo": 1.0}
RESUMABLE_MIN_S = 120.0  # a training job is launched while this much of the deadline remains [s]
STOP_GRACE_S = 20.0  # after SIGTERM at the deadline, SIGKILL a job still alive this long after [s]


@dataclasses.dataclass
class Job:
    """One stage command. ``deps``/``outs``: paths relative to the work directory."""

    name: str
    cmd: str
    deps: list[str]
    outs: list[str]
    cost: float
    after: set[str] = dataclasses.field(default_factory=set)  # names of jobs that must finish first


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
    name (``gca``, ``gca@seed1``; a method that does not train runs the first seed only); the first (the cheapest
    method's first seed) estimates the velocity."""
    from gca.config import resolve
    from gca.train.methods import get_method
    from gca.pipeline.settings import Settings
    from gca.pipeline.train import seed_runs

    resolved = Settings(resolve(params, params["profile"]))
    several = len(resolved.train.seeds) > 1
    out = {}
    for name, job in jobs.items():
        if not name.startswith("train@"):
            out[name] = job
            continue
        scene = name.split("@", 1)[1]
        methods = sorted(params["scenes"][scene]["methods"], key=lambda m: COST.get(f"train:{m}", COST["train"]))
        run_dir = re.search(r"--out (\S+)", job.cmd).group(1)
        first = None
        for method, s, run in seed_runs(resolved, [get_method(m) for m in methods]):
            m = method.name
            cmd = f"{job.cmd} --methods {m}" + (f" --seeds {s}" if several else "")
            if first is not None:
                cmd += f" --velocity {run_dir}/velocity.json"
            j = Job(f"{name}:{run}", cmd, list(job.deps), [f"{run_dir}/{run}"] + ([] if first else [f"{run_dir}/velocity.json"]),
                    COST.get(f"train:{m}", COST["train"]))
            if first is not None:
                j.after.add(first)
            first = first or j.name
            out[j.name] = j
    return out


def _under(path: str, root: str) -> bool:
    return path == root or path.startswith(root.rstrip("/") + "/")


def link(jobs: dict[str, Job]) -> dict[str, Job]:
    """Job B runs after job A when one of B's deps is (under) one of A's outs or A's out is under B's dep."""
    for b in jobs.values():
        for a in jobs.values():
            if a is not b and any(_under(d, o) or _under(o, d) for d in b.deps for o in a.outs):
                b.after.add(a.name)
    return jobs


def critical_path(jobs: dict[str, Job]) -> dict[str, float]:
    """Longest cost from each job to the end of the grid (list-scheduling priority)."""
    children = {n: [] for n in jobs}
    for j in jobs.values():
        for a in j.after:
            if a in children:
                children[a].append(j.name)
    memo: dict[str, float] = {}

    def walk(n: str) -> float:
        if n not in memo:
            memo[n] = jobs[n].cost + max((walk(c) for c in children[n]), default=0.0)
        return memo[n]
    return {n: walk(n) for n in jobs}


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
    """The work directory as a checkout: the code linked, its own params.yaml."""
    work.mkdir(parents=True, exist_ok=True)
    for name in ("stages", "gca", "dvc.yaml"):
        target = work / name
        if not target.exists():
            target.symlink_to(ROOT / name)
    (work / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    (work / ".grid").mkdir(exist_ok=True)


class Scheduler:
    """List scheduling of jobs over ``gpus x slots`` places, longest remaining path first."""

    def __init__(self, jobs: dict[str, Job], work: Path, gpus: int | list[int], slots: int, deadline: float | None, log):
        """``gpus``: a count (GPUs 0 .. gpus-1) or the GPU ids to use."""
        self.jobs, self.work, self.log = jobs, work, log
        ids = list(range(gpus)) if isinstance(gpus, int) else list(gpus)
        self.places = [g for g in ids for _ in range(slots)]  # free places (a GPU per slot)
        self.threads = max(1, (os.cpu_count() or 1) // len(self.places))  # CPU threads per job
        self.priority = critical_path(jobs)
        self.deadline = None if deadline is None else time.monotonic() + deadline
        self.state = {n: ("done" if self._marker(n).is_file() else "todo") for n in jobs}
        self.running: dict[str, tuple[subprocess.Popen, int, float]] = {}

    def _marker(self, name: str, suffix: str = ".done") -> Path:
        """``.grid/<job>.done`` (finished) or, with ``suffix=".log"``, the job's output."""
        return self.work / ".grid" / (re.sub(r"[^A-Za-z0-9_.@:-]", "_", name) + suffix)

    def _ready(self) -> list[str]:
        return [n for n, s in self.state.items() if s == "todo" and all(self.state.get(a) == "done" for a in self.jobs[n].after)]

    def _skip_dependents(self) -> None:
        changed = True
        while changed:
            changed = False
            for n, s in self.state.items():
                if s == "todo" and any(self.state.get(a) in ("failed", "skipped") for a in self.jobs[n].after):
                    self.state[n] = "skipped"
                    self.log(f"skip {n}: an upstream job failed")
                    changed = True

    def _launch(self, name: str, gpu: int) -> None:
        job = self.jobs[name]
        argv = shlex.split(job.cmd)
        if argv[0] == "python":
            argv[0] = sys.executable
        env = {"OMP_NUM_THREADS": str(self.threads), **os.environ, "CUDA_VISIBLE_DEVICES": str(gpu), "PYTHONUNBUFFERED": "1",
               "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
               "MLFLOW_TRACKING_URI": os.environ.get("MLFLOW_TRACKING_URI", f"sqlite:///{self.work / 'mlflow.db'}")}
        logf = open(self._marker(name, ".log"), "w")
        proc = subprocess.Popen(argv, cwd=self.work, env=env, stdout=logf, stderr=subprocess.STDOUT)
        self.running[name] = (proc, gpu, time.monotonic())
        self.state[name] = "running"
        self.log(f"start {name} on gpu {gpu}")

    def _reap(self, stopped: set[str] = frozenset()) -> None:
        """Record the jobs that ended: done, failed, or (``stopped`` at the deadline) to do again."""
        for name, (proc, gpu, t0) in list(self.running.items()):
            rc = proc.poll()
            if rc is None:
                continue
            del self.running[name]
            self.places.append(gpu)
            took = time.monotonic() - t0
            if name in stopped:
                self.state[name] = "todo"
                self.log(f"stop  {name} at the deadline after {took:.0f} s (resumes next time)")
            elif rc == 0:
                self.state[name] = "done"
                self._marker(name).write_text(f"{took:.1f}\n")
                self.log(f"done  {name} in {took:.0f} s")
            else:
                self.state[name] = "failed"
                tail = self._marker(name, ".log").read_text()[-1500:]
                self.log(f"FAIL  {name} (exit {rc}) after {took:.0f} s:\n{tail}")
                self._skip_dependents()

    def _fits(self, name: str) -> bool:
        if self.deadline is None:
            return True
        need = RESUMABLE_MIN_S if name.startswith("train@") else 60 * self.jobs[name].cost * 1.3
        return time.monotonic() + need < self.deadline

    def _stop_at_deadline(self) -> None:
        """Stop every running job (SIGTERM, SIGKILL after ``STOP_GRACE_S``): a stopped job stays to do; one
        that ended on its own meanwhile counts as done or failed by its exit status."""
        self._reap()
        for proc, _, _ in self.running.values():
            proc.terminate()
        t_end = time.monotonic() + STOP_GRACE_S
        for name, (proc, _, _) in list(self.running.items()):
            try:
                proc.wait(timeout=max(0.1, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._reap(stopped={n for n, (proc, _, _) in self.running.items()
                            if proc.returncode in (-signal.SIGTERM, -signal.SIGKILL)})

    def run(self) -> dict[str, str]:
        while True:
            self._reap()
            ready = sorted(self._ready(), key=lambda n: -self.priority[n])
            for name in ready:
                if not self.places:
                    break
                if not self._fits(name):
                    continue
                gpu = min(self.places, key=lambda g: sum(1 for _, (_, gg, _) in self.running.items() if gg == g))
                self.places.remove(gpu)
                self._launch(name, gpu)
            if not self.running:
                return self.state
            if self.deadline is not None and time.monotonic() >= self.deadline:
                self._stop_at_deadline()
                return self.state
            time.sleep(1.0)


def collect(work: Path, out: Path) -> Path:
    """The small results of a grid in one archive: metrics, reports, train/eval summaries, the learned laws
    (~40 kB each: a run can be evaluated again elsewhere), priors, logs."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "grid_results.tar.gz"
    keep = re.compile(r"^(metrics/.*|reports/.*|models/prior/.*|runs/[^/]+/velocity\.json|"
                      r"runs/[^/]+/[^/]+/(train|history)\.json|runs/[^/]+/[^/]+/(loss\.png|law\.pt)|\.grid/.*|params\.yaml)$")
    with tarfile.open(path, "w:gz") as tar:
        for f in sorted(work.rglob("*")):
            rel = f.relative_to(work).as_posix()
            if f.is_file() and not f.is_symlink() and keep.match(rel) and f.stat().st_size < 8 * 2 ** 20:
                tar.add(f, arcname=rel)
    return path


def gpu_ids(text: str) -> int | list[int]:
    """``--gpus``: ``4`` -> 4 (GPUs 0..3); ``1,2,3`` -> [1, 2, 3] (leaves GPU 0 to something else);
    ``3,`` -> [3] (one id)."""
    try:
        return [int(g) for g in text.split(",") if g] if "," in text else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--gpus {text!r}: a count or comma-separated GPU ids") from None


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
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--scenes", nargs="+", required=True)
    ap.add_argument("--methods", nargs="+", help="default: each scene's methods in params.yaml")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="dotted.key=yaml_value")
    ap.add_argument("--gpus", type=gpu_ids, default=1, help="a count (GPUs 0 .. N-1) or ids: 0,1,2 (one id: 3,)")
    ap.add_argument("--slots", type=int, default=2, help="concurrent jobs per GPU")
    ap.add_argument("--deadline", type=float, default=None, help="seconds: launch nothing that would end later")
    ap.add_argument("--stages", nargs="+", default=["assets", "particles", "prior", "ground_truth", "preprocess",
                                                   "train", "evaluate", "report"])
    ap.add_argument("--priors", type=Path, help="folder of <family>.pt from an earlier run (no prior jobs)")
    ap.add_argument("--collect", type=Path, help="write grid_results.tar.gz (small results) into this folder")
    ap.add_argument("--collect-only", action="store_true", help="only --collect what --work holds")
    ap.add_argument("--before", help="a command run once before the jobs (e.g. compile a JIT extension the "
                                     "jobs share: concurrent first builds can corrupt its cache)")
    ap.add_argument("--mps", action="store_true", help="run the jobs under CUDA MPS: start the daemon where "
                                                        "allowed (root), stop it at the end; says so where not")
    args = ap.parse_args(argv)
    if args.collect_only:
        print(f"[grid] results: {collect(args.work, args.collect)}")
        return {}
    params = grid_params(args.profile, args.scenes, args.methods, args.overrides)
    prepare(args.work, params)
    jobs = expand(yaml.safe_load((ROOT / "dvc.yaml").read_text()), params, args.stages)
    if args.priors is not None:
        for family in params["prior"]["families"]:
            src = args.priors / f"{family}.pt"
            if not src.is_file():
                raise SystemExit(f"{src}: no prior for family {family!r} (--priors)")
            dst = args.work / "models" / "prior" / f"{family}.pt"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
            jobs.pop(f"prior@{family}", None)
    jobs = link(split_train(jobs, params))
    if "report" in jobs:  # report reads metrics/demo only when it exists: run without the demo stage
        jobs["report"].after = {a for a in jobs["report"].after if not a.startswith("demo")}
    logfile = open(args.work / ".grid" / "grid.log", "a")

    def log(msg: str) -> None:
        line = f"[grid {time.strftime('%H:%M:%S')}] {msg}"
        print(line, flush=True)
        logfile.write(line + "\n")
        logfile.flush()

    if args.before:
        log(f"before: {args.before}")
        subprocess.run(args.before, shell=True, check=True, cwd=args.work,
                       env={**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"})
    scheduler = Scheduler(jobs, args.work, args.gpus, args.slots, args.deadline, log)
    todo = sum(1 for s in scheduler.state.values() if s == "todo")
    log(f"{len(jobs)} jobs ({todo} to run) on GPU(s) {args.gpus} x {args.slots} slots, profile {args.profile}")
    t0 = time.monotonic()
    with mps_daemon(args.mps, log):
        state = scheduler.run()
    counts = {s: sum(1 for v in state.values() if v == s) for s in ("done", "todo", "failed", "skipped")}
    log(f"after {time.monotonic() - t0:.0f} s: {counts}" + ("; run the same command again to go on" if counts["todo"]
                                                            else "; nothing left to run"))
    if counts["todo"] and args.deadline is not None and args.deadline < RESUMABLE_MIN_S:
        log(f"--deadline {args.deadline:g} s is under {RESUMABLE_MIN_S:g} s: no training job will ever be launched")
    for name in sorted(state):
        if state[name] != "done":
            log(f"  {state[name]:>8}  {name}")
    if args.collect:
        log(f"results: {collect(args.work, args.collect)}")
    return state


if __name__ == "__main__":
    main(sys.argv[1:])
