"""Robust to what users do (issue 24): atomic writes and their litter, stamps on reused files, the stage
wrapper (one-line user errors, exit 2, --debug, SIGTERM), unreadable inputs naming the file, --help,
and `make pipeline` leaving params.yaml alone. Each probe asserts the exact message."""

from __future__ import annotations

import argparse
import importlib.util
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gca import io, stamp, stop
from gca.pipeline import cli

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("assets", "particles", "prior", "ground_truth", "preprocess", "train", "evaluate", "demo", "report")


# ------------------------------------------------------------------------------------------ gca.io


def test_atomic_outputs_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        io.write_json(tmp_path / "a.json", {"a": 1})
        with io.atomic_path(tmp_path / "d", is_dir=True) as tmp:
            (tmp / "x").write_text("x")
        os.umask(0o002)
        io.write_text(tmp_path / "b.txt", "b")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "d").stat().st_mode) == 0o755
    assert stat.S_IMODE((tmp_path / "b.txt").stat().st_mode) == 0o664


def test_exception_leaves_no_temporary_and_the_old_output(tmp_path):
    io.write_text(tmp_path / "out.txt", "good")
    with pytest.raises(RuntimeError):
        with io.atomic_path(tmp_path / "out.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    with pytest.raises(stop.Terminated):
        with io.atomic_path(tmp_path / "dir", is_dir=True) as tmp:
            (tmp / "x").write_text("half")
            raise stop.Terminated()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    assert (tmp_path / "out.txt").read_text() == "good"


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_sweep_removes_stale_temporaries_and_keeps_live_ones(tmp_path):
    dead = _dead_pid()
    (tmp_path / "ball").mkdir()
    (tmp_path / ".ball.at4r17my").mkdir()  # a SIGKILLed run before issue 24 (mkdtemp's name)
    (tmp_path / f".ball.tmp{dead}.k2j3").mkdir()  # a SIGKILLed run
    (tmp_path / f".law.pt.tmp{dead}.abcd.pt").write_text("half")
    live = tmp_path / f".law.pt.tmp{os.getpid()}.live.pt"  # this process is writing it
    live.write_text("in progress")
    (tmp_path / ".gitignore").write_text("/ball\n")
    (tmp_path / ".bashrc.backup12").write_text("a user's file that looks like an old temporary")
    removed = io.sweep(tmp_path)  # a stage's start: only what a dead process's pid names
    assert sorted(p.name for p in removed) == sorted([f".ball.tmp{dead}.k2j3", f".law.pt.tmp{dead}.abcd.pt"])
    assert io.sweep(tmp_path, "ball") == [tmp_path / ".ball.at4r17my"]  # before writing ball: its old litter too
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([".bashrc.backup12", ".gitignore", "ball", live.name])


def test_sweep_puts_back_an_output_parked_by_a_cut_swap(tmp_path):
    dead = _dead_pid()
    parked = tmp_path / f".scene.old{dead}"
    parked.mkdir()
    (parked / "meta.json").write_text("{}")
    assert io.sweep(tmp_path) == [parked]
    assert (tmp_path / "scene" / "meta.json").read_text() == "{}"


def test_unreadable_inputs_name_the_file(tmp_path):
    from gca.assets.particles import load_particles

    bad = tmp_path / "depth.npy"
    np.save(bad, np.zeros((4, 8, 8), np.float32))
    bad.write_bytes(bad.read_bytes()[:100])
    with pytest.raises(io.InputError) as info:
        io.load_array(bad, "depth")
    assert str(info.value).startswith(f"{bad}: unreadable depth (ValueError: ")
    npz = tmp_path / "particles.npz"
    np.savez(npz, x=np.zeros((100, 3)))
    npz.write_bytes(npz.read_bytes()[:200])
    with pytest.raises(io.InputError) as info:
        load_particles(npz)
    assert str(info.value).startswith(f"{npz}: unreadable particles file (BadZipFile: ")


def _scene(tmp_path, frame: np.ndarray):
    """A one-frame scene folder of a 4x4 camera whose rgb frame 0 is ``frame``."""
    import imageio.v3 as iio

    from gca.io import write_json
    from gca.render.camera import Camera
    from gca.scenes.store import frame_name, view_dir

    cam = Camera(np.array([[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1]]), np.eye(4), 4, 4)
    write_json(tmp_path / "meta.json", {"video_frames": [1]})
    write_json(tmp_path / "cameras.json", {"train0": cam.to_dict()})
    folder = view_dir(tmp_path, "train0")
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "mask").mkdir(exist_ok=True)
    iio.imwrite(folder / "rgb" / frame_name(0), frame)
    iio.imwrite(folder / "mask" / frame_name(0), np.zeros((4, 4), np.uint8))
    np.save(folder / "depth.npy", np.ones((1, 4, 4), np.float32))
    return folder / "rgb" / frame_name(0)


