"""The shipped params.yaml sections for vision and align.rdga build into their dataclasses (both profiles)."""

from pathlib import Path

import pytest

from gca.align.rdga import RDGAConfig
from gca.config import ConfigError, build, read_yaml, resolve, section
from gca.vision import VisionConfig

PARAMS = Path(__file__).resolve().parents[1] / "params.yaml"


@pytest.mark.parametrize("profile", ["paper", "ci"])
def test_shipped_sections_validate(profile):
    tree = resolve(read_yaml(PARAMS), profile)
    vision = build(VisionConfig, section(tree, "vision"), "vision")
    rdga = build(RDGAConfig, section(tree, "align.rdga"), "align.rdga")
    assert vision.depth.backend in ("simulated", "transformers") and rdga.k <= rdga.r


def test_unknown_key_is_refused():
    with pytest.raises(ConfigError, match="unknown keys"):
        build(RDGAConfig, {"kappa": 3})
