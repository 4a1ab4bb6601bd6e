"""Fault injection (issue 24 item 7): every stage of ``dvc.yaml``, killed with SIGKILL and with SIGTERM at a
point inside its work, then run again, leaves no partial output and no litter, and ends with the outputs of an
uninterrupted run.

The pipeline is ``dvc.yaml``'s, expanded (``gca.pipeline.grid.expand``) at the CI profile for one scene
(``ball``: its object, the ``jelly`` prior) and one method (``gca``), with the CI sizes cut further (``SHRINK``:
a few hundred Gaussians and particles, 2 video frames at 24 px, 2 training iterations) so the module stays
within ~90 s on the 2-core CI machine. A module fixture runs every stage once, uninterrupted, in dependency
order: the reference. Then, for each stage, in a copy of the reference without that stage's outputs:

1. SIGKILL at a random moment (seeded: ``GCA_FAULT_SEED``, default 0) within the first 60 % of the stage's
   reference time (``train``: 35 %, before its training ends), or sooner, a few milliseconds after an output's
   temporary first appears (polled), so a kill lands inside a write when the stage has a visible one;
   afterwards every output is absent or complete (equal to the reference's; ``train``'s and ``evaluate``'s
   folders fill file by file, so each file present is), and the only hidden entries are temporaries of the
   killed process;
2. the reference's outputs put back (a previous complete version), SIGTERM at a random moment (``train``: inside
   training, after its checkpoint stamp appeared): exit status 143 and the last line ``<stage>: stopped by
   SIGTERM``; the previous outputs still there and complete; no temporary of that process; the temporaries of
   step 1 beside the outputs swept at its start, each said; ``train`` saved its checkpoint first (loadable, at
   the iteration it stopped after);
3. a plain re-run: status 0, no hidden entry left anywhere under the outputs' roots, and the outputs equal
   the reference's (``train`` resumes from the checkpoint: its ``train.json`` says where).

A stage that ends before the moment drawn runs again with an earlier one (3 runs at most, then the test fails).
"Equal" is byte-equal, except the fields that measure the machine, not the result (JSON keys of timings,
memory and MLflow run ids: ``VOLATILE``) and the efficiency table built from them: the stages are
deterministic on the CPU (measured: two uninterrupted runs of this pipeline, one as ``python stages/x.py``
and one forked, differ in those fields only), a resumed training included.

A stage runs in a process forked from a server that imported the libraries once (``tests/forked_stages.py``:
the script itself runs as ``__main__``, as ``python stages/<x>.py`` after its imports); starting ~40
interpreters would take several times the time budget.
"""

from __future__ import annotations

import dataclasses
import json
import os
import queue
import random
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCENE, METHOD = "ball", "gca"
CAPTURE = "example_capture"  # a capture scene too: the demo_capture stage runs only for one (README "Your own object")
SEED = int(os.environ.get("GCA_FAULT_SEED", "0"))
# the CI profile, with sizes cut further (the work of every step still runs)
SHRINK = {
    "objects.ball.n_gaussians": 400, "particles.spacing": 0.05, "video.resolution": 24, "video.max_duration_s": 0.02,
    "render.lighting.shadow_resolution": 8, f"scenes.{SCENE}.extra_train_cameras": [],
    f"scenes.{SCENE}.eval_cameras": [{"azimuth_deg": 60}],
    "prior.train.iterations": 3, "prior.train.n_train": 1, "prior.train.n_heldout": 1, "prior.train.window": 4,
    "prior.train.batch": 1, "prior.train.data.n_steps": 20, "prior.train.data.particles_per_axis": 4,
    **{f"prior.train.{fit}.{key}": value for fit in ("fit_elasticity", "fit_plasticity")
       for key, value in (("steps", 30), ("n_samples", 256), ("batch_size", 64))},
    "velocity.iterations": 1, "velocity.n_video_frames": 2, "train.iterations": 2, "train.term_shares_every": 0,
    "eval.metrics.response_points": 5,
    "demo.n_frames": 2, "demo.resolution": 16, "demo.steps_per_frame": 2, "demo.strip_frames": 2,
    "demo.new_shape.law_scene": SCENE, "demo.new_shape.object": SCENE, "demo.interaction.b.scene": SCENE,
}
# JSON keys that measure the run, not its result; files made of them (compared for presence only)
VOLATILE = re.compile(r"seconds|^time/|^mlflow_run_id$|^peak_memory_gib$|^resumed_at$|^processes$")
VOLATILE_FILES = {"table4_efficiency.md", "table4_efficiency.csv"}
INCREMENTAL = {"train", "evaluate"}  # their folders fill file by file (each file atomic), not as one folder
KILL_WITHIN = {"train": 0.35}  # SIGKILL before training ends (its checkpoint would make the SIGTERM run resume past it)
# a temporary of gca.io: .<name>.tmp<pid>.<random>[.<suffix>] or a parked .<name>.old<pid>
TEMPORARY = re.compile(r"^\..+\.(?:tmp(?P<pid>\d+)\.[A-Za-z0-9_]+(?:\.[A-Za-z0-9]+)?|old(?P<old>\d+))$")


