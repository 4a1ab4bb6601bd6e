"""Knobs of the evaluation metrics (params ``eval.metrics``)."""

from __future__ import annotations

import dataclasses

from gca.eval.law_response import SWEEPS


@dataclasses.dataclass(frozen=True)
class MetricsConfig:
    """How the evaluate stage computes its metrics (definitions live in the metric modules)."""

    chamfer_squared: bool = False  # False: mean NN Euclidean distance [m]; True: squared [m^2]
    ssim_window: int = 11  # Gaussian SSIM window side [px] (Wang et al. 2004)
    lpips_net: str = "vgg"  # LPIPS backbone (NeuMA evaluation: vgg); skipped with a reason if absent
    image_max_val: float = 1.0  # peak value of rendered/GT images (PSNR/SSIM data range)
    response_points: int = 41  # samples per held-out F sweep of the law response error [count]
    response_sweeps: tuple[str, ...] = ("uniaxial", "shear")  # sweeps reported (see law_response.SWEEPS)

    def __post_init__(self):
        object.__setattr__(self, "response_sweeps", tuple(self.response_sweeps))
        bad = [s for s in self.response_sweeps if s not in SWEEPS]
        if bad or self.ssim_window < 3 or self.ssim_window % 2 == 0 or self.response_points < 2:
            raise ValueError(f"gca/eval/config.py: MetricsConfig needs sweeps in {list(SWEEPS)}, an odd "
                             f"ssim_window >= 3 and response_points >= 2; got {self}")