def test_greyscale_and_truncated_frames_name_the_file(tmp_path):
    from gca.scenes.store import SceneDataError, load_view

    path = _scene(tmp_path, np.zeros((4, 4), np.uint8))
    with pytest.raises(SceneDataError, match=f"^{path}: expected a colour image \\(3 channels\\), got shape \\(4, 4\\)$"):
        load_view(tmp_path, "train0")
    path = _scene(tmp_path, np.zeros((4, 4, 3), np.uint8))
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(io.InputError, match=f"^{path}: unreadable image "):
        load_view(tmp_path, "train0")


# ------------------------------------------------------------------------------------------ gca.stamp


def test_stale_checkpoint_starts_afresh_and_says_so(tmp_path):
    ckpt = tmp_path / "gca" / "checkpoint.pt"
    ckpt.parent.mkdir()
    said = []
    assert not stamp.guard_checkpoint(ckpt, "aaaa", said.append)  # nothing to resume
    ckpt.write_bytes(b"weights")
    assert stamp.guard_checkpoint(ckpt, "aaaa", said.append)  # same params and inputs: resumed
    assert said == []
    assert not stamp.guard_checkpoint(ckpt, "bbbb", said.append)  # params changed
    assert not ckpt.exists()
    assert said == [f"{ckpt}: not resumed: the checkpoint was made with other params or inputs "
                    "(stamp aaaa != bbbb); training afresh"]
    ckpt.write_bytes(b"weights")
    (tmp_path / "gca" / "checkpoint.pt.stamp").unlink()
    stamp.guard_checkpoint(ckpt, "bbbb", said.append)
    assert said[-1] == f"{ckpt}: not resumed: the checkpoint has no stamp (stamp None != bbbb); training afresh"
    stamp.clear_checkpoint(ckpt)
    assert list((tmp_path / "gca").iterdir()) == []


def test_fingerprint_follows_params_and_input_content(tmp_path):
    params = {"train": {"iterations": 40, "lr": 1e-3}, "video": {"n_frames": 16}}
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "a.npy").write_bytes(b"1")
    base = stamp.fingerprint(params, ["train"], [tmp_path / "in"])
    assert stamp.fingerprint({**params, "video": {"n_frames": 3}}, ["train"], [tmp_path / "in"]) == base
    assert stamp.fingerprint({**params, "train": {"iterations": 2, "lr": 1e-1}}, ["train"], [tmp_path / "in"]) != base
    (tmp_path / "in" / ".a.npy.tmp1.x").write_bytes(b"litter")  # temporaries are not inputs
    assert stamp.fingerprint(params, ["train"], [tmp_path / "in"]) == base
    (tmp_path / "in" / "a.npy").write_bytes(b"2")
    assert stamp.fingerprint(params, ["train"], [tmp_path / "in"]) != base


# ------------------------------------------------------------------------------------------ gca.cli


def test_user_error_is_one_line_and_exit_2(capsys):
    from gca.config import ConfigError

    def main(argv):
        raise ConfigError("params: train.iterations=-5 must be >= 1")

    assert cli.run(main, [], name="train") == 2
    assert capsys.readouterr().err == "train: error: params: train.iterations=-5 must be >= 1\n"
    assert cli.run(main, ["--debug"], name="train") == 2
    err = capsys.readouterr().err
    assert err.startswith("Traceback") and err.endswith("train: error: params: train.iterations=-5 must be >= 1\n")


