"""The Bondo-like synthetic case study of the paper (Table 1, Table 2 cases 1-10, Fig. 3-6 analogues).

Run ``python -m experiments.bondo [--case N] [--quick]``; results page: experiments/bondo/README.md.
"""
from .config import CASES, DATA, OBSERVABLES, BondoConfig

__all__ = ["BondoConfig", "CASES", "DATA", "OBSERVABLES"]
