"""GCA's alignment modules: RDGA (rank-based depth-geometric anchors) and CPR (constitutive prior regularizer)."""

from gca.align.cpr import CPR, CPRConfig
from gca.align.rdga import RDGAConfig, rdga_loss

__all__ = ["CPR", "CPRConfig", "RDGAConfig", "rdga_loss"]
