"""The pipeline's stage jobs dispatched through an existing job engine: SLURM through submitit, or
submitit's local executor on one machine.

One job is one stage command of ``dvc.yaml`` (``gca.pipeline.grid`` expands them and is the command
line; a scene's ``train`` stage is split into one job per (method, seed) run), sized to one GPU. The
command runs in the work directory where ``dvc repro`` runs it, so its outputs land where ``dvc repro``
puts them; in a DVC repository ``dvc commit -f <every finished stage>`` then records them in ``dvc.lock``
and DVC's cache (``grid --repo . --commit``): a ``dvc repro`` afterwards computes nothing again.

What the engine gives: queuing and placement (SLURM), the time limit and preemption signals, the requeue
of a job with the submission its ``checkpoint()`` returns (training goes on from
``runs/<scene>/<run>/checkpoint.pt``), a log per job. What stays here: the order of the jobs (SLURM
dependencies, or for the local executor: submit a job once the jobs it reads from are done), one job per
GPU slot on one machine (the local executor starts every job it is given at once), attaching to the
SLURM jobs an interrupted call left queued, a failed job reported
with its log path and its dependents skipped while the others go on, resume (a finished job leaves
``.grid/<job>.done`` and is not submitted again) and ``--deadline`` (stop what runs at the deadline).

Why submitit (and not Ray): SLURM is the scheduler labs' GPU clusters run; submitit drives it from Python
with no service to operate (sbatch/sacct/scontrol) and has a local executor with the same requeue path
for one machine and for tests. Ray needs a Ray cluster running (on SLURM: started inside an allocation).
Another engine is one :class:`Engine` subclass: ``submit`` (a picklable callable, after some jobs, on a
place), ``state``, ``error``, ``log``, ``cancel`` (``attach``: optional); a Ray one would wrap :class:`StageCommand` in
``ray.remote(num_gpus=1)`` and poll its ``ObjectRef`` with ``ray.wait``.
"""

from __future__ import annotations

import abc
import argparse
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from gca.stop import parent_death_signal  # stdlib only: light in the job process

ROOT = Path(__file__).resolve().parents[2]  # the checkout: params.yaml, dvc.yaml, stages/
STOP_GRACE_S = 20.0  # a stopped stage process gets SIGTERM, then SIGKILL after this long [s]
STOP_REQUEST_S = STOP_GRACE_S / 2  # before the SIGTERM, this long for the stage to stop at its stop file [s]
RESUMABLE_MIN_S = 120.0  # --deadline: a training job is submitted while this much of the deadline remains [s]
DONE, FAILED, RUNNING = "done", "failed", "running"
JOB_START_S = 60.0  # a training job's process start, data and launch-velocity estimate (~30-60 s, session 20), also
# each time it resumes: grid.expected_train_s adds it to a run's time, the lease check to a resumed run's work left [s]


def marker(work: Path, name: str, suffix: str = ".done") -> Path:
    """``<work>/.grid/<job>.done``: the job finished (its seconds inside)."""
    import re

    return Path(work) / ".grid" / (re.sub(r"[^A-Za-z0-9_.@:+-]", "_", name) + suffix)  # "+": batched runs


