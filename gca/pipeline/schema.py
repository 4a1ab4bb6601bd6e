"""The params schema: which typed config each ``params.yaml`` section builds, and the checks that need
more than one section. :func:`validate` runs at every :func:`gca.config.load` (under DVC on the whole
params file, not only the keys the stage declares), so a malformed params file stops a stage before it
computes anything, with one message naming the key.

Three kinds of check, all raising :class:`gca.config.ConfigError`:

- **Types and presence** (:func:`gca.config.build`): every key of a knob section is required (no code
  default may stand in for a missing key), values are coerced to the field's type (YAML 1.1 reads
  ``1e-3`` as a string) or refused, floats are finite.
- **Ranges** (:data:`RANGES`): counts >= 1, positive sizes and rates, and each dataclass's own checks.
- **Cross-references** (:func:`cross_check`): a scene's object, material, prior family and methods
  exist; the demo's scenes and objects exist (``demo.captures``' keys are capture scenes); the particles'
  floor gap lies above the walls' zone.

Which dataclass a section builds is :data:`KNOB_SECTIONS` (strict) and :data:`RECORD_TABLES` (a table of
records such as ``objects.<name>``). ``tests/test_pipeline_schema.py`` compares every config built from the
shipped ``params.yaml`` (both profiles) with its dataclass's defaults field by field: one source of truth.

``prior.train.sim`` is not a section of its own: it lists the keys where the prior's simulator departs
from ``sim`` (:func:`prior_sim`), and every other key comes from ``sim``.
"""

from __future__ import annotations

import importlib
import math
from typing import Any, Mapping

from gca.config import ConfigError, build, load as load_params, read_yaml, resolve, section
from gca.capture import objects as capture
from gca.scenes.config import OrbitCamera, SceneConfig

# params section -> the dataclass it builds (strict: every key required)
KNOB_SECTIONS: dict[str, str] = {
    "sim": "gca.sim.solver:SimConfig",
    "particles": "gca.assets.particles:ParticleConfig",
    "video": "gca.scenes.config:VideoConfig",
    "render.raster": "gca.render.rasterize:RasterConfig",
    "render.lighting": "gca.render.shading:LightingConfig",
    "vision": "gca.vision:VisionConfig",
    "laws.neural": "gca.laws.neural:NeuralLawConfig",
    "laws.lora": "gca.laws.lora:LoRAConfig",
    "prior.train": "gca.train.prior:PriorTrainConfig",
    "align.rdga": "gca.align.rdga:RDGAConfig",
    "align.cpr": "gca.align.cpr:CPRConfig",
    "velocity": "gca.train.config:VelocityConfig",
    "train": "gca.train.config:TrainConfig",
    "eval.metrics": "gca.eval.config:MetricsConfig",
    "demo": "gca.eval.demos:DemoConfig",
    "report": "gca.report:ReportConfig",
    "tuning": "gca.pipeline.tuning:TuningConfig",
}

# params table -> the dataclass each of its entries builds
RECORD_TABLES: dict[str, str] = {
    "objects": "gca.assets.objects:ObjectConfig",
}

# (section, key) -> (lowest allowed, strict?) : counts >= 1, sizes and rates > 0. The dataclasses check
# the rest (choices, fractions in [0, 1], ...).
RANGES: dict[str, tuple[float, bool]] = {
    "sim.dt": (0.0, True), "sim.n_grid": (4, False), "sim.max_refine": (1, False),
    "particles.spacing": (0.0, True), "particles.floor_gap": (0.0, True), "particles.n_candidates": (1, False),
    "video.n_frames": (1, False), "video.substeps": (1, False), "video.frame_every": (1, False),
    "video.resolution": (8, False),
    "render.raster.tile_size": (1, False), "render.raster.slab": (1, False), "render.raster.max_elems": (1, False),
    "render.raster.max_per_tile": (1, False),
    "laws.lora.rank": (1, False), "laws.neural.stress_scale": (0.0, True),
    "prior.train.iterations": (0, False), "prior.train.lr_elasticity": (0.0, False),  # 0: the warm start only
    "prior.train.lr_plasticity": (0.0, False),
    "align.cpr.subset_size": (2, False), "align.cpr.n_groups": (2, False), "align.cpr.refit_every": (1, False),
    "align.rdga.r": (1, False), "align.rdga.k": (1, False),
    "velocity.iterations": (1, False), "velocity.n_video_frames": (1, False), "velocity.lr": (0.0, True),
    "train.iterations": (1, False), "train.lr_elasticity": (0.0, True), "train.lr_plasticity": (0.0, True),
    "train.lr_explicit": (0.0, True), "train.grad_clip": (0.0, True), "train.cpr_every": (1, False),
    "train.checkpoint_every": (1, False), "train.max_spread_growth": (0.0, True),
    "demo.n_frames": (1, False), "demo.steps_per_frame": (1, False), "demo.resolution": (8, False),
    "report.dpi": (1, False),
}

