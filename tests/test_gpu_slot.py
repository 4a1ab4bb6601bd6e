"""gca.gpu_slot: one GPU per stage process for DVC queue workers (lock files; no GPU needed to test)."""

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
print(claim({n}, Path({lock_dir!r}), poll_s=0.05, timeout_s={timeout}), flush=True)
sys.stdin.read()  # hold the GPU until the test closes stdin
"""


def _holder(lock_dir, n=2, timeout=None):
    code = HOLDER.format(n=n, lock_dir=str(lock_dir), timeout=timeout)
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