def test_internal_error_keeps_its_traceback():
    def main(argv):
        raise ZeroDivisionError("a bug")

    with pytest.raises(ZeroDivisionError):
        cli.run(main, [], name="train")


def _run_restoring_sigterm(main, name: str, argv: list[str] | None = None) -> int:
    """``cli.run(main, argv)`` as stage ``name``; the test process's SIGTERM handler and stop state (the watcher
    included) restored after."""
    previous = signal.getsignal(signal.SIGTERM)
    try:
        return cli.run(main, argv or [], name=name)
    finally:
        signal.signal(signal.SIGTERM, previous)
        stop.reset()


def test_sigterm_ends_a_stage_cleanly(tmp_path, capsys):
    def main(argv):
        with io.atomic_path(tmp_path / "out", is_dir=True) as tmp:
            (tmp / "half").write_text("x")
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)

    assert _run_restoring_sigterm(main, "ground_truth") == 143
    assert capsys.readouterr().err == "ground_truth: stopped by SIGTERM\n"
    assert list(tmp_path.iterdir()) == []


def test_sigterm_while_the_stage_start_sweeps_is_a_clean_stop_too(tmp_path, capsys, monkeypatch):
    """Issue 24 item 7: the start's sweep of stale temporaries is inside the clean-stop handling (it was
    before it: a SIGTERM there ended the stage with 143 and no message)."""
    def sweeping(folder):
        raise stop.Terminated()

    monkeypatch.setattr(cli, "sweep", sweeping)
    assert cli.run(lambda argv: None, ["--out", str(tmp_path / "out")], name="assets") == 143
    assert capsys.readouterr().err == "assets: stopped by SIGTERM\n"


def test_sigterm_in_training_waits_for_the_checkpoint():
    saved = []
    previous = signal.getsignal(signal.SIGTERM)
    stop.install()
    try:
        with pytest.raises(stop.Terminated):
            with stop.deferred():
                for it in range(5):
                    if it == 2:
                        os.kill(os.getpid(), signal.SIGTERM)
                    if stop.requested():
                        saved.append(it)  # the loop's checkpoint
                    stop.check()
    finally:
        signal.signal(signal.SIGTERM, previous)
        stop.reset()
    assert saved == [2]



def test_sigterm_after_the_last_check_keeps_the_finished_work():
    """stop_at_end=False (the train stage): a SIGTERM after the loop's last check, while the run writes its results,
    ends the block normally (the run is kept) and stops at the caller's next check; the default block stops at its
    end (negative control)."""
    previous = signal.getsignal(signal.SIGTERM)
    stop.install()
    try:
        with stop.deferred(stop_at_end=False):
            stop.check()  # the loop's last check
            os.kill(os.getpid(), signal.SIGTERM)  # during the final writes
            written = True
        assert written and stop.requested()
        with pytest.raises(stop.Terminated):
            stop.check()  # before the next run
        stop.reset()
        with pytest.raises(stop.Terminated):
            with stop.deferred():
                os.kill(os.getpid(), signal.SIGTERM)
    finally:
        signal.signal(signal.SIGTERM, previous)
        stop.reset()

def test_a_stop_file_stops_like_sigterm_without_a_signal(tmp_path, monkeypatch):
    """NOTES session 42: under CUDA MPS a SIGTERM to a process with GPU work in flight ended every process on the GPU;
    a stop file (GCA_STOP_FILE) asks for the same stop with no signal: not before the file exists (negative control),
    then latched (the file removed, the stop stands), with the file named in the stop's message."""
    path = tmp_path / "job.stop"
    monkeypatch.setenv(stop.STOP_FILE_ENV, str(path))
    monkeypatch.delenv(stop.STOP_AT_ENV, raising=False)
    try:
        assert not stop.requested()  # no file yet: no stop (negative control)
        stop.check()
        path.write_text("now\n")
        assert stop.requested()
        path.unlink()
        assert stop.requested(), "a stop once asked stands"
        with pytest.raises(stop.Terminated, match=f"stopped by the stop file {path}"):
            stop.check()
    finally:
        stop.reset()
    assert not stop.requested()


