"""The prior stage's glue: the family preset and the typed configs of NCLaw-style pretraining from params."""

from __future__ import annotations

from typing import Mapping

from gca.config import ConfigError, build, section
from gca.laws.neural import NeuralLawConfig
from gca.train.prior import PriorTrainConfig


def prior_configs(params: Mapping, family: str) -> tuple[dict, NeuralLawConfig, PriorTrainConfig]:
    """(family preset, network config, stage config) from resolved params (``prior.*``, ``laws.neural``)."""
    families = section(params, "prior.families")
    if family not in families:
        raise ConfigError(f"params: prior.families has no family {family!r}; have {sorted(families)}")
    law_cfg = build(NeuralLawConfig, section(params, "laws.neural"), "laws.neural")
    return dict(families[family]), law_cfg, build(PriorTrainConfig, section(params, "prior.train"), "prior.train")