def _params() -> dict:
    from gca.pipeline import grid

    return grid.grid_params("ci", [SCENE, CAPTURE], [METHOD], [f"{k}={json.dumps(v)}" for k, v in SHRINK.items()])


def _jobs(params: dict) -> tuple[dict, dict]:
    """dvc.yaml's stage commands for ``params`` in an order where each comes after the jobs it reads (name ->
    job), and the job each stage is tested with (stage -> job: the synthetic scene's, else the capture's)."""
    from gca.pipeline import grid

    jobs = grid.link(grid.expand(yaml.safe_load((ROOT / "dvc.yaml").read_text()), params))
    order = []
    while len(order) < len(jobs):
        ready = [name for name, job in jobs.items() if name not in order and job.after <= set(order)]
        assert ready, f"dvc.yaml: a cycle among {sorted(set(jobs) - set(order))}"
        order.append(ready[0])
    ordered = {name: jobs[name] for name in order}
    chosen = {}
    for name, job in ordered.items():
        stage, _, key = name.partition("@")
        if stage not in chosen or key == SCENE:
            chosen[stage] = job
    return ordered, chosen


@dataclasses.dataclass
class Ended:
    pid: int
    returncode: int
    seconds: float  # from fork to exit
    log: str
    signalled: bool = False


class Server:
    """Client of ``tests/forked_stages.py``: runs a stage's command in a forked process, optionally signalled."""

    def __init__(self, env: dict):
        self.proc = subprocess.Popen([sys.executable, str(ROOT / "tests" / "forked_stages.py")], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env)
        self.lines = queue.Queue()
        threading.Thread(target=lambda: [self.lines.put(line) for line in self.proc.stdout], daemon=True).start()
        assert "ready" in self._answer(300), "the stage fork server did not start"

    def _answer(self, timeout: float) -> dict:
        try:
            return json.loads(self.lines.get(timeout=timeout))
        except queue.Empty:
            raise AssertionError(f"no answer from the stage fork server in {timeout} s") from None

    def run(self, cmd: str, cwd: Path, log: Path, sig: int | None = None, at: float = 0.0, early: float | None = None,
            watch: tuple[Path, ...] = (), after=None, timeout: float = 300.0) -> Ended:
        """Run ``cmd`` (a dvc.yaml command) in ``cwd``. With ``sig``: send it ``at`` seconds after the start
        (after ``after()`` first holds, when given) or, with ``early``, that many seconds after a hidden entry first
        appears in one of the ``watch`` folders, whichever comes first."""
        _, script, *argv = shlex.split(cmd)
        self.proc.stdin.write(json.dumps({"script": str(ROOT / script), "argv": argv, "cwd": str(cwd), "log": str(log),
                                          "env": {}}) + "\n")
        self.proc.stdin.flush()
        pid, start = self._answer(60)["pid"], time.monotonic()
        signalled, clock = False, None if after is not None else start
        while sig is not None and not signalled and self.lines.empty():
            now = time.monotonic()
            if clock is None and after():
                clock = now
            if clock is not None and early is not None and any(
                    any(p.name.startswith(".") for p in folder.iterdir()) for folder in watch if folder.is_dir()):
                at, early = min(at, now - clock + early), None
            if clock is not None and now - clock >= at:
                try:
                    os.kill(pid, sig)
                    signalled = True
                except ProcessLookupError:  # it ended first
                    break
            if now - start > timeout:
                os.kill(pid, signal.SIGKILL)
                raise AssertionError(f"{cmd}: no signal moment in {timeout} s:\n{log.read_text()}")
            time.sleep(0.003)
        answer = self._answer(timeout)
        assert answer["pid"] == pid
        return Ended(pid, answer["returncode"], time.monotonic() - start, log.read_text(), signalled)

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


