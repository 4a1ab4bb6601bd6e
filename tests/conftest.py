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


def pytest_collection_modifyitems(config, items):
    """Mark the tests listed in ``tests/slow.txt`` ``slow``; skip `gpu`-marked tests where torch has no CUDA device."""
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
