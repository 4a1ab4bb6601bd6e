"""gca.eval: evaluation metrics (geometry, images, law responses, efficiency). No I/O, no stage logic."""

from gca.eval.config import MetricsConfig
from gca.efficiency import Usage, count_parameters, measure
from gca.eval.geometry import (CHAMFER_DEFINITION, CHAMFER_DEFINITION_SQUARED, chamfer,
                               chamfer_over_time, nearest_distance)
from gca.eval.image import SSIM_WINDOW, lpips_or_reason, lpips_unavailable_reason, psnr, ssim
from gca.eval.law_response import (SWEEPS, deformation_sweep, law_response_curve,
                                   law_response_error)

__all__ = [
    "CHAMFER_DEFINITION", "CHAMFER_DEFINITION_SQUARED", "MetricsConfig", "SSIM_WINDOW", "SWEEPS", "Usage",
    "chamfer", "chamfer_over_time", "count_parameters", "deformation_sweep", "law_response_curve",
    "law_response_error", "lpips_or_reason", "lpips_unavailable_reason", "measure",
    "nearest_distance", "psnr", "ssim",
]
