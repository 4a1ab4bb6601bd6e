"""gca.gpu_slot: GPU slots per stage process for DVC queue workers, one per GPU or ``GCA_RUNS_PER_GPU`` (lock files;
no GPU needed to test)."""

import os
import subprocess
import sys
import time

import pytest

from gca import gpu_slot

HOLDER = """
import sys
from pathlib import Path
from gca.gpu_slot import claim
print(claim({n}, Path({lock_dir!r}), poll_s=0.05, timeout_s={timeout}, per_gpu={per_gpu}), flush=True)
sys.stdin.read()  # hold the GPU until the test closes stdin
"""


def _holder(lock_dir, n=2, timeout=None, per_gpu=1):
    code = HOLDER.format(n=n, lock_dir=str(lock_dir), timeout=timeout, per_gpu=per_gpu)
    env = {k: v for k, v in os.environ.items() if k != gpu_slot.ENV}
    return subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _release(process):
    process.stdin.close()
    assert process.wait(timeout=30) == 0, process.stderr.read()


def test_processes_get_distinct_gpus_and_wait_while_all_are_held(tmp_path):
    a, b = _holder(tmp_path), _holder(tmp_path)
    index_a, index_b = int(a.stdout.readline()), int(b.stdout.readline())
    assert {index_a, index_b} == {0, 1}
    late = _holder(tmp_path, timeout=0.5)  # both held: it gives up after its timeout with a clear error
    assert late.wait(timeout=30) != 0 and "all 2 GPUs held by other gca processes" in late.stderr.read()
    waiting = _holder(tmp_path)
    time.sleep(0.5)
    assert waiting.poll() is None  # still waiting for a GPU
    _release(a)  # a's process exits: its GPU is free again
    assert int(waiting.stdout.readline()) == index_a
    _release(b)
    _release(waiting)


def test_pin_narrows_cuda_visible_devices(tmp_path, monkeypatch):
    monkeypatch.setenv(gpu_slot.LOCK_DIR_ENV, str(tmp_path))
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.delenv("CUDA_DEVICE_ORDER", raising=False)
    monkeypatch.delenv(gpu_slot.ENV, raising=False)
    assert gpu_slot.pin_from_env(n_gpus=4) is None and "CUDA_VISIBLE_DEVICES" not in os.environ  # off by default
    monkeypatch.setenv(gpu_slot.ENV, "1")
    assert gpu_slot.pin_from_env(n_gpus=0) is None  # no GPU on the machine
    held = _holder(tmp_path, n=4)  # another process holds GPU 0
    assert int(held.stdout.readline()) == 0
    monkeypatch.setattr(gpu_slot, "_held", None)
    assert gpu_slot.pin_from_env(n_gpus=4) == 1
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "1" and os.environ["CUDA_DEVICE_ORDER"] == "PCI_BUS_ID"
    assert gpu_slot.pin_from_env(n_gpus=4) is None  # already pinned (as grid.py's jobs are): left alone
    gpu_slot._held.close()  # let the lock go before the holder is released
    _release(held)


def test_no_gpu_to_claim_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="no GPU to claim"):
        gpu_slot.claim(0, tmp_path)


def test_runs_per_gpu_share_each_gpu_and_spread_over_them(tmp_path):
    """Two slots on each of two GPUs: four processes take slot 0 of GPU 0 and 1, then slot 1 of each (spread, not
    GPU 0 filled first); a fifth waits and gives up with the slots named; a freed slot is taken again. A one-slot
    process (GCA_RUNS_PER_GPU unset) excludes a two-slot one only from slot 0 (the same lock file there)."""
    holders, got = [], []
    for _ in range(4):  # one after the other: each has its slot before the next starts
        holders.append(_holder(tmp_path, per_gpu=2))
        got.append(int(holders[-1].stdout.readline()))
    assert got == [0, 1, 0, 1]
    late = _holder(tmp_path, timeout=0.5, per_gpu=2)
    assert late.wait(timeout=30) != 0 and "all 2 GPUs x 2 slots held" in late.stderr.read()
    single = _holder(tmp_path, timeout=0.5)  # one slot per GPU: both slot-0 locks are held
    assert single.wait(timeout=30) != 0 and "all 2 GPUs held" in single.stderr.read()
    _release(holders[3])  # GPU 1's slot 1 frees
    again = _holder(tmp_path, per_gpu=2)
    assert int(again.stdout.readline()) == 1
    for h in (*holders[:3], again):
        _release(h)
    with pytest.raises(ValueError, match="no slot to claim"):
        gpu_slot.claim(2, tmp_path, per_gpu=0)


