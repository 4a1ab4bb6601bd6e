"""The pipeline's typed configuration: params -> typed configs, once per stage process.

A stage loads its resolved params (``gca.config.load``: under ``dvc repro`` only the sections its
``dvc.yaml`` entry declares), wraps them in :class:`Settings` once, and passes that to the pipeline
functions; each typed section is built on first use and kept, so a run never rebuilds one (the train stage
built ``TrainConfig`` three times per training run before). Below this layer the library takes the typed
values alone. A section the stage did not declare is a :class:`gca.config.ConfigError` naming the key.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Mapping

import torch

from gca.align.cpr import CPRConfig
from gca.align.rdga import RDGAConfig
from gca.config import ConfigError, build, entry, section
from gca.pipeline import schema
from gca.pipeline.schema import scene_config
from gca.eval.config import MetricsConfig
from gca.laws.lora import LoRAConfig
from gca.render.rasterize import RasterConfig
from gca.render.shading import LightingConfig
from gca.scenes.config import SceneConfig, VideoConfig
from gca.scenes.world import Body, load_body, resolve_backend
from gca.sim.solver import SimConfig
from gca.train.config import TrainConfig, VelocityConfig, check_seeds
from gca.vision import VisionConfig
from gca.vision.matching import MatchConfig


class Settings:
    """Typed views of one stage's resolved params, each built once on first use.

    Attributes:
        params: the resolved params mapping (for MLflow, which logs them as they are).
    """

    def __init__(self, params: Mapping):
        self.params = params
        self._scenes: dict[str, SceneConfig] = {}

    @classmethod
    def load(cls, stage: str, path="params.yaml") -> "Settings":
        """The settings of DVC stage ``stage`` (:func:`gca.config.load`: only its declared params under dvc),
        validated at load (:func:`gca.pipeline.schema.validate`)."""
        return cls(schema.load(stage, path))

    def section_as(self, cls, dotted: str):
        """The dataclass ``cls`` built from params section ``dotted`` (for a section one stage reads once)."""
        return build(cls, section(self.params, dotted), dotted)

    @functools.cached_property
    def profile(self) -> str:
        return str(section(self.params, "profile"))

    @functools.cached_property
    def seed(self) -> int:
        """The global seed (data and priors; training runs take theirs from ``train.seeds``)."""
        return int(section(self.params, "seed"))

    @functools.cached_property
    def sim(self) -> SimConfig:
        return self.section_as(SimConfig, "sim")

    @functools.cached_property
    def video(self) -> VideoConfig:
        """The ``video`` section, with the chosen ``video.timing`` variant of ``video.timings`` merged in (a
        scene's own timing: :func:`gca.scenes.config.scene_video`)."""
        return build(VideoConfig, schema.video_section(section(self.params, "video")), "video")

    @functools.cached_property
    def benchmark_version(self) -> str:
        """``benchmark.version`` (docs/benchmark.md): the frozen conditions the scenes were made under."""
        return str(section(self.params, "benchmark.version"))

    @functools.cached_property
    def lighting(self) -> LightingConfig:
        return self.section_as(LightingConfig, "render.lighting")

    @functools.cached_property
    def raster(self) -> RasterConfig:
        return self.section_as(RasterConfig, "render.raster")

    @functools.cached_property
    def backend(self) -> str:
        """``render.backend`` as written (auto | torch | gsplat); :meth:`load_body` resolves it per device."""
        return str(section(self.params, "render.backend"))

    @functools.cached_property
    def train(self) -> TrainConfig:
        """``train`` for the first of ``train.seeds``; :meth:`train_for` gives another seed's."""
        return self.section_as(TrainConfig, "train")

    @functools.cached_property
    def seeds(self) -> tuple[int, ...]:
        """``train.seeds`` alone (the ground_truth and preprocess stages declare only this key of ``train``: each
        seed draws its own nuisances, :func:`gca.scenes.store.seed_dir`)."""
        try:
            return check_seeds(section(self.params, "train.seeds"))
        except ValueError as exc:
            raise ConfigError(str(exc)) from None

    def train_for(self, seed: int | None = None) -> TrainConfig:
        """``train`` for the run of ``seed`` (one of ``train.seeds``; None: the first)."""
        return self.train if seed is None else dataclasses.replace(self.train, seed=seed)

    @functools.cached_property
    def velocity(self) -> VelocityConfig:
        return self.section_as(VelocityConfig, "velocity")

    @functools.cached_property
    def rdga(self) -> RDGAConfig:
        return self.section_as(RDGAConfig, "align.rdga")

    @functools.cached_property
    def cpr(self) -> CPRConfig:
        return self.section_as(CPRConfig, "align.cpr")

    @functools.cached_property
    def lora(self) -> LoRAConfig:
        return self.section_as(LoRAConfig, "laws.lora")

    @functools.cached_property
    def match(self) -> MatchConfig:
        return self.section_as(MatchConfig, "vision.matching")

    @functools.cached_property
    def vision(self) -> VisionConfig:
        return self.section_as(VisionConfig, "vision")

    @functools.cached_property
    def metrics(self) -> MetricsConfig:
        return self.section_as(MetricsConfig, "eval.metrics")

    @functools.cached_property
    def prior_families(self) -> dict[str, dict]:
        """``prior.families``: family name -> its analytic preset (E, nu, ...)."""
        return {k: dict(v) for k, v in section(self.params, "prior.families").items()}

    def material(self, name: str) -> dict:
        """The preset of ``materials.<name>`` (a ground-truth law: evaluation and ground truth; training reads only
        its category, which the PAC-NeRF-style explicit rows are told: ``gca.pipeline.train.law_for``)."""
        return dict(section(self.params, f"materials.{name}"))

    def scene(self, name: str) -> SceneConfig:
        """The :class:`SceneConfig` of ``scenes.<name>`` (built once per name)."""
        if name not in self._scenes:
            self._scenes[name] = scene_config(entry(self.params, "scenes", name), f"scenes.{name}")
        return self._scenes[name]

    def load_body(self, particles_path, gaussians_path, device: str | torch.device = "cpu") -> Body:
        """:func:`gca.scenes.world.load_body` with ``render.backend`` resolved for ``device`` and ``render.raster``."""
        return load_body(particles_path, gaussians_path, device, backend=resolve_backend(self.backend, device),
                         raster=self.raster)

