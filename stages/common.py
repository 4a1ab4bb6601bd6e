"""What the per-scene training stages share: their arguments and the scene they load (not a stage)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gca.pipeline import cli
from gca.config import section
from gca.pipeline.settings import Settings
from gca.pipeline.train import SceneInputs, default_device
from gca.train.methods import get_method


PATH_HELP = {"scene-dir": "the ground_truth stage's data/scenes/<scene>", "prep": "the preprocess stage's data/prep/<scene>",
             "particles": "data/particles/<object>.npz", "gaussians": "data/assets/<object>/gaussians.ply",
             "prior-dir": "models/prior (the scene's prior family's .pt)", "runs": "the train stage's runs/<scene>",
             "out": "output folder"}


def scene_parser(description: str, paths: tuple[str, ...]) -> argparse.ArgumentParser:
    """--scene, --methods, --params, --device and the required path arguments ``paths``."""
    ap = argparse.ArgumentParser(description=description)
    for name in paths:
        ap.add_argument(f"--{name}", type=Path, required=True, help=PATH_HELP.get(name, name))
    ap.add_argument("--scene", required=True, help="a key of `scenes:` in params.yaml (e.g. duck)")
    ap.add_argument("--methods", nargs="*", help="methods (table rows) to run; default: scenes.<scene>.methods")
    ap.add_argument("--seeds", nargs="*", type=int, help="default: train.seeds (a method that does not train: the first)")
    cli.add_common(ap, device=default_device())
    return ap


def scene_context(stage: str, args: argparse.Namespace):
    """(settings, scene config, methods, inputs) of ``<stage>@<scene>``."""
    settings = Settings.load(f"{stage}@{args.scene}", args.params)
    scene = settings.scene(args.scene)
    methods = [get_method(m) for m in (args.methods or section(settings.params, f"scenes.{args.scene}.methods"))]
    inputs = SceneInputs(args.scene_dir, getattr(args, "prep", None), args.particles, args.gaussians,
                         args.prior_dir / f"{scene.prior}.pt")
    return settings, scene, methods, inputs

