"""The prior stage's glue: the family preset and the typed configs of NCLaw-style pretraining from params."""

from __future__ import annotations

from gca.config import ConfigError
from gca.laws.neural import NeuralLawConfig
from gca.pipeline import schema
from gca.pipeline.settings import Settings
from gca.train.prior import PriorTrainConfig


def prior_configs(settings: Settings, family: str) -> tuple[dict, NeuralLawConfig, PriorTrainConfig]:
    """(family preset, network config, stage config) from params ``prior.*`` and ``laws.neural``."""
    families = settings.prior_families
    if family not in families:
        raise ConfigError(f"params: prior.families has no family {family!r}; have {sorted(families)}")
    # prior.train.sim lists only its overrides of sim (gca.pipeline.schema.prior_sim)
    return (families[family], settings.section_as(NeuralLawConfig, "laws.neural"),
            schema.build_section(settings.params, "prior.train"))