@dataclasses.dataclass
class Pipeline:
    tmp: Path
    reference: Path
    jobs: dict
    seconds: dict
    server: Server


def _roots(jobs: dict) -> set[str]:
    return {Path(out).parts[0] for job in jobs.values() for out in job.outs}


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("faults")
    reference = tmp / "reference"
    reference.mkdir()
    params = _params()
    (reference / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    # TQDM_DISABLE: what gca.pipeline.cli asks for under CI (tqdm reads it when imported: before the fork)
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp / 'mlflow.db'}", "CI": "true", "TQDM_DISABLE": "1",
           "GIT_PYTHON_REFRESH": "quiet", "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    for key in ("DVC_STAGE", "DVC_ROOT"):
        env.pop(key, None)
    import mlflow  # its store made here (its schema migrations take seconds), not inside the first stage's time

    mlflow.MlflowClient(env["MLFLOW_TRACKING_URI"]).search_experiments()
    (reference / "captures").symlink_to(ROOT / "captures")  # the capture scene's scan, frames and camera
    server = Server(env)
    (ordered, jobs), seconds = _jobs(params), {}
    try:
        for name, job in ordered.items():
            done = server.run(job.cmd, reference, tmp / f"{name}.log")
            assert done.returncode == 0, done.log
            seconds[name] = done.seconds
        print("reference run [s]:", {name: round(t, 1) for name, t in seconds.items()})
        assert _litter(reference, _roots(ordered)) == []  # an uninterrupted run leaves nothing hidden
        yield Pipeline(tmp, reference, jobs, {stage: seconds[job.name] for stage, job in jobs.items()}, server)
    finally:
        server.close()


def _normal(value):
    if isinstance(value, dict):
        return {k: _normal(v) for k, v in value.items() if not VOLATILE.search(k)}
    if isinstance(value, list):
        return [_normal(v) for v in value]
    return value


def _content(path: Path):
    """What must be equal between two runs of a file (bytes; JSON without ``VOLATILE`` keys)."""
    if path.name in VOLATILE_FILES:
        return "<present>"
    if path.suffix == ".json":
        return _normal(json.loads(path.read_text()))
    return path.read_bytes()


def _outputs(folder: Path, outs: list[str]) -> dict:
    """Every non-hidden file of ``outs`` under ``folder``: relative path -> :func:`_content`."""
    files = {}
    for out in outs:
        path = folder / out
        found = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else []
        for p in found:
            rel = p.relative_to(folder)
            if not any(part.startswith(".") for part in rel.parts):
                files[str(rel)] = _content(p)
    return files


def _litter(folder: Path, roots) -> list[str]:
    """Hidden entries under the ``roots`` of ``folder`` (not those inside a hidden folder)."""
    found = []
    for root in sorted(roots):
        for parent, dirs, files in os.walk(folder / root):
            for name in sorted(dirs + files):
                if name.startswith("."):
                    found.append(str((Path(parent) / name).relative_to(folder)))
            dirs[:] = [d for d in dirs if not d.startswith(".")]
    return found


def _pid_of(path: str) -> int | None:
    match = TEMPORARY.match(Path(path).name)
    return int(match["pid"] or match["old"]) if match else None


def assert_no_partial_output(work: Path, reference: Path, outs: list[str], incremental: bool) -> None:
    """Each output is absent or complete: equal to the reference's (a folder written as one: all of its files;
    an ``incremental`` one: each file present), training's resume state (``checkpoint.pt`` and its stamp) whole."""
    for out in outs:
        if not (work / out).exists():
            continue
        mine, theirs = _outputs(work, [out]), _outputs(reference, [out])
        if not incremental:
            assert sorted(mine) == sorted(theirs), f"{out}: partial output"
        for rel, content in mine.items():
            if Path(rel).name == "checkpoint.pt":
                torch.load(work / rel, weights_only=False)  # whole: it loads
                continue
            if Path(rel).name == "checkpoint.pt.stamp":
                assert re.fullmatch(r"[0-9a-f]{16}\n", content.decode()), f"{rel}: {content!r}"
                continue
            assert rel in theirs, f"{rel}: not an output of an uninterrupted run"
            assert content == theirs[rel], f"{rel}: differs from the uninterrupted run's (half-written?)"