def _ignore_usr_signal() -> None:
    """In the stage process: ignore submitit's time-limit/preemption signal (SLURM's ``--signal`` reaches
    every process of the job): the job process handles it and stops the stage itself (``checkpoint``). On Linux
    the stage also gets SIGTERM (a clean stop: training checkpoints) when the job process dies: submitit's local
    cancel ends the job process with SIGKILL a second after its SIGINT, which would otherwise leave the stage
    running on its own. A stage that installs ``gca.stop``'s watcher (every ``cli.run`` stage) clears that signal
    and stops by its parent check instead, with no signal (``GCA_STOP_PARENT``, :meth:`StageCommand.environment`);
    the SIGTERM stays for a command that does not."""
    import signal

    signal.signal(getattr(signal, "SIG" + os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2")), signal.SIG_IGN)
    parent_death_signal(signal.SIGTERM)


PYTHON = ("python", "python3")  # a stage command's interpreter names, run as this process's own


def python_argv(cmd: str) -> list[str]:
    """A stage command's argv, its ``python``/``python3`` replaced by this process's interpreter (the job's: the one
    the engine started)."""
    argv = shlex.split(cmd)
    if argv and argv[0] in PYTHON:
        argv[0] = sys.executable
    return argv


def write_done(work: Path, name: str, took: float, stamp: str = "") -> None:
    """Write job ``name``'s ``.done`` marker: its seconds ``took`` and the ``stamp`` of its inputs (:func:`is_done`)."""
    done = marker(work, name)
    done.parent.mkdir(parents=True, exist_ok=True)
    done.write_text(f"{took:.1f}\n{stamp}\n")


def is_done(work: Path, name: str, stamp: str = "") -> bool:
    """The job left its ``.done`` marker, with ``stamp`` in it when one is given (a marker of a run with
    other inputs does not count)."""
    path = marker(work, name)
    return path.is_file() and (not stamp or stamp in path.read_text().split())


class StageFailed(RuntimeError):
    """A stage command exited non-zero."""


class StageCommand:
    """One job: a stage command run in ``work`` as its own process (its output goes to the job's log).

    A picklable callable for the engine. ``checkpoint()`` is submitit's hook at a time limit or a
    preemption: it stops the stage process and returns the same command to requeue; a training stage run
    again resumes from its checkpoint, any other stage starts over.
    """

    def __init__(self, name: str, cmd: str, work: str | Path, env: dict[str, str] | None = None, stamp: str = ""):
        """``stamp``: written into the job's ``.done`` marker (the inputs it was run with: :func:`is_done`)."""
        self.name, self.cmd, self.work, self.env, self.stamp = name, cmd, str(work), dict(env or {}), stamp
        self._proc: subprocess.Popen | None = None

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k != "_proc"}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._proc = None

    def argv(self) -> list[str]:
        return python_argv(self.cmd)

    def stop_file(self) -> Path:
        """``<work>/.grid/<job>.stop``: its existence asks the stage to stop (``gca.stop``: a training stage
        checkpoints at its iteration's end and exits 143, with no signal; NOTES session 42: a SIGTERM to a process
        packed under CUDA MPS ended every process on the GPU)."""
        return marker(Path(self.work), self.name, ".stop")

    def environment(self) -> dict[str, str]:
        """The stage's environment: ``self.env`` over this process's, its stop file (``GCA_STOP_FILE``) and this
        process as the parent whose end stops it (``GCA_STOP_PARENT``, ``gca.stop``)."""
        from gca.stop import STOP_FILE_ENV, STOP_PARENT_ENV

        env = {**os.environ, **self.env, "PYTHONUNBUFFERED": "1", STOP_FILE_ENV: str(self.stop_file()),
               STOP_PARENT_ENV: str(os.getpid())}
        # the work directory's own gca first (a checkout, or a grid work directory linking this one's)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (self.work, str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
        return env

    def __call__(self) -> float:
        t0 = time.monotonic()
        print(f"[gca job {self.name}] {self.cmd}  (cwd {self.work}, CUDA_VISIBLE_DEVICES="
              f"{os.environ.get('CUDA_VISIBLE_DEVICES', '')!r})", flush=True)
        self.stop_file().unlink(missing_ok=True)  # an earlier stop's request is not this run's
        # a session of its own: a Ctrl-C at the grid's terminal reaches this job process, whose stop() asks the stage
        # by its stop file, and not the stage (a signal to a process packed under CUDA MPS: gca.stop, session 44)
        self._proc = subprocess.Popen(self.argv(), cwd=self.work, env=self.environment(), preexec_fn=_ignore_usr_signal,
                                      start_new_session=True)
        pid_file = marker(Path(self.work), self.name, ".pid")  # what a deadline stop waits on (_wait_stopped)
        pid_file.parent.mkdir(parents=True, exist_ok=True)
        pid_file.write_text(f"{self._proc.pid}\n")
        try:
            rc = self._proc.wait()
        finally:
            self.stop()  # an exception (a requeue's SystemExit, Ctrl-C) never leaves the stage running
            pid_file.unlink(missing_ok=True)
            self.stop_file().unlink(missing_ok=True)
        if rc != 0:
            raise StageFailed(f"{self.name}: exit {rc}")
        took = time.monotonic() - t0
        write_done(Path(self.work), self.name, took, self.stamp)
        return took

    def stop(self) -> None:
        """Stop the stage process if it still runs: its stop file first (unless a deadline stop wrote it and waited
        already), ``STOP_REQUEST_S`` for it to end, then SIGTERM, then SIGKILL after ``STOP_GRACE_S``.

        Reaps it with ``os.waitpid`` itself: called from submitit's signal handler, it interrupts
        ``Popen.wait`` in ``__call__``, which holds the lock that another ``Popen.wait`` would wait for."""
        proc = self._proc
        if proc is None or proc.returncode is not None:
            return
        # (submitit's cancel of a local job kills this controller ~1 s after its SIGINT; the stage then stops by its
        # parent check, GCA_STOP_PARENT, or a command without gca.stop's watcher by its parent-death SIGTERM)
        if not self.stop_file().exists() and _request_stop(self.stop_file()) and self._reaped(STOP_REQUEST_S):
            return
        proc.terminate()
        if not self._reaped(STOP_GRACE_S):
            proc.kill()
            self._reaped(float("inf"))

    def _reaped(self, seconds: float) -> bool:
        """Wait up to ``seconds`` for the stage process to end (reaped here); whether it did."""
        proc, t_end = self._proc, time.monotonic() + seconds
        while True:
            try:
                pid, status = os.waitpid(proc.pid, os.WNOHANG)
            except ChildProcessError:  # reaped already
                return True
            if pid:
                proc.returncode = os.waitstatus_to_exitcode(status)
                return True
            if time.monotonic() > t_end:
                return False
            time.sleep(0.05)

    def checkpoint(self, *args, **kwargs):
        """submitit: the job hit its time limit or was preempted; requeue the same command."""
        import submitit

        self.stop()
        print(f"[gca job {self.name}] stopped for a requeue (a training run resumes from its checkpoint)", flush=True)
        return submitit.helpers.DelayedSubmission(StageCommand(self.name, self.cmd, self.work, self.env, self.stamp))


class Engine(abc.ABC):
    """What the driver needs from a job engine.

    ``places``: the places a job can be given (the local executor: one GPU id per slot, ``None`` for no
    GPU); ``None`` when the engine places jobs itself (SLURM). ``dependencies``: the engine holds a job
    until the jobs it is submitted ``after`` succeeded (and drops it when one fails), so the whole grid is
    submitted at once; otherwise the driver submits a job once its inputs are done.
    """

    places: list | None = None
    dependencies: bool = False

    @abc.abstractmethod
    def submit(self, job: StageCommand, after: list, place=None):
        """Submit ``job`` to run after the (handles) ``after``, on ``place``; returns a handle."""

    @abc.abstractmethod
    def state(self, handle) -> str:
        """``RUNNING`` (queued or running), ``DONE`` or ``FAILED``."""

    @abc.abstractmethod
    def error(self, handle) -> str:
        """A failed job's error, one line."""

    @abc.abstractmethod
    def log(self, handle) -> Path:
        """The job's log file (the stage command's output)."""

    @abc.abstractmethod
    def cancel(self, handle) -> None:
        """Stop the job (queued or running)."""

    def stop_jobs(self, handles: dict, work: Path, log, poll_s: float) -> None:
        """Stop the jobs ``handles`` (name -> handle) at a deadline: cancel each (an engine whose jobs run on
        this machine also waits for them to end)."""
        for handle in handles.values():
            self.cancel(handle)

    def attach(self, job: StageCommand):
        """The handle of ``job`` submitted by an earlier call and still queued or running, else None
        (then it is submitted again)."""
        return None

    def running(self, handle) -> bool:
        """Whether the job still runs, without reading its outcome (a stopped job has none to read)."""
        return self.state(handle) == RUNNING


class SubmititEngine(Engine):
    """A submitit executor: ``submitit.LocalExecutor`` (``places``: one GPU id or None per slot) or
    ``submitit.SlurmExecutor`` (SLURM places jobs; ``afterok`` dependencies)."""

    def __init__(self, executor, places: list | None = None, parameters: dict | None = None):
        import submitit

        self.executor = executor
        self.slurm = isinstance(executor, submitit.SlurmExecutor)
        self.dependencies = self.slurm
        self.places = None if self.slurm else list(places or [None])
        self.parameters = dict(parameters or {})

    def submit(self, job: StageCommand, after: list, place=None):
        params = dict(self.parameters)
        if self.slurm:
            params["job_name"] = job.name
            if after:
                params["dependency"] = "afterok:" + ":".join(str(h.job_id) for h in after)
                extra = dict(params.get("additional_parameters") or {})
                extra.setdefault("kill-on-invalid-dep", "yes")  # a failed input cancels the job, not pends it
                params["additional_parameters"] = extra
        else:
            params.update(gpus_per_node=0 if place is None else 1, visible_gpus=() if place is None else (place,))
        self.executor.update_parameters(**params)
        handle = self.executor.submit(job)
        if self.slurm:
            path = marker(Path(job.work), job.name, ".jobid")
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(f"{handle.job_id}\n")
        return handle

    ACTIVE = ("PENDING", "RUNNING", "REQUEUED", "CONFIGURING", "COMPLETING", "SUSPENDED", "RESIZING")

    def attach(self, job: StageCommand):
        """SLURM: the job this grid submitted before (``.grid/<job>.jobid``) while ``sacct`` says it is
        queued or running (the command was interrupted, or its login session ended)."""
        import submitit

        path = marker(Path(job.work), job.name, ".jobid")
        if not self.slurm or not path.is_file():
            return None
        handle = submitit.SlurmJob(folder=self.executor.folder, job_id=path.read_text().strip())
        return handle if handle.state.split()[0] in self.ACTIVE else None

    def running(self, handle) -> bool:
        """``handle.done()`` alone: submitit's outcome read (``exception()``) waits 15 s for the result file of a job
        that has none (one stopped at a deadline), per job: eight stopped jobs held the stop 120 s, past the bundle's
        timeout, so no state was saved (session 19, two H100 calls lost)."""
        return not handle.done()

    def state(self, handle) -> str:
        if self.running(handle):
            return RUNNING
        if not self.slurm and not handle.paths.result_pickle.exists():
            return FAILED  # a local job ended without its result (killed): submitit would wait 15 s for it
        try:
            return FAILED if handle.exception() is not None else DONE
        except Exception:  # noqa: BLE001 - a job with no result (killed, cancelled) counts as failed
            return FAILED

    def error(self, handle) -> str:
        try:
            exc = handle.exception()
        except Exception as e:  # noqa: BLE001
            exc = e
        lines = [ln for ln in str(exc).strip().splitlines() if ln.strip()]
        stage = [ln for ln in lines if "StageFailed" in ln or ": exit " in ln]
        return (stage or lines or ["no result"])[-1].strip()

    def log(self, handle) -> Path:
        return handle.paths.stdout

    def cancel(self, handle) -> None:
        try:
            handle.cancel(check=False)
        except Exception:  # noqa: BLE001 - already gone
            pass

    def stop_jobs(self, handles: dict, work: Path, log, poll_s: float) -> None:
        """Local jobs: each running stage's stop file first (``.grid/<job>.stop``: a training checkpoints at its
        iteration's end and exits, with no signal: under CUDA MPS a SIGTERM to a process with GPU work in flight ended
        every process on the GPU, NOTES session 42), up to ``STOP_REQUEST_S`` for them to end on their own (a training
        that finished as the request came exits 0 and its job writes the ``.done`` marker: session 25, the cancel
        killed the job first and a finished 441-s run trained again); then SIGTERM to each stage process still running
        (``.grid/<job>.pid``: a data stage or an evaluation does not read the file; submitit's cancel is a SIGINT to
        its controller, which did not always stop the stage: in fresh-clone CI runs a job ran on to its end after the
        deadline stop), then the cancel, then wait for them to end (at most ``STOP_GRACE_S`` + 10 s), so that the next
        call never starts a job whose stopped process still writes its outputs. SLURM jobs: the cancel (their end is
        SLURM's to see)."""
        if not self.slurm:
            t_end = time.monotonic() + STOP_REQUEST_S
            while True:  # the stop files first (a packed training stops without a signal, NOTES s42), again for a
                for name in handles:  # stage that started meanwhile
                    if _running_pid(marker(work, name, ".pid")) is not None and not marker(work, name, ".stop").exists():
                        _request_stop(marker(work, name, ".stop"))
                if time.monotonic() >= t_end or not any(self.running(h) for h in handles.values()):
                    break
                time.sleep(min(poll_s, 0.2))
            for name in handles:  # what did not stop at its file (a data stage, an evaluation): SIGTERM
                _terminate(marker(work, name, ".pid"))
        super().stop_jobs(handles, work, log, poll_s)
        if not self.slurm:
            _wait_stopped(self, handles, log, poll_s, work)


def local_engine(folder: Path, gpus: int | list[int], slots: int, timeout_min: float, max_requeue: int,
                 signal_delay_s: int = 60) -> SubmititEngine:
    """submitit's local executor: ``slots`` jobs per GPU (``gpus``: a count, GPUs 0 .. n-1, or ids; 0: no
    GPU, ``slots`` jobs on the CPU), each with a time limit of ``timeout_min``: ``signal_delay_s`` before it
    the job is checkpointed and requeued (at most ``max_requeue`` times)."""
    import submitit

    ids = list(range(gpus)) if isinstance(gpus, int) else list(gpus)
    places = [g for g in ids for _ in range(slots)] or [None] * slots
    executor = submitit.LocalExecutor(folder=folder, max_num_timeout=max_requeue)
    return SubmititEngine(executor, places, {"timeout_min": timeout_min, "signal_delay_s": signal_delay_s,
                                             "stderr_to_stdout": True})


def slurm_engine(folder: Path, timeout_min: float, max_requeue: int, partition: str | None = None,
                 cpus_per_task: int | None = None, extra: dict | None = None) -> SubmititEngine:
    """SLURM through submitit: one GPU per job, USR2 90 s before ``timeout_min`` (submitit requeues the
    job with its checkpoint), ``extra``: more sbatch options (``{"account": "x", "qos": "y"}``)."""
    import submitit

    executor = submitit.SlurmExecutor(folder=folder, max_num_timeout=max_requeue)
    params = {"time": int(timeout_min), "gpus_per_node": 1, "ntasks_per_node": 1, "stderr_to_stdout": True,
              "additional_parameters": dict(extra or {})}
    if partition:
        params["partition"] = partition
    if cpus_per_task:
        params["cpus_per_task"] = cpus_per_task
    return SubmititEngine(executor, None, params)


def critical_path(jobs: dict) -> dict[str, float]:
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


def estimated_s(job) -> float:
    """A job's estimated seconds on its own from its ``cost`` [GPU-minutes], with a 30 % margin (``--deadline``
    submits no job that would end late by it; the slot reservation counts inputs still to be made by it)."""
    return 60 * job.cost * 1.3


RUN_JOB_RE = re.compile(r"^(?:train|evaluate)@([^:/]+):([^:/]+)$")


def unit_of(name: str) -> str | None:
    """The (scene, seed) unit of a per-run job (``grid.split_train``/``split_evaluate``, or a batch of one seed's runs,
    ``grid.batch_runs``): ``train@ball:neuma@seed1``, ``evaluate@ball:gca@seed1`` and ``train@ball:neuma@seed1+gca@seed1``
    -> ``ball@seed1``, ``train@ball:gca`` -> ``ball@seed0``; None for any other job."""
    m = RUN_JOB_RE.match(name)
    if m is None:
        return None
    seed = re.search(r"@seed(\d+)", m.group(2))
    return f"{m.group(1)}@seed{seed.group(1) if seed else 0}"


def unit_keys(priority: dict[str, float], todo, expected_s: Callable[[str], float] | None = None,
              first: Callable[[str], bool] | None = None) -> dict[str, tuple[int, float, float, str]]:
    """Each (scene, seed) unit's rank key, lower first: 0 for a unit with a ``todo`` training job that ``first``
    names (a table to finish before the next begins, session 26), else 1 (0 for all without ``first``); then the
    longest path among all its jobs (``priority``'s, done or not: a unit keeps its rank as its runs finish), negated;
    then the training it has left (``expected_s`` [s] summed over its ``todo`` training jobs: a unit already under
    way comes before a fresh one of the same rank, so a cut-off table leaves it whole); then its name."""
    path: dict[str, float] = {}
    for n, value in priority.items():
        u = unit_of(n)
        if u is not None:
            path[u] = max(path.get(u, float("-inf")), round(value, 6))
    work = dict.fromkeys(path, 0.0)
    rank = dict.fromkeys(path, 0 if first is None else 1)
    for n in todo:
        u = unit_of(n)
        if u is not None and n.startswith("train@"):
            work[u] += 0.0 if expected_s is None else expected_s(n)
            if first is not None and first(n):
                rank[u] = 0
    return {u: (rank[u], -path[u], work[u], u) for u in path}


def launch_order(ready, priority: dict[str, float], todo,
                 expected_s: Callable[[str], float] | None = None,
                 first: Callable[[str], bool] | None = None,
                 units: dict[str, tuple[int, float, float, str]] | None = None) -> list[str]:
    """``ready`` job names in the order to launch them: per-run jobs grouped by their (scene, seed) unit
    (:func:`unit_of`), the units by :func:`unit_keys` (the longest path first, units of equal path by the least
    training left in their ``todo`` jobs), and within a unit each job by its own path; any other job by
    its own path. So the slots go to every method of one unit before the next unit, a table cut off by a machine's
    end leaves whole units, each usable for paired per-unit claims (issue 22 item 4; session 22 gave every slot to
    GCA, costed above NeuMA, and left no NeuMA run), and the quicker units finish first (Table 3 after Table 1: the
    pawn's ~430-s runs before the ball's ~850-s ones, not by the scenes' names). ``first(name)``: the units with
    such a training job left go before all others (:func:`unit_keys`). ``units``: those keys when the caller has
    them for the same arguments already (they are not computed again).
    """
    units = unit_keys(priority, todo, expected_s, first) if units is None else units

    def key(n: str):
        u = unit_of(n)
        if u is None or u not in units:  # inputs, a scene-level job, the report: among the first units
            return (0, -priority[n], 0.0, "", 0.0, n)
        return (*units[u], -priority[n], n)
    return sorted(ready, key=key)


def lease_admits(left_s: float, new_s: float, running: list[tuple[float, float]],
                 packed_s: Callable[[float, float], float], others: int = 0) -> bool:
    """Whether a training run expected ``new_s`` [s] at the grid's packing may start on a GPU where the trainings
    ``running`` go on (each: its expected seconds at the grid's packing, the fraction of its work left), with
    ``left_s`` [s] of the machine's lease left, beside ``others`` jobs more (evaluations: they share the GPU too).
    ``packed_s(seconds, k)``: those seconds at k-way packing (``grid.packed_seconds``). With
    k = len(running) + others + 1 it must end in time, and no running run that would end in
    time at (k - 1)-way may be pushed past the lease by it: the new run slows it to k-way for the new run's own
    time T = ``packed_s(new_s, k)`` only, (k - 1)-way again after it (:func:`pushed_end`). The other load is taken as
    constant from now on (a run ending earlier only speeds the rest up: a margin). At the grid's full packing this is
    the plain rule (``new_s <= left_s``); with fewer runs on the GPU, as at the tail of a machine, a run is quicker
    than its full-packing time and may still fit (session 25: with only ball and duck runs left, 30-45 of them were
    held back and the slots stood idle for the machine's last ~10 min). Session 27: the rule took the new run's load
    as lasting to the machine's end, and held 60-s NCLaw runs beside duck runs near the lease for ~13 min."""
    k = len(running) + others + 1
    t_new = packed_s(new_s, k)
    if t_new > left_s:
        return False
    for full, frac in running:
        alone, beside = packed_s(full, k - 1), packed_s(full, k)
        if frac * alone <= left_s < pushed_end(frac, alone, beside, t_new):
            return False
    return True


def pushed_end(frac: float, alone_s: float, beside_s: float, t_new: float) -> float:
    """Seconds until a running run with ``frac`` of its work left ends, when it shares the GPU one way more for
    ``t_new`` [s] (a new run's time) and as now after: ``alone_s`` / ``beside_s`` [s] its whole work's time at the
    present / the one-more packing. Ends within the new run's time: ``frac * beside_s``; else ``t_new`` plus the rest
    of its work (``frac - t_new / beside_s``) at ``alone_s``."""
    if frac * beside_s <= t_new:
        return frac * beside_s
    return t_new + (frac - t_new / beside_s) * alone_s


def job_runs(name: str) -> tuple[str, list[str]]:
    """(scene, run names) of a per-run job ``<stage>@<scene>:<run>[+<run>...]`` (``grid.split_runs``,
    ``grid.batch_runs``), also given as its marker's file stem (:func:`marker` keeps ``+``)."""
    scene, runs = name.split("@", 1)[1].split(":", 1)
    return scene, runs.split("+")


def record_progress(work: Path, name: str, left: float) -> None:
    """Write the fraction of training job ``name``'s work left when a call stopped it (``.grid/<name>.progress``, not
    a state file: a run goes on only on this machine), for the next call's :func:`lease_admits`."""
    from gca.io import write_text

    write_text(marker(work, name, ".progress"), f"left={left:.4f}\n")


def progress_left(work: Path, name: str) -> float | None:
    """The fraction of work left that :func:`record_progress` wrote for job ``name``, or None."""
    try:
        return float(marker(work, name, ".progress").read_text().split("=", 1)[1])
    except (OSError, IndexError, ValueError):
        return None


def dependents(jobs: dict, name: str) -> set[str]:
    """Every job that (transitively) runs after ``name``."""
    out, frontier = set(), {name}
    while frontier:
        frontier = {n for n, j in jobs.items() if j.after & frontier and n not in out}
        out |= frontier
    return out


def run(jobs: dict, engine: Engine, work: Path, log, deadline: float | None = None, poll_s: float = 1.0,
        job_env=None, stamp: str = "", launch_until: float | None = None,
        expected_s: Callable[[str], float] | None = None,
        packed_s: Callable[[float, float], float] | None = None,
        first: Callable[[str], bool] | None = None,
        may_wait: Callable[[str], bool] | None = None) -> dict[str, str]:
    """Run ``jobs`` (``gca.pipeline.grid.Job``: name, cmd, cost, ``after`` linked) through ``engine`` in ``work``.

    A job already done (``.grid/<job>.done``) is not submitted. A failed job is logged with its error and
    log path; the jobs after it are skipped (cancelled where already submitted); the others go on.
    ``deadline`` [s]: submit nothing that its estimated cost would not finish in time (training: resumable,
    submitted while ``grid.RESUMABLE_MIN_S`` remain) and stop what still runs then (to do next time).
    ``job_env(job, place)``: extra environment of a job's stage process; ``stamp``: what a job's ``.done``
    marker must hold to count (the digest of the inputs, :func:`is_done`). ``launch_until`` [s]: the time left to
    the machine (a lease that ends, beyond this command's ``deadline``): a training job without a checkpoint is
    launched only while its ``expected_s(name)`` [s] fits in it, since a run cut off by the machine's end resumes
    on no other machine (its remade inputs differ: session 20); one with a checkpoint goes on regardless.
    ``packed_s(seconds, k)`` (with slots): ``expected_s``'s seconds at k-way packing; the lease check then counts the
    trainings on the run's GPU and the work they have left (:func:`lease_admits`; a stopped run's left work goes to
    the next call, :func:`record_progress`). ``first(name)``: training jobs whose (scene, seed) units go before
    the others (:func:`launch_order`). ``may_wait(name)``: whether the slot reservation (:func:`waiting_above`'s rule)
    may keep training job ``name`` waiting for better-ranked units' coming runs (default every one; the grid exempts
    a job with no run that trains: NCLaw's is its scene's ~30-s launch-velocity fit, which its unit's runs wait on,
    session 47). Returns each job's state: done, failed, skipped or todo.
    """
    work = Path(work)
    (work / ".grid").mkdir(parents=True, exist_ok=True)
    state = {n: DONE if is_done(work, n, stamp) else "todo" for n in jobs}
    priority = critical_path(jobs)
    handles: dict[str, object] = {}
    place_of: dict[str, object] = {}
    started: dict[str, float] = {}
    shared: dict[str, float] = {}  # a training job's integral of the trainings running on its GPU (itself too) [s]
    last = [time.monotonic()]
    free = None if engine.places is None else list(engine.places)
    end = None if deadline is None else time.monotonic() + deadline
    machine_end = None if launch_until is None else time.monotonic() + launch_until
    held_back: set[str] = set()  # training jobs the machine's lease held back (logged once each)
    expected_now: dict[str, float] = {}  # expected_s of this poll (it reads the finished runs' records)
    full: dict[str, float] = {}  # a running training's expected seconds at the grid's packing (packed_s)
    left: dict[str, float] = {}  # and the fraction of its work left

    def expected(name: str) -> float:
        """``expected_s(name)`` [s] (0 without it), once per poll."""
        if expected_s is None:
            return 0.0
        if name not in expected_now:
            expected_now[name] = expected_s(name)
        return expected_now[name]

    def place_next():
        """The free place the next job goes to: the one with the fewest jobs."""
        return min(free, key=lambda p: sum(q == p for q in place_of.values()))

    def beside(place) -> list[str]:
        """The jobs running on ``place``."""
        return [m for m in handles if place_of.get(m) == place]

    def lease_fits(name: str) -> bool:
        """Whether training job ``name`` may start within the machine's lease (one with a checkpoint always)."""
        if machine_end is None or not name.startswith("train@") or _has_checkpoint(work, jobs[name]):
            return True
        if packed_s is None or not free:
            return time.monotonic() + expected(name) <= machine_end
        on = beside(place_next())
        running = [(full[m], left[m]) for m in on if m in full]
        return lease_admits(machine_end - time.monotonic(), expected(name), running, packed_s, len(on) - len(running))

    def fits(name: str) -> bool:
        if not lease_fits(name):
            if name not in held_back:  # said once: why a call starts no training (session 23: silent)
                held_back.add(name)
                need, way = expected(name), ""
                if packed_s is not None and free:
                    k = len(beside(place_next())) + 1
                    need, way = packed_s(need, k), f" at {k}-way"
                log(f"hold  {name}: expected {need:.0f} s{way}, the machine has {machine_end - time.monotonic():.0f} s "
                    "left (a run cut off by its end resumes nowhere); next machine")
            return False
        if end is None:
            return True
        need = RESUMABLE_MIN_S if name.startswith("train@") else estimated_s(jobs[name])
        return time.monotonic() + need < end

    def skip_after(name: str) -> None:
        for n in sorted(dependents(jobs, name)):
            if state[n] in ("todo", RUNNING):
                if n in handles:
                    engine.cancel(handles.pop(n))
                    if free is not None:
                        free.append(place_of.pop(n))
                state[n] = "skipped"
                log(f"skip  {n}: {name} failed")

    def reap() -> None:
        for n in list(handles):
            if n not in handles:  # cancelled meanwhile: a job before it failed
                continue
            s = engine.state(handles[n])
            if s == RUNNING:
                continue
            h = handles.pop(n)
            if free is not None:
                free.append(place_of.pop(n))
            took = time.monotonic() - started[n]
            full.pop(n, None)
            left.pop(n, None)
            if s == DONE:
                state[n] = DONE
                marker(work, n, ".progress").unlink(missing_ok=True)
                log(f"done  {n} in {took:.0f} s")
                if n in shared and took > 0:
                    record_sharing(work, n, shared.pop(n) / took)
            else:
                state[n] = FAILED
                path = engine.log(h)
                tail = Path(path).read_text(errors="replace")[-1500:] if Path(path).is_file() else ""
                log(f"FAIL  {n} ({engine.error(h)}) after {took:.0f} s; log: {path}\n{tail}")
                skip_after(n)

    def todo_units():
        """:func:`unit_keys` of the jobs still to do (this poll's ranks)."""
        return unit_keys(priority, [n for n, s in state.items() if s == "todo"], expected, first)

    def ready_jobs(keys):
        """Jobs whose inputs are done (an engine with dependencies: done or submitted), in :func:`launch_order`
        (whole (scene, seed) units first, longest path first; ``keys``: this poll's :func:`todo_units`, for the
        first pass); with dependencies, what becomes ready by submitting one comes next in the same pass."""
        ok = (DONE, RUNNING) if engine.dependencies else (DONE,)
        seen: set[str] = set()
        while True:
            ready = launch_order([n for n, s in state.items() if s == "todo" and n not in seen
                                  and all(state.get(a, DONE) in ok for a in jobs[n].after)], priority,
                                 [], expected, first, keys if not seen else todo_units())
            if not ready:
                return
            for n in ready:
                seen.add(n)
                yield n
            if not engine.dependencies:
                return

    def ready_in(name: str, memo: dict) -> float:
        """Seconds until job ``name`` has run, estimated: 0 when done (or not this grid's); a running job's
        :func:`estimated_s` less its time so far; a todo job's plus the longest of its inputs' (the inputs' chain:
        assets -> ... -> preprocess)."""
        if name not in memo:
            s_ = state.get(name, DONE)
            if s_ == DONE:
                memo[name] = 0.0
            elif s_ == RUNNING:
                memo[name] = max(0.0, estimated_s(jobs[name]) - (time.monotonic() - started[name]))
            else:
                memo[name] = estimated_s(jobs[name]) + max((ready_in(a, memo) for a in jobs[name].after), default=0.0)
        return memo[name]

    def waiting_above(keys):
        """With slots (one machine): ``n -> how many training runs of units ranked above n's are waiting for their
        inputs``: todo, not ready, no input failed or skipped, and expected to start and finish in time, counting
        the inputs still to be made (:func:`ready_in`) before the run itself (``expected``, the machine's lease;
        :data:`RESUMABLE_MIN_S` before the deadline). The free slots are kept for them: session 23's Table 3
        started one to three runs of four units as the scenes' inputs finished one by one, instead of the
        best-ranked unit whole. ``keys``: this poll's :func:`todo_units`. None where nothing waits."""
        if free is None:
            return None
        now, memo = time.monotonic(), {}

        def coming(m: str) -> bool:
            after = [a for a in jobs[m].after if state.get(a, DONE) != DONE]
            if not after or any(state.get(a) not in ("todo", RUNNING) for a in after):
                return False
            start_at = now + max(ready_in(a, memo) for a in after)
            if end is not None and start_at + RESUMABLE_MIN_S >= end:
                return False
            return machine_end is None or _has_checkpoint(work, jobs[m]) or start_at + expected(m) <= machine_end

        blocked = [m for m, s_ in state.items() if s_ == "todo" and m.startswith("train@") and unit_of(m) and coming(m)]
        if not blocked:
            return None
        # the launch order's ranks (session 27: without ``first`` the dragon's NCLaw units ranked above duck's Table 3
        # units by their long inputs, and kept three of eight slots free for them for 7 min)
        return lambda n: sum(1 for m in blocked if keys[unit_of(m)] < keys.get(unit_of(n) or "", (float("inf"),)))

    def tally() -> None:
        if free is None:  # SLURM places its jobs: which share a GPU is not known here
            return
        now = time.monotonic()
        training = [n for n in handles if n.startswith("train@")]
        for n in training:  # those on its GPU (``place_of``; one engine place, or none, for all)
            k = sum(1 for m in training if place_of.get(m) == place_of.get(n))
            dt = now - max(last[0], started[n])
            shared[n] = shared.get(n, 0.0) + k * dt
            if n in full and full[n] > 0:  # its work left, at the load of every job beside it; never below a
                # restart's worth (a run past its estimate is still protected by lease_admits)
                k_all = sum(1 for m in handles if place_of.get(m) == place_of.get(n))
                left[n] = max(min(1.0, JOB_START_S / full[n]), left[n] - dt / packed_s(full[n], k_all))
        last[0] = now

    while True:
        tally()
        reap()
        expected_now.clear()
        keys = todo_units()  # once per poll: the waiting rule's and the launch order's ranks
        waiting = waiting_above(keys)
        for n in ready_jobs(keys):
            if free is not None and not free:
                break
            if not fits(n):
                continue
            if waiting and n.startswith("train@") and (may_wait is None or may_wait(n)) and waiting(n) >= len(free):
                continue  # the free slots are kept for better-ranked units' runs whose inputs are being made
            place = None if free is None else place_next()
            env = dict(job_env(jobs[n], place)) if job_env else {}
            cmd = StageCommand(n, jobs[n].cmd, work, env, stamp)
            after = [handles[a] for a in jobs[n].after if a in handles]
            attached = engine.attach(cmd)
            handles[n] = attached if attached is not None else engine.submit(cmd, after, place)
            if free is not None:
                free.remove(place)
                place_of[n] = place
            state[n], started[n] = RUNNING, time.monotonic()
            if packed_s is not None and free is not None and n.startswith("train@") and expected_s is not None:
                full[n] = expected(n)  # resumed: what the last call left of it, and its restart again
                was = progress_left(work, n)
                left[n] = 1.0 if was is None else min(1.0, was + JOB_START_S / max(full[n], 1.0))
            log(("attach" if attached is not None else "start") + f" {n}"
                + ("" if free is None else f" on {'cpu' if place is None else f'gpu {place}'}")
                + f" (log {engine.log(handles[n])})")
        if not handles:
            return state
        if end is not None and time.monotonic() >= end:
            reap()
            tally()
            for n in left:
                if n in handles:
                    record_progress(work, n, left[n])
            stopping = {n: handles.pop(n) for n in list(handles)}
            for n in stopping:
                state[n] = "todo"
                log(f"stop  {n} at the deadline (resumes next time)")
            engine.stop_jobs(stopping, work, log, poll_s)
            for n in stopping:  # ended on its own after the signal, its work finished (its job wrote the marker)
                if is_done(work, n, stamp):
                    state[n] = DONE
                    marker(work, n, ".progress").unlink(missing_ok=True)
                    log(f"done  {n} as it was stopped")
            return state
        time.sleep(poll_s)


def record_sharing(work: Path, name: str, mean: float) -> None:
    """Add ``sharing=<mean>`` to training job ``name``'s ``.done`` marker: how many training jobs ran on its GPU at
    once, itself included, averaged over its time in this call (the last call, when it resumed across calls). A run
    packed 5-way takes ~0.7 of its time packed 8-way (``grid.packed_seconds``), so the machine-lease check scales
    finished runs' times by it (session 21)."""
    from gca.io import write_text

    path = marker(work, name)
    if path.is_file():  # whole or not at all (atomically): a marker is a state file, its stamp decides `is_done`
        write_text(path, path.read_text().rstrip("\n") + f"\nsharing={mean:.2f}\n")


def sharing(work: Path, name: str) -> float | None:
    """The ``sharing=`` of job ``name``'s ``.done`` marker (:func:`record_sharing`), or None (none recorded)."""
    path = marker(work, name)
    if path.is_file():
        for token in path.read_text().split():
            if token.startswith("sharing="):
                return float(token.split("=", 1)[1])
    return None


def _has_checkpoint(work: Path, job) -> bool:
    """Whether one of a training job's runs (its ``outs``: ``runs/<scene>/<run>``) left a checkpoint."""
    return any((work / out / "checkpoint.pt").is_file() for out in job.outs)


def _running_pid(pid_file: Path) -> int | None:
    """The stage process named in ``pid_file`` (``.grid/<job>.pid``, written by the job) if it still runs; a
    stale file (the process is gone) is removed."""
    try:
        pid = int(pid_file.read_text())
        os.kill(pid, 0)
        return pid
    except (OSError, ValueError):
        pid_file.unlink(missing_ok=True)
        return None


def _request_stop(stop_file: Path) -> bool:
    """Write ``stop_file`` (a stage's request to stop: ``gca.stop``); whether it could be written."""
    try:
        stop_file.parent.mkdir(parents=True, exist_ok=True)
        stop_file.write_text(f"{time.time():.0f}\n")
        return True
    except OSError:
        return False


def _terminate(pid_file: Path) -> None:
    """SIGTERM to the stage process named in ``pid_file`` (a clean stop: training checkpoints), if it runs."""
    import signal

    pid = _running_pid(pid_file)
    if pid is not None:
        try:
            os.kill(pid, signal.SIGTERM)
        except OSError:  # ended in between
            pass


def _wait_stopped(engine: Engine, stopping: dict, log, poll_s: float, work: Path) -> None:
    """Wait until the cancelled jobs ``stopping`` (name -> handle) have ended, their stage processes included (a
    stage stopped with SIGTERM checkpoints first; SIGKILL follows after ``STOP_GRACE_S``), at most ``STOP_GRACE_S``
    + 10 s, so that the next call never starts a job whose previous process still writes its outputs."""
    t_end = time.monotonic() + STOP_GRACE_S + 10.0
    left = dict(stopping)
    while left and time.monotonic() < t_end:
        left = {n: h for n, h in left.items()
                if engine.running(h) or _running_pid(marker(work, n, ".pid")) is not None}
        if left:
            time.sleep(min(poll_s, 0.2))
    for n in left:
        log(f"stop  {n}: still running {STOP_GRACE_S + 10.0:.0f} s after it was stopped")


def dvc_stages(done: dict[str, str]) -> list[str]:
    """The dvc.yaml stages all of whose jobs are done (``train@ball:gca`` is a job of ``train@ball``)."""
    stages: dict[str, bool] = {}
    for name, s in done.items():
        stage = name.split(":", 1)[0]
        stages[stage] = stages.get(stage, True) and s == DONE
    return sorted(k for k, ok in stages.items() if ok)


def engine_from_args(args, folder: Path) -> Engine:
    if args.engine == "slurm":
        extra = dict(kv.split("=", 1) for kv in args.sbatch)
        return slurm_engine(folder, args.timeout_min, args.max_requeue, args.partition, args.cpus_per_task, extra)
    return local_engine(folder, args.gpus, args.slots, args.timeout_min, args.max_requeue)


def gpu_ids(text: str) -> int | list[int]:
    """``--gpus``: ``4`` -> 4 (GPUs 0..3); ``1,2,3`` -> [1, 2, 3] (leaves GPU 0 to something else);
    ``3,`` -> [3] (one id)."""
    try:
        return [int(g) for g in text.split(",") if g] if "," in text else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--gpus {text!r}: a count or comma-separated GPU ids") from None


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1 (``--slots``: 0 would start no job and tell each ``GCA_RUNS_PER_GPU=0``)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: an integer >= 1 expected")
    return value


def add_engine_args(ap: argparse.ArgumentParser, slots: int = 1) -> None:
    """The engine's options: ``--engine``, ``--gpus``/``--slots`` (local), the time limit and requeues,
    ``--partition``/``--cpus-per-task``/``--sbatch`` (SLURM), ``--deadline``."""
    ap.add_argument("--engine", choices=("local", "slurm"), default="local",
                    help="local: submitit's local executor on this machine; slurm: one SLURM job per stage command")
    ap.add_argument("--gpus", type=gpu_ids, default=1, help="local: a count (GPUs 0 .. N-1; 0: CPU) or ids 0,1,2")
    ap.add_argument("--slots", type=positive_int, default=slots, help="local: concurrent jobs per GPU (per machine without GPU)")
    ap.add_argument("--timeout-min", type=float, default=24 * 60.0,
                    help="a job's time limit [min]: then it is checkpointed and requeued")
    ap.add_argument("--max-requeue", type=int, default=20, help="requeues at the time limit per job (preemptions: no limit)")
    ap.add_argument("--partition", help="slurm: the partition")
    ap.add_argument("--cpus-per-task", type=int, help="slurm: CPU cores per job")
    ap.add_argument("--sbatch", action="append", default=[], metavar="KEY=VALUE",
                    help="slurm: another sbatch option, e.g. --sbatch account=lab --sbatch qos=high")
    ap.add_argument("--deadline", type=float, help="seconds: submit nothing that would end later; stop what runs then")
