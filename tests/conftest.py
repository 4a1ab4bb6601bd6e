"""Shared fixtures: a private MLflow store per test session, warp on CPU, deterministic seeds."""

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _mlflow_in_tmp(tmp_path, monkeypatch):
    """Point MLflow at a throw-away sqlite store so tests never touch ./mlflow.db."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.setenv("GIT_PYTHON_REFRESH", "quiet")
    yield


@pytest.fixture
def repo_root() -> Path:
    return ROOT


def _slow_tests() -> set[str]:
    """``file::function`` names of the tests measured slow (``tests/slow.txt``)."""
    lines = (ROOT / "tests" / "slow.txt").read_text().splitlines()
    return {line.split("#")[0].strip() for line in lines} - {""}


# The files that take longest, longest first (session 58's fresh-clone run, `--durations=30` on the 2-core CPU: the
# DVC pipeline's fixture 580 s, the grid bundles ~450 s, the velocity fits ~380 s, ...). They are collected first so
# that `-n 2 --dist loadfile` (which hands out files in collection order) starts the long poles at once instead of
# leaving one worker idle at the end: the suite's wall time was 27 min with 83 % of the two cores busy.
LONG_FIRST = ("test_dvc_pipeline.py", "test_pipeline_grid.py", "test_train_velocity.py", "test_pipeline_smoke.py",
              "test_bench_sim.py", "test_pipeline_tune.py", "test_capture_e2e.py", "test_pipeline_chain.py")


def pytest_collection_modifyitems(config, items):
    """Collect the ``LONG_FIRST`` files first (in that order; the rest keep theirs); mark the tests listed in
    ``tests/slow.txt`` ``slow``; skip `gpu`-marked tests where torch has no CUDA device."""
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FIRST)))  # stable: each file's own order kept
    slow = _slow_tests()
    for item in items:
        if item.path.name in slow or f"{item.path.name}::{getattr(item, 'originalname', item.name)}" in slow:
            item.add_marker(pytest.mark.slow)
    try:
        import torch
        has_cuda = torch.cuda.is_available()
    except Exception:  # noqa: BLE001
        has_cuda = False
    if has_cuda:
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)