PRIOR_SIM_KEY = "prior.train.sim"  # overrides of `sim` for the prior's simulator


def dataclass_of(spec: str) -> type:
    """The class named ``"module:Class"`` (imported lazily: the schema sits above every package)."""
    module, name = spec.split(":")
    return getattr(importlib.import_module(module), name)


def prior_sim(params: Mapping) -> dict:
    """The prior's simulator section: ``sim`` with ``prior.train.sim``'s keys replacing its values.

    A key of the overrides that ``sim`` lacks is an error (a typo would otherwise be a silent no-op).
    """
    base, overrides = section(params, "sim"), section(params, PRIOR_SIM_KEY)
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"params: {PRIOR_SIM_KEY} must be a mapping of `sim` keys to override")
    unknown = sorted(set(overrides) - set(base))
    if unknown:
        raise ConfigError(f"params: {PRIOR_SIM_KEY} overrides keys that `sim` does not have: {unknown}")
    return {**base, **overrides}


def _check_range(key: str, value: Any) -> None:
    low, strict = RANGES[key]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if not math.isfinite(value):
            raise ConfigError(f"params: {key}={value!r} must be a finite number")
        if value <= low if strict else value < low:
            raise ConfigError(f"params: {key}={value!r} must be {'>' if strict else '>='} {low}")


def build_section(params: Mapping, dotted: str) -> Any:
    """The typed config of knob section ``dotted`` (range-checked), from resolved params."""
    raw = section(params, dotted)
    if dotted == "video":
        raw = video_section(raw)
    if dotted == "prior.train":
        raw = {**raw, "sim": prior_sim(params)}
    if isinstance(raw, Mapping):
        for key, value in raw.items():
            if f"{dotted}.{key}" in RANGES:
                _check_range(f"{dotted}.{key}", value)
    return build(dataclass_of(KNOB_SECTIONS[dotted]), raw, dotted)


def _has(params: Mapping, dotted: str) -> bool:
    try:
        section(params, dotted)
    except ConfigError:
        return False
    return True


def validate(params: Mapping, stage: str | None = None) -> None:
    """Check every section of resolved ``params`` that is present (a DVC stage sees only its own).

    ``stage`` (``"train@duck"``; None: all checks): the demo's references to scenes are checked for the
    ``demo`` stage only (``demo.captures``': also for ``demo_capture``), so a params file cut down to a few
    scenes still runs their other stages."""
    for dotted in KNOB_SECTIONS:
        if _has(params, dotted) and (dotted != "prior.train" or _has(params, "sim")):
            build_section(params, dotted)
    for table, spec in RECORD_TABLES.items():
        if _has(params, table):
            for name, raw in section(params, table).items():
                if table == "objects" and capture.is_capture(raw):
                    continue  # a user's scan: the assets stage checks it with its files (one line naming them)
                build(dataclass_of(spec), raw, f"{table}.{name}")
    which = None if stage is None else stage.split("@")[0]
    cross_check(params, demo=which in (None, "demo"), captures=which in (None, "demo", "demo_capture"))


def _refs(params: Mapping, what: str, name: Any, table: str) -> list[str]:
    if not _has(params, table):
        return []
    known = section(params, table)
    if not isinstance(name, str) or name not in known:
        return [f"{what}={name!r} is not a key of {table} ({', '.join(map(str, known))})"]
    return []


