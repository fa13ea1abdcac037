"""torchslide: batched landslide run-out simulation, Bayesian active-learning calibration, diagnosis."""
__version__ = "0.1.0"
