"""torchslide: batched landslide run-out simulation, Bayesian active-learning calibration, diagnosis.

``torchslide.calibrate(log_posterior, bounds, ...)`` is the calibration entry point (see
:func:`torchslide.calibration.calibrate`); ``torchslide.simulate`` runs the solver. Both are loaded on
first use, so ``import torchslide`` stays light.
"""
__version__ = "0.1.0"

__all__ = ["calibrate", "simulate", "CalibrationResult", "Params", "__version__"]


def __getattr__(name):
    if name in ("calibrate", "CalibrationResult"):
        from . import calibration

        return getattr(calibration, name)
    if name == "simulate":
        from .solver import simulate

        return simulate
    if name == "Params":
        from .physics import Params

        return Params
    raise AttributeError(f"module 'torchslide' has no attribute {name!r}")
