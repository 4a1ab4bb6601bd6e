"""The demo stage's glue: the demos' config, solver and learned laws from params and the pipeline's folders.

The demos themselves (simulate, render, combine bodies) are ``gca.eval.demos``; this module turns params
into their typed inputs and loads the trained laws the train stage left.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Sequence

import torch

from gca.eval.demos import (MISSING_LAW, DemoConfig, density, run_capture_demo, run_interaction, run_new_shape)
from gca.laws.base import Material
from gca.pipeline.settings import Settings
from gca.pipeline.train import SceneInputs, load_learned_law
from gca.scenes.store import TRAIN_VIEW, load_plate, read_cameras, read_meta
from gca.scenes.world import Body, load_body
from gca.sim.solver import MPMSolver
from gca.train.config import run_dir_name
from gca.train.methods import get_method

_WHERE = "gca/pipeline/demo.py"


def demo_config(settings: Settings) -> DemoConfig:
    """The :class:`DemoConfig` of params section ``demo``."""
    return settings.section_as(DemoConfig, "demo")


def demo_solver(settings: Settings, scenes: Sequence[str], device: str | torch.device = "cpu") -> MPMSolver:
    """The ``sim`` section's solver with the smallest ``dt`` of the given scenes (stable for all laws)."""
    dt = min(settings.scene(s).dt for s in scenes)
    return MPMSolver(dataclasses.replace(settings.sim, dt=dt), device)


@dataclasses.dataclass(frozen=True)
class DemoInputs:
    """Where the pipeline keeps what the demos read."""

    runs: Path  # runs/<scene>/<method>/law.pt
    data: Path  # data/particles/<object>.npz, data/assets/<object>/gaussians.ply
    prior_dir: Path  # models/prior/<family>.pt
    device: str = "cpu"  # torch device of bodies, laws and the solver

    def body(self, obj: str) -> Body:
        """The object's body (particles + Gaussians, sim frame) on ``device``."""
        return load_body(Path(self.data) / "particles" / f"{obj}.npz",
                         Path(self.data) / "assets" / obj / "gaussians.ply", self.device)


def load_demo_law(settings: Settings, scene: str, method: str, inputs: DemoInputs, rho: float,
                  missing_law: str = "prior") -> tuple[Material, str]:
    """The law ``method`` learned on ``scene`` with the first of ``train.seeds`` (``runs/<scene>/<method>/law.pt``
    for seed 0, ``<method>@seed<k>`` otherwise), with density ``rho``.

    Args:
        settings: the stage's typed params (scenes, sim, laws, train sections).
        scene: the scene the law was trained on (gives its prior family).
        method: method name (``gca``, ``neuma``, ...).
        inputs: pipeline folders.
        rho: density of the object it will drive [kg/m^3].
        missing_law: what to do without ``law.pt``: ``prior`` (warn, return the scene's prior law
            as is, i.e. the ``nclaw`` row) or ``error`` (raise ``FileNotFoundError``).

    Returns:
        ``(material, source)`` with ``source`` saying which law file was used.
    """
    family = settings.scene(scene).prior
    scene_inputs = SceneInputs(None, None, None, None, Path(inputs.prior_dir) / f"{family}.pt")
    seed = settings.train.seed
    run_dir = Path(inputs.runs) / scene / run_dir_name(method, seed)
    chosen = get_method(method)
    source = str(run_dir / "law.pt") if chosen.trains else f"prior {scene_inputs.prior} ({method} does not train)"
    if chosen.trains and not (run_dir / "law.pt").is_file():
        message = f"{_WHERE}: {run_dir / 'law.pt'}: no trained {method} law for scene {scene!r}"
        if missing_law == "error":
            raise FileNotFoundError(f"{message} (run the train stage, or set demo.missing_law: prior)")
        if missing_law != "prior":
            raise ValueError(f"{_WHERE}: missing_law must be one of {MISSING_LAW}, got {missing_law!r}")
        warnings.warn(f"{message}; falling back to the scene's {family!r} prior {scene_inputs.prior}",
                      RuntimeWarning, stacklevel=2)
        chosen, source = get_method("nclaw"), f"prior {scene_inputs.prior} (fallback: no {method} law.pt)"
    return load_learned_law(settings, scene, chosen, scene_inputs, run_dir, rho, inputs.device).material, source