def test_a_deadline_stops_once_it_has_passed(monkeypatch):
    monkeypatch.delenv(stop.STOP_FILE_ENV, raising=False)
    try:
        monkeypatch.setenv(stop.STOP_AT_ENV, f"{time.time() + 3600:.0f}")
        stop.check()  # an hour ahead: no stop (negative control)
        monkeypatch.setenv(stop.STOP_AT_ENV, f"{time.time() - 1:.3f}")
        with pytest.raises(stop.Terminated, match="stopped at the deadline GCA_STOP_AT="):
            stop.check()
        stop.reset()
        monkeypatch.setenv(stop.STOP_AT_ENV, "soon")
        with pytest.raises(ValueError, match="GCA_STOP_AT='soon' is not a Unix time"):
            stop.requested()
    finally:
        stop.reset()


def test_a_stage_stopped_at_its_stop_file_ends_143_with_the_reason(tmp_path, monkeypatch, capsys):
    path = tmp_path / "job.stop"
    monkeypatch.setenv(stop.STOP_FILE_ENV, str(path))
    waited = []
    monkeypatch.setattr(stop, "quiesce", lambda: waited.append(True))  # the GPU's queued work, before the exit

    def main(argv):
        with io.atomic_path(tmp_path / "out", is_dir=True) as tmp:
            (tmp / "half").write_text("x")
            path.write_text("1\n")
            stop.check()

    assert _run_restoring_sigterm(main, "train") == 143
    assert capsys.readouterr().err == f"train: stopped by the stop file {path}\n"
    assert waited == [True] and [p.name for p in tmp_path.iterdir()] == ["job.stop"]


def test_a_stage_that_never_reads_the_flag_stops_at_its_file_without_a_signal(tmp_path, monkeypatch, capsys):
    """The watcher (gca.stop.install) raises the stop in the main thread with no signal: a data stage or an evaluation,
    which never reads the flag, ends 143 within a poll of the file's appearance; without the file it runs to its end
    (negative control), and a GCA_STOP_AT that is no time is one line, exit 2."""
    path = tmp_path / "job.stop"
    monkeypatch.setenv(stop.STOP_FILE_ENV, str(path))
    steps = []

    def main(argv):
        for i in range(60):  # 3 s of work, in steps (the stop lands between two)
            steps.append(i)
            if i == 4 and argv:
                path.write_text("1\n")
            time.sleep(0.05)

    t0 = time.monotonic()
    assert _run_restoring_sigterm(main, "ground_truth", ["--stop"]) == 143
    assert time.monotonic() - t0 < 2.0 and len(steps) < 60, len(steps)
    assert capsys.readouterr().err == f"ground_truth: stopped by the stop file {path}\n"
    path.unlink()
    steps.clear()
    assert _run_restoring_sigterm(main, "ground_truth", []) == 0 and len(steps) == 60
    monkeypatch.setenv(stop.STOP_AT_ENV, "later")
    assert _run_restoring_sigterm(main, "ground_truth", []) == 2
    assert capsys.readouterr().err == "ground_truth: error: gca/stop.py: GCA_STOP_AT='later' is not a Unix time in seconds\n"


