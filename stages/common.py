"""What the per-scene training stages share: their arguments and the scene they load (not a stage)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gca import config
from gca.scenes import scene_config
from gca.train.methods import get_method
from gca.train.config import run_dir_name
from gca.train.run import SceneInputs, default_device, run_seeds, train_config


def scene_parser(description: str, paths: tuple[str, ...]) -> argparse.ArgumentParser:
    """--scene, --methods, --params, --device and the required path arguments ``paths``."""
    ap = argparse.ArgumentParser(description=description)
    for name in paths:
        ap.add_argument(f"--{name}", type=Path, required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--methods", nargs="*", help="default: scenes.<scene>.methods")
    ap.add_argument("--seeds", nargs="*", type=int, help="default: train.seeds (a method that does not train: the first)")
    ap.add_argument("--params", type=Path, default=Path("params.yaml"))
    ap.add_argument("--device", default=default_device(), help="cuda when available, else cpu")
    return ap


def scene_context(stage: str, args: argparse.Namespace):
    """(params, scene config, methods, inputs) of ``<stage>@<scene>``."""
    params = config.load(f"{stage}@{args.scene}", args.params)
    scene = scene_config(params, args.scene)
    methods = [get_method(m) for m in (args.methods or config.section(params, f"scenes.{args.scene}.methods"))]
    inputs = SceneInputs(args.scene_dir, getattr(args, "prep", None), args.particles, args.gaussians,
                         args.prior_dir / f"{scene.prior}.pt")
    return params, scene, methods, inputs


def scene_runs(params, methods, args) -> list[tuple]:
    """Every ``(method, seed, run name)`` the stage handles: ``train.seeds`` (or ``--seeds``) per method, seeds
    outermost (in their params order), so that a whole table's first seed is done before the second starts."""
    per_method = {m.name: run_seeds(params, m, args.seeds) for m in methods}
    return [(m, s, run_dir_name(m.name, s)) for s in train_config(params).seeds for m in methods
            if s in per_method[m.name]]