def _workspace(pipeline: Pipeline, work: Path, outs: list[str]) -> Path:
    """A copy of the reference without ``outs`` (and without the server logs and MLflow's artifacts)."""
    skip = {str(pipeline.reference / out) for out in outs}
    shutil.copytree(pipeline.reference, work, ignore=lambda d, names: [
        n for n in names if str(Path(d) / n) in skip or n == "mlruns"])
    return work


STAGES = [name for name in yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]]


def test_every_stage_is_covered(pipeline):
    assert sorted(pipeline.jobs) == sorted(STAGES)


@pytest.mark.parametrize("stage", STAGES)
def test_a_killed_stage_reruns_to_the_uninterrupted_outputs(pipeline, stage, tmp_path):
    job, reference = pipeline.jobs[stage], pipeline.reference
    roots, incremental = _roots(pipeline.jobs), stage in INCREMENTAL
    work = _workspace(pipeline, tmp_path / "work", job.outs)
    watch = tuple({(work / out).parent for out in job.outs} | {work / out for out in job.outs})
    rng, took = random.Random(f"{SEED}/{stage}"), pipeline.seconds[stage]
    name = Path(shlex.split(job.cmd)[1]).stem

    # 1. SIGKILL: no chance to clean up; a temporary may stay behind, nothing else
    for attempt in range(3):  # a fast stage may end before the moment drawn: draw an earlier one
        killed = pipeline.server.run(job.cmd, work, tmp_path / f"killed{attempt}.log", signal.SIGKILL,
                                     at=rng.uniform(0.05, KILL_WITHIN.get(stage, 0.6)) * took / 2 ** attempt,
                                     early=rng.uniform(0.0, 0.02),
                                     watch=watch)
        if killed.signalled and killed.returncode == -signal.SIGKILL:
            break
    assert killed.returncode == -signal.SIGKILL, killed.log
    assert_no_partial_output(work, reference, job.outs, incremental)
    litter = _litter(work, roots)
    assert all(_pid_of(p) == killed.pid for p in litter), litter

    # 2. SIGTERM, over the previous complete outputs: a clean stop (training: after a checkpoint) that keeps them
    for out in job.outs:
        source = reference / out
        if source.is_dir():
            shutil.copytree(source, work / out, dirs_exist_ok=True)
        else:
            shutil.copy2(source, work / out)
    swept = {str(Path(out).parent) for out in job.outs} | {out for out in job.outs if (reference / out).is_dir()}
    swept = [path for path in litter if str(Path(path).parent) in swept]  # the next start sweeps these, saying so
    after = (lambda: not any((work / path).exists() for path in swept)) if swept else None  # the clock starts then
    window = took
    if stage == "train":
        run = work / job.outs[0] / METHOD
        assert not (run / "checkpoint.pt").exists(), "the SIGKILL came after training: SIGTERM cannot land inside it"
        since = time.time_ns()
        # the checkpoint's stamp is (re)written just before training starts (gca.stamp.guard_checkpoint)
        after = lambda: (run / "checkpoint.pt.stamp").is_file() and (run / "checkpoint.pt.stamp").stat().st_mtime_ns > since  # noqa: E731
        history = json.loads((reference / job.outs[0] / METHOD / "history.json").read_text())["history"]
        window = sum(v for record in history for k, v in record.items() if k.startswith("time/"))
    logs = ""  # of every attempt: the first one swept
    for attempt in range(3):
        stopped = pipeline.server.run(job.cmd, work, tmp_path / f"stopped{attempt}.log", signal.SIGTERM,
                                      at=rng.uniform(0.05, 0.6) * window / 2 ** attempt, after=after)
        logs += stopped.log
        if stopped.signalled and stopped.returncode == 143:
            break
    assert stopped.returncode == 143, stopped.log
    assert stopped.log.strip().splitlines()[-1] == f"{name}: stopped by SIGTERM", stopped.log
    assert_no_partial_output(work, reference, job.outs, incremental)
    assert all((work / out).exists() for out in job.outs), "the previous outputs are gone"
    assert [p for p in _litter(work, roots) if _pid_of(p) == stopped.pid] == []
    for path in swept:
        assert f"{name}: removed the stale temporary {path} (an earlier run was killed)" in logs, logs
    if stage == "train":
        checkpoint = torch.load(run / "checkpoint.pt", weights_only=False)
        assert 1 <= checkpoint["iteration"] <= len(history), checkpoint["iteration"]

    # 3. the re-run: no litter, the uninterrupted outputs
    again = pipeline.server.run(job.cmd, work, tmp_path / "again.log")
    assert again.returncode == 0, again.log
    assert _litter(work, roots) == []
    assert _outputs(work, job.outs) == _outputs(reference, job.outs)
    if stage == "train":  # it went on from the checkpoint, to the same law
        record = json.loads((run / "train.json").read_text())
        assert record["resumed_at"] == checkpoint["iteration"]
        started = [process["resumed_at"] for process in record["processes"]]  # each process's first iteration
        assert started[0] == 0 and started[-1] == record["resumed_at"]
        assert not (run / "checkpoint.pt").exists() and not (run / "checkpoint.pt.stamp").exists()
    if stage == "prior":  # a stop in teacher forcing left a checkpoint, which the re-run used and removed
        out = work / job.outs[0]
        assert not list(out.parent.glob(out.name + ".checkpoint*")), sorted(out.parent.iterdir())


