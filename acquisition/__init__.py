"""BoTorch acquisition functions for GP emulators of log-posteriors (log-normal entropy, exp-variance)
and batch selection (kriging believer)."""
from .functions import ExpVariance, LogNormalEntropy, make_acquisition, select_batch

__all__ = ["LogNormalEntropy", "ExpVariance", "make_acquisition", "select_batch"]