def new_shape_demo(settings: Settings, cfg: DemoConfig, inputs: DemoInputs, out_dir: Path,
                   background=(1.0, 1.0, 1.0)) -> dict:
    """Load the target object and the borrowed law from the pipeline's files; run :func:`run_new_shape`."""
    ns = cfg.new_shape
    body = inputs.body(ns.object)
    material, source = load_demo_law(settings, ns.law_scene, ns.method, inputs, density(body), cfg.missing_law)
    solver = demo_solver(settings, [ns.law_scene], inputs.device)
    metrics = run_new_shape(solver, material, body, cfg, out_dir, background)
    return {**metrics, "law_scene": ns.law_scene, "method": ns.method, "object": ns.object, "law_source": source,
            "v0": list(ns.v0), "w0": list(ns.w0)}


def interaction_demo(settings: Settings, cfg: DemoConfig, inputs: DemoInputs, out_dir: Path,
                     background=(1.0, 1.0, 1.0)) -> dict:
    """Load both objects and their laws from the pipeline's files; run :func:`run_interaction`."""
    refs = (cfg.interaction.a, cfg.interaction.b)
    objects = [r.object or settings.scene(r.scene).object for r in refs]
    bodies = [inputs.body(o) for o in objects]
    laws = [load_demo_law(settings, r.scene, r.method, inputs, density(b), cfg.missing_law) for r, b in zip(refs, bodies)]
    solver = demo_solver(settings, [r.scene for r in refs], inputs.device)
    metrics = run_interaction(solver, [m for m, _ in laws], bodies, cfg, out_dir, background)
    for key, ref, obj, (_, source) in zip(("a", "b"), refs, objects, laws):
        metrics.setdefault(key, {}).update(scene=ref.scene, method=ref.method, object=obj, law_source=source)
    metrics.update(v0_a=list(cfg.interaction.v0_a), v0_b=list(cfg.interaction.v0_b))
    return metrics


def capture_demo(settings: Settings, scene: str, cfg: DemoConfig, inputs: DemoInputs, out_dir: Path,
                 background=(1.0, 1.0, 1.0)) -> dict:
    """A capture scene's new-scene demo (``demo.captures.<scene>``): the law learned on ``scene`` drives its
    object raised, turned and launched anew, filmed by the capture's camera over its plate
    (``data/scenes/<scene>``) at the video's frame rate (``round(1 / (fps dt))`` MPM steps per frame)."""
    if scene not in cfg.captures:
        raise ValueError(f"{_WHERE}: demo.captures has no entry {scene!r} (known: {', '.join(cfg.captures) or 'none'})")
    if not settings.scene(scene).is_capture:
        raise ValueError(f"{_WHERE}: demo.captures.{scene}: scenes.{scene} is not a capture scene (kind: capture)")
    cd = cfg.captures[scene]
    scene_dir = Path(inputs.data) / "scenes" / scene
    meta = read_meta(scene_dir)
    body = inputs.body(cd.object)
    material, source = load_demo_law(settings, scene, cd.method, inputs, density(body), cfg.missing_law)
    solver = demo_solver(settings, [scene], inputs.device)
    steps = int(meta["substeps"])
    metrics = run_capture_demo(solver, material, body, cd, read_cameras(scene_dir)[TRAIN_VIEW],
                               load_plate(scene_dir, TRAIN_VIEW), cfg.n_frames, steps, cfg, out_dir, background,
                               frame_ms=1000.0 * cfg.render_every / float(meta["fps"]))
    return {**metrics, "scene": scene, "method": cd.method, "object": cd.object, "law_source": source,
            "v0": list(cd.v0), "w0": list(cd.w0), "fps": float(meta["fps"]),
            "seconds_simulated": cfg.n_frames * steps * solver.cfg.dt}