def cross_check(params: Mapping, demo: bool = True, captures: bool = True) -> None:
    """References between sections, checked where both sides are visible (``demo``: the demo's too;
    ``captures``: ``demo.captures``')."""
    problems: list[str] = []
    if _has(params, "scenes"):
        from gca.train.methods import METHODS

        for name in section(params, "scenes"):
            raw = section(params, f"scenes.{name}")
            if not isinstance(raw, Mapping):
                raise ConfigError(f"params: scenes.{name} must be a mapping")
            scene = scene_config(raw, f"scenes.{name}")
            problems += _refs(params, f"scenes.{name}.object", scene.object, "objects")
            problems += _refs(params, f"scenes.{name}.material", scene.material, "materials")
            problems += _refs(params, f"scenes.{name}.prior", scene.prior, "prior.families")
            unknown = [m for m in scene.methods if m not in METHODS]
            if unknown:
                problems.append(f"scenes.{name}.methods: unknown methods {unknown} (valid: {', '.join(sorted(METHODS))})")
    if demo and _has(params, "demo") and _has(params, "scenes"):
        demo = section(params, "demo")
        problems += _refs(params, "demo.new_shape.law_scene", demo["new_shape"]["law_scene"], "scenes")
        problems += _refs(params, "demo.new_shape.object", demo["new_shape"]["object"], "objects")
        for side in ("a", "b"):
            problems += _refs(params, f"demo.interaction.{side}.scene", demo["interaction"][side]["scene"], "scenes")
    if captures and _has(params, "demo.captures") and _has(params, "scenes"):
        for name, entry in (section(params, "demo.captures") or {}).items():  # a capture scene's new-scene demo
            problems += _refs(params, f"demo.captures.{name}", name, "scenes")
            if isinstance(entry, Mapping):
                problems += _refs(params, f"demo.captures.{name}.object", entry.get("object"), "objects")
            if name in section(params, "scenes") and section(params, f"scenes.{name}").get("kind") != "capture":
                problems.append(f"demo.captures.{name}: scenes.{name} is not a capture scene (kind: capture)")
    if _has(params, "particles.floor_gap") and _has(params, "sim.bound") and _has(params, "sim.n_grid"):
        gap, bound, n_grid = (section(params, k) for k in ("particles.floor_gap", "sim.bound", "sim.n_grid"))
        if section(params, "particles.placement") == "floor" and float(gap) <= float(bound) / float(n_grid):
            problems.append(f"particles.floor_gap={gap} must lie above the floor's wall zone, "
                            f"sim.bound / sim.n_grid = {float(bound) / float(n_grid):.4g} m")
    if problems:
        raise ConfigError("params: " + "; ".join(problems))



def load_section(dotted: str, path="params.yaml", profile: str | None = None) -> Any:
    """The typed config of ``dotted`` read from the params file ``path`` (benchmarks and tools outside
    the stages: they measure the pipeline's setup, not a dataclass's defaults)."""
    raw = read_yaml(path)
    profile = profile or raw.get("profile", "paper")
    params = {**resolve(raw, profile), "profile": profile}
    return build_section(params, dotted)


def _cameras(items, where: str) -> tuple[OrbitCamera, ...]:
    return tuple(build(OrbitCamera, c, f"{where}[{i}]", partial=True) for i, c in enumerate(items or ()))


def scene_config(raw: Mapping, where: str) -> SceneConfig:
    """Build a :class:`SceneConfig` from one ``scenes.<name>`` mapping (``where`` names it in errors)."""
    raw = dict(raw)
    raw["camera"] = build(OrbitCamera, raw.get("camera", {}), f"{where}.camera", partial=True)
    raw["extra_train_cameras"] = _cameras(raw.get("extra_train_cameras"), f"{where}.extra_train_cameras")
    raw["eval_cameras"] = _cameras(raw.get("eval_cameras"), f"{where}.eval_cameras")
    # a capture scene (scenes.<name>.capture) is a user's record: launch and lighting keys are the synthetic
    # scenes' (required there), the video and camera come from the capture
    return build(SceneConfig, raw, where, partial="capture" in raw)


def load(stage: str | None = None, path="params.yaml", via_dvc: bool | None = None) -> dict:
    """:func:`gca.config.load` with :func:`validate` at load: the resolved params of ``stage``, checked."""
    return load_params(stage, path, via_dvc, check=validate)


def video_section(raw: Mapping) -> dict:
    """The ``video`` section with the chosen ``video.timing`` variant of ``video.timings`` merged in."""
    raw = dict(raw)
    timings = raw.pop("timings", None) or {}
    timing = raw.get("timing", "")
    if timing:
        if timing not in timings:
            raise ConfigError(f"params: video.timing {timing!r} is not one of video.timings {sorted(timings)}")
        raw.update(timings[timing])
    if "background" in raw:
        raw["background"] = tuple(raw["background"])
    return raw
