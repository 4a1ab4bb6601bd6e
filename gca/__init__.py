"""GCA: learning implicit constitutive laws for dynamic 3D Gaussian splatting from monocular video.

Sub-packages (see docs/architecture.md): assets, sim, laws, render, vision, align, train, eval, report.
"""

__version__ = "0.1.0"