def test_the_checks_catch_litter_and_partial_output(tmp_path):
    """Negative controls: a planted temporary is litter (tagged with its process), a truncated file or a folder
    missing a file is partial output, a training checkpoint is not; the same tree passes."""
    reference, work = tmp_path / "reference", tmp_path / "work"
    (reference / "data/scenes/ball/views").mkdir(parents=True)
    (reference / "data/scenes/ball/views/a.png").write_bytes(b"\x89PNG whole")
    (reference / "data/scenes/ball/meta.json").write_text(json.dumps({"frames": 2, "train_seconds": 1.0}))
    shutil.copytree(reference, work)
    (work / "data/scenes/ball/meta.json").write_text(json.dumps({"frames": 2, "train_seconds": 9.0}))
    assert_no_partial_output(work, reference, ["data/scenes/ball"], incremental=False)  # timings differ: fine
    assert _litter(work, {"data"}) == []
    (work / "data/scenes/.ball.tmp4242.k2j3").mkdir()
    (work / "data/scenes/ball/views/.a.png.tmp4243.x1.png").write_bytes(b"")
    assert _litter(work, {"data"}) == ["data/scenes/.ball.tmp4242.k2j3", "data/scenes/ball/views/.a.png.tmp4243.x1.png"]
    assert [_pid_of(p) for p in _litter(work, {"data"})] == [4242, 4243] and _pid_of("data/.hidden") is None
    (work / "data/scenes/ball/views/a.png").write_bytes(b"\x89PNG")
    with pytest.raises(AssertionError, match="a.png: differs"):
        assert_no_partial_output(work, reference, ["data/scenes/ball"], incremental=True)
    (work / "data/scenes/ball/views/a.png").unlink()
    with pytest.raises(AssertionError, match="data/scenes/ball: partial output"):
        assert_no_partial_output(work, reference, ["data/scenes/ball"], incremental=False)
    assert_no_partial_output(work, reference, ["data/scenes/ball"], incremental=True)  # each file present is whole
    torch.save({"iteration": 1}, work / "data/scenes/ball/checkpoint.pt")
    (work / "data/scenes/ball/checkpoint.pt.stamp").write_text("0123456789abcdef\n")
    assert_no_partial_output(work, reference, ["data/scenes/ball"], incremental=True)
    data = (work / "data/scenes/ball/checkpoint.pt").read_bytes()
    (work / "data/scenes/ball/checkpoint.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(RuntimeError):  # a half-written checkpoint does not load
        assert_no_partial_output(work, reference, ["data/scenes/ball"], incremental=True)
    (work / "data/scenes/ball/checkpoint.pt").unlink()
    (work / "data/scenes/ball/law.pt").write_bytes(b"?")
    with pytest.raises(AssertionError, match="law.pt: not an output"):
        assert_no_partial_output(work, reference, ["data/scenes/ball"], incremental=True)
