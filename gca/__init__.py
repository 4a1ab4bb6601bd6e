"""GCA: learning implicit constitutive laws for dynamic 3D Gaussian splatting from monocular video.

Sub-packages (see docs/architecture.md): assets, sim, laws, render, vision, align, train, eval, report.
"""

from gca.gpu_slot import pin_from_env as _pin_from_env

__version__ = "0.1.0"

_pin_from_env()  # GCA_GPU_PER_PROCESS=1: one GPU per stage process (DVC queue workers), before CUDA starts
