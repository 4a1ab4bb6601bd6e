"""benchmarks/velocity_vs_cd.py: the launch velocity's error beside each (scene, seed)'s Chamfer distances."""

import importlib.util
import io
import json
import tarfile
from pathlib import Path

import numpy as np
import yaml

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "velocity_vs_cd.py"


def _module():
    spec = importlib.util.spec_from_file_location("velocity_vs_cd", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_errors_come_from_the_velocity_each_run_trained_with_and_rank_the_cd(tmp_path):
    truth = {"ball": [0.6, -2.0, 0.0], "pawn": [0.4, -2.2, 0.0]}
    members = {}
    for scene, offsets in (("ball", (0.1, 3.0, 1.0)), ("pawn", (0.5, 2.0, 0.2))):
        for seed, dz in enumerate(offsets):
            suffix = "" if seed == 0 else f"@seed{seed}"
            v0 = [truth[scene][0], truth[scene][1], dz]
            members[f"runs/{scene}/nclaw{suffix}/train.json"] = json.dumps({"velocity": {"v0": v0}})
            members[f"runs/{scene}/velocity{suffix}.json"] = json.dumps({"v0": [9.0, 9.0, 9.0]})  # overwritten later
            for method, scale in (("nclaw", 0.01), ("gca", 0.008)):
                members[f"metrics/eval/{scene}/{method}{suffix}.json"] = json.dumps({"chamfer_mean": scale * (1 + dz)})
    members["metrics/eval/pawn/gca@seed2.json"] = json.dumps({"status": "diverged"})  # no CD: that unit is left out
    state = tmp_path / "state.tgz"
    with tarfile.open(state, "w:gz") as tar:
        for name, text in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(text.encode())
            tar.addfile(info, io.BytesIO(text.encode()))
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"train": {"seeds": [0, 1, 2]}, "scenes": {s: {"v0": v} for s, v in truth.items()}}))
    rows = _module().main(["--state", str(state), "--params", str(params), "--methods", "nclaw", "gca"])
    assert len(rows) == 5 and not any(r["scene"] == "pawn" and r["seed"] == 2 for r in rows)
    ball1 = next(r for r in rows if r["scene"] == "ball" and r["seed"] == 1)
    assert np.allclose(ball1["error"], [0.0, 0.0, 3.0])  # the run's own estimate, not the seed's later file
    assert ball1["cd"] == {"nclaw": 0.04, "gca": 0.032}