def test_the_parent_to_watch_is_this_processs_own_and_checked(monkeypatch):
    """GCA_STOP_PARENT: install() takes it out of the environment (a child's parent is this process, not the job) and
    the stop comes once the parent is another process; this process's own parent asks for no stop (negative
    control); a value that is no process id is refused."""
    monkeypatch.delenv(stop.STOP_FILE_ENV, raising=False)
    monkeypatch.delenv(stop.STOP_AT_ENV, raising=False)
    cleared = []
    monkeypatch.setattr(stop, "parent_death_signal", cleared.append)  # not pytest's own
    previous = signal.getsignal(signal.SIGTERM)
    try:
        monkeypatch.setenv(stop.STOP_PARENT_ENV, str(os.getppid()))
        stop.install()
        assert stop.STOP_PARENT_ENV not in os.environ and not stop.requested() and cleared == [0]
        stop.reset()
        monkeypatch.setenv(stop.STOP_PARENT_ENV, str(os.getppid() + 100000))  # not our parent: as if it had ended
        stop.install()
        with pytest.raises(stop.Terminated, match=r"stopped: its parent process \d+ ended \(GCA_STOP_PARENT\)"):
            stop.check()
        stop.reset()
        monkeypatch.setenv(stop.STOP_PARENT_ENV, "the job")
        with pytest.raises(ValueError, match="GCA_STOP_PARENT='the job' is not a process id"):
            stop.install()
    finally:
        signal.signal(signal.SIGTERM, previous)
        stop.reset()


def test_quiesce_waits_for_the_gpu_only_where_torch_has_started_cuda(monkeypatch):
    import torch

    calls = []
    monkeypatch.setattr(torch.cuda, "synchronize", lambda *a: calls.append("sync"))
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: False)
    stop.quiesce()
    assert calls == []  # no CUDA context: nothing to wait for (negative control)
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    stop.quiesce()
    assert calls == ["sync"]

    def faulted(*a):
        raise RuntimeError("CUDA error: an illegal memory access was encountered")
    monkeypatch.setattr(torch.cuda, "synchronize", faulted)
    stop.quiesce()  # a GPU already faulted: the stop's own message follows, not this error


def test_an_ended_watcher_never_stops_the_process(tmp_path, monkeypatch):
    """unwatch (cli.run's end, reset) ends the watcher: a stop file written afterwards stops nothing; a live watcher
    does stop (control)."""
    path = tmp_path / "job.stop"
    monkeypatch.setenv(stop.STOP_FILE_ENV, str(path))
    previous = signal.getsignal(signal.SIGTERM)
    try:
        stop.install()
        stop.unwatch()
        path.write_text("1\n")
        time.sleep(3 * stop.WATCH_S)
        assert not stop._state["requested"]
        path.unlink()
        stop.install()
        with pytest.raises(stop.Terminated, match="stop file"):
            path.write_text("1\n")
            for _ in range(40):
                time.sleep(stop.WATCH_S / 4)
    finally:
        signal.signal(signal.SIGTERM, previous)
        stop.reset()


