"""Fine registration: the 7-parameter similarity by least-squares matching to the lidar surface."""

from .lsm import FineResult, register_fine
from .solver import HelmertFit, solve_helmert

METHODS = ("auto", "lsm", "icp-point", "icp-plane", "planes", "none")  # auto: lsm

__all__ = ["METHODS", "FineResult", "HelmertFit", "register_fine", "solve_helmert"]
