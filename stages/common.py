"""What the per-scene training stages share: their arguments and the scene they load (not a stage)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gca.config import section
from gca.pipeline.settings import Settings
from gca.pipeline.train import SceneInputs, default_device
from gca.train.methods import get_method


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
    """(settings, scene config, methods, inputs) of ``<stage>@<scene>``."""
    settings = Settings.load(f"{stage}@{args.scene}", args.params)
    scene = settings.scene(args.scene)
    methods = [get_method(m) for m in (args.methods or section(settings.params, f"scenes.{args.scene}.methods"))]
    inputs = SceneInputs(args.scene_dir, getattr(args, "prep", None), args.particles, args.gaussians,
                         args.prior_dir / f"{scene.prior}.pt")
    return settings, scene, methods, inputs