def _parser(stage: str, monkeypatch) -> argparse.ArgumentParser:
    """The argument parser a stage's main builds (caught at parse_args)."""
    sys.path.insert(0, str(ROOT / "stages"))
    spec = importlib.util.spec_from_file_location(f"stage_{stage}", ROOT / "stages" / f"{stage}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    caught = []

    def capture(self, args=None, namespace=None):
        caught.append(self)
        raise SystemExit(0)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    with pytest.raises(SystemExit):
        module.main([])
    return caught[0]


@pytest.mark.parametrize("stage", STAGES)
def test_help_documents_every_argument(stage, monkeypatch):
    parser = _parser(stage, monkeypatch)
    undocumented = [a.option_strings[0] for a in parser._actions if a.option_strings and not a.help]
    assert undocumented == []
    options = {a.option_strings[0] for a in parser._actions}
    assert "--debug" in options
    for name in ("--object", "--scene", "--family"):
        if name in options:
            action = next(a for a in parser._actions if name in a.option_strings)
            table = {"--object": "objects", "--scene": "scenes", "--family": "prior.families"}[name]
            assert f"a key of `{table}:`" in action.help


def test_unknown_scene_given_to_a_stage_is_one_line_exit_2(tmp_path):
    proc = subprocess.run([sys.executable, "stages/preprocess.py", "--scene", "nosuch", "--scene-dir", str(tmp_path),
                           "--out", str(tmp_path / "prep"), "--metrics", str(tmp_path / "m.json")],
                          cwd=ROOT, capture_output=True, text=True, env={**os.environ, "DVC_STAGE": ""})
    assert proc.returncode == 2
    assert proc.stderr == ("preprocess: error: params: unknown scene 'nosuch' (not a key of scenes: ball, bottle, "
                           "calib_mushroom, calib_star, calib_torus, cat, composite, dragon, duck, example_capture, fish, "
                           "pawn, pudding, wolf)\n")


# ------------------------------------------------------------------------------------- make pipeline


def test_pipeline_script_leaves_params_yaml_as_it_found_it(tmp_path):
    """scripts/pipeline.sh with a stand-in dvc that writes the -S override into params.yaml, as dvc does."""
    work = tmp_path / "repo"
    (work / "scripts").mkdir(parents=True)
    (work / "scripts" / "pipeline.sh").write_text((ROOT / "scripts" / "pipeline.sh").read_text())
    (work / ".venv" / "bin").mkdir(parents=True)
    (work / ".venv" / "bin" / "activate").write_text("")
    original = "# knobs\nprofile: paper   # paper | ci\nseed: 0\n"
    (work / "params.yaml").write_text(original)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "dvc"
    fake.write_text("#!/bin/sh\n# dvc exp run -S profile=X\nsed -i \"s/^profile: paper/profile: ${3#profile=}/\" params.yaml\n")
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "PROFILE": "ci", "GIT_DIR": str(tmp_path / "nogit")}
    proc = subprocess.run(["bash", "scripts/pipeline.sh"], cwd=work, capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    assert (work / "params.yaml").read_text() == original
    assert ("pipeline: params.yaml put back as it was (dvc exp run -S profile=ci had written the override into it; "
            "this run used profile=ci, recorded in dvc.lock and dvc exp show)") in proc.stderr


def test_progress_bars_are_quiet_under_ci_although_tqdm_was_imported_first(tmp_path):
    """Issue 24 item 5: under CI a stage prints no progress bar, although tqdm read its environment when the
    library imported it (before cli.run); the same script run without cli.run prints the bar (control)."""
    script = tmp_path / "stage.py"
    script.write_text(
        "import sys\nfrom tqdm import tqdm\nfrom gca.pipeline import cli\n"
        "def main(argv):\n    for _ in tqdm(range(3), desc='work-bar'):\n        pass\n"
        "if sys.argv[1:] == ['bare']:\n    main([])\nelse:\n    sys.exit(cli.run(main, []))\n")
    env = {**os.environ, "CI": "true"}
    env.pop("TQDM_DISABLE", None)
    quiet = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=120)
    bare = subprocess.run([sys.executable, str(script), "bare"], capture_output=True, text=True, env=env, timeout=120)
    assert quiet.returncode == 0 and "work-bar" not in quiet.stderr
    assert bare.returncode == 0 and "work-bar" in bare.stderr


HALF_BUILT = """
import sys
from gca import stop
from gca.pipeline import cli


class HalfBuilt:  # like GitPython's config parser when a SIGTERM lands inside its __init__ (CI, session 18)
    def __init__(self):
        raise stop.Terminated()  # what the signal handler raises, before the attribute is set
        self.ready = True

    def __del__(self):
        self.ready  # AttributeError: the object was never finished


def main(argv):
    HalfBuilt()


sys.exit(cli.run(main, [], name="stage"))
"""


def test_a_stop_inside_a_half_built_object_still_ends_on_the_stop_line(tmp_path):
    """A SIGTERM can land inside third-party code mid-construction; the half-built object's ``__del__`` then
    complains when it is collected. Its complaint stays visible but comes before the stage's last line, which is
    the stop (a job log's last line says why the stage ended), with exit status 143."""
    import subprocess

    script = tmp_path / "stage.py"
    script.write_text(HALF_BUILT)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert out.returncode == 143, out.stderr
    assert "AttributeError" in out.stderr  # not silenced
    assert out.stderr.strip().splitlines()[-1] == "stage: stopped by SIGTERM", out.stderr
