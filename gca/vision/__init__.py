"""gca.vision: what a monocular method extracts from the GT video (depth, masks, matches).

Numpy in, numpy out (preprocessing runs once per scene and is cached by the preprocess stage);
the differentiable losses that consume these live in :mod:`gca.align`.
"""

from __future__ import annotations

import dataclasses

from gca.vision.depth import (DepthConfig, DepthError, DepthEstimator, SimulatedDepth, SimulatedDepthConfig,
                              TransformersDepth, TransformersDepthConfig, disparity_to_depth, estimate_depth,
                              make_depth_estimator)
from gca.vision.masks import MaskConfig, compute_masks, load_mask_files, mask_from_alpha, mask_from_background
from gca.vision.matching import (MatchConfig, detect_keypoints, match_cached, match_descriptors, match_features,
                                 match_flow, match_frame, match_precision, pack_keypoints, unpack_keypoints)


@dataclasses.dataclass(frozen=True)
class VisionConfig:
    """The ``vision`` params section: depth, masks and matching."""

    depth: DepthConfig = DepthConfig()
    masks: MaskConfig = MaskConfig()
    matching: MatchConfig = MatchConfig()


__all__ = ["VisionConfig", "DepthConfig", "DepthError", "DepthEstimator", "SimulatedDepth", "SimulatedDepthConfig",
           "TransformersDepth", "TransformersDepthConfig", "disparity_to_depth", "estimate_depth",
           "make_depth_estimator", "MaskConfig", "compute_masks", "load_mask_files", "mask_from_alpha",
           "mask_from_background", "MatchConfig", "detect_keypoints", "match_cached", "match_descriptors",
           "match_features", "match_flow", "match_frame", "match_precision", "pack_keypoints", "unpack_keypoints"]