def test_a_process_takes_the_gpu_with_the_most_free_slots(tmp_path):
    """Three slots on each of two GPUs, freed out of order: GPU 0's slots 1 and 2 and GPU 1's slot 0 held (GPU 0 has
    one free, GPU 1 two): the next process goes to GPU 1, not to GPU 0's free slot 0 (which the first-free order took).
    """
    import fcntl

    held = []
    for name in ("gpu0.slot1.lock", "gpu0.slot2.lock", "gpu1.lock"):
        handle = open(tmp_path / name, "a")
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        held.append(handle)
    nxt = _holder(tmp_path, per_gpu=3)
    assert int(nxt.stdout.readline()) == 1
    for handle in held:
        handle.close()
    _release(nxt)


def _pin(tmp_path, **env):
    """``pin_from_env`` in a fresh process (it runs at `import gca`) with ``env``: (exit status, stdout, stderr). An
    ``nvidia-smi`` that lists no GPU comes first on PATH, so the import's own pin leaves the process alone on a GPU
    machine too; the explicit call then counts 2."""
    code = "from gca import gpu_slot; import os; print(gpu_slot.pin_from_env(n_gpus=2), os.environ.get('GCA_MPS'))"
    stub = tmp_path / "bin"
    stub.mkdir(exist_ok=True)
    (stub / "nvidia-smi").write_text("#!/bin/sh\nexit 0\n")
    (stub / "nvidia-smi").chmod(0o755)
    base = {k: v for k, v in os.environ.items() if k not in ("CUDA_VISIBLE_DEVICES", "GCA_MPS", gpu_slot.RUNS_ENV,
                                                            gpu_slot.ENV)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**base, "PATH": f"{stub}:{os.environ['PATH']}",
                              gpu_slot.LOCK_DIR_ENV: str(tmp_path / "locks"), **env})
    return out.returncode, out.stdout.strip(), out.stderr.strip()


@pytest.mark.parametrize("bad", ["0", "-1", "two", "1.5", "\u00b2"])
@pytest.mark.parametrize("pinned", ["1", "0"])
def test_a_bad_runs_per_gpu_is_one_line_and_exit_2(tmp_path, bad, pinned):
    """Refused at `import gca` whether or not the process pins itself (the run would record it only after its
    training)."""
    rc, _, err = _pin(tmp_path, GCA_GPU_PER_PROCESS=pinned, GCA_RUNS_PER_GPU=bad)
    assert rc == 2 and err.splitlines() == [f"gca.gpu_slot: GCA_RUNS_PER_GPU={bad!r}: the runs per GPU must be an "
                                            "integer >= 1"]
    rc, out, _ = _pin(tmp_path, GCA_GPU_PER_PROCESS=pinned, GCA_RUNS_PER_GPU="2")  # the control: a good value
    assert rc == 0 and out.split()[0] == ("0" if pinned == "1" else "None")


def test_pin_says_the_sharing_and_records_whether_mps_runs(tmp_path):
    """With K slots the pinned process says it shares its GPU and whether an MPS daemon's control pipe is there
    (GCA_MPS, the run's record); a launcher's own GCA_MPS is kept; one slot says nothing of sharing."""
    pipe = tmp_path / "mps"
    pipe.mkdir()
    rc, out, err = _pin(tmp_path, GCA_GPU_PER_PROCESS="1", GCA_RUNS_PER_GPU="3", CUDA_MPS_PIPE_DIRECTORY=str(pipe))
    assert rc == 0 and out == "0 0" and "shared by up to 3 runs (GCA_RUNS_PER_GPU, CUDA MPS off)" in err
    (pipe / "control").write_text("")
    rc, out, err = _pin(tmp_path, GCA_GPU_PER_PROCESS="1", GCA_RUNS_PER_GPU="3", CUDA_MPS_PIPE_DIRECTORY=str(pipe))
    assert rc == 0 and out == "0 1" and "CUDA MPS on" in err
    (pipe / "control").unlink()
    os.mkfifo(pipe / "control")  # a named pipe nobody reads: a daemon killed without its cleanup, so off
    rc, out, err = _pin(tmp_path, GCA_GPU_PER_PROCESS="1", GCA_RUNS_PER_GPU="3", CUDA_MPS_PIPE_DIRECTORY=str(pipe))
    assert rc == 0 and out == "0 0" and "CUDA MPS off" in err
    reader = os.open(pipe / "control", os.O_RDONLY | os.O_NONBLOCK)  # the daemon reading its pipe: on
    try:
        rc, out, err = _pin(tmp_path, GCA_GPU_PER_PROCESS="1", GCA_RUNS_PER_GPU="3",
                            CUDA_MPS_PIPE_DIRECTORY=str(pipe))
        assert rc == 0 and out == "0 1"
    finally:
        os.close(reader)
    rc, out, _ = _pin(tmp_path, GCA_GPU_PER_PROCESS="1", GCA_RUNS_PER_GPU="3", CUDA_MPS_PIPE_DIRECTORY=str(pipe),
                      GCA_MPS="0")
    assert out == "0 0"
    rc, out, err = _pin(tmp_path, GCA_GPU_PER_PROCESS="1")
    assert rc == 0 and out.startswith("0 ") and "shared" not in err and "uses GPU 0 of 2" in err

