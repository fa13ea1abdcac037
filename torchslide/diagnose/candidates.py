"""The library of candidate missing-physics terms of the diagnosis.

Each candidate is a term of the solver's model (torchslide.physics.Params) with a switch parameter
whose value ``baseline`` (0) gives plain Voellmy bitwise: the candidate models are nested in the
baseline. ``prior`` is the switch's calibration range, ``signature`` what the term leaves in the
recordings, ``fixed`` the other parameters the term needs (e.g. phi_int for the Savage-Hutter earth
pressure). ``release_volume`` is not physics but the explanation a modeller checks first: a release that
holds more than stated (Params.release_scale), which a term that adds mass (entrainment) could be
mistaken for.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Candidate:
    """A candidate missing-physics term: its switch parameter and calibration prior box."""

    name: str
    param: str
    baseline: float
    prior: tuple[float, float]
    signature: str
    fixed: tuple[tuple[str, float], ...] = ()
    open_range: bool = False    # the prior's upper end is a budget, not a limit of the term (every rate or
                                # stress here; not the 0-1 switches, whose 1 is the physical term): a fit
                                # there (the data want more than the range allows) is not named
                                # (decide: within_range, set aside)


CANDIDATES: dict[str, Candidate] = {
    "entrainment": Candidate(
        "entrainment", "kappa", 0.0, (0.0, 0.02),
        "volume grows along the path; deposits larger and further out than released volume allows", open_range=True),
    "curvature": Candidate(
        "curvature", "curvature", 0.0, (0.0, 1.0),
        "extra friction in hollows / bends (centrifugal normal stress): slower in curved channels, faster on convex crests"),
    "earth_pressure": Candidate(
        "earth_pressure", "earth_pressure", 0.0, (0.0, 1.0),
        "Savage-Hutter active/passive k (phi_int 35 deg): faster spreading of the front, steeper piling at the stop",
        fixed=(("phi_int", 35.0),)),
    "yield_stress": Candidate(
        "yield_stress", "tau_y", 0.0, (0.0, 20.0),  # m^2/s^2 (stress / density): up to ~40 kPa at 2000 kg/m^3
        "thin flows stop early: thick lobate deposits with steep margins, shorter run-out of the tail",
        open_range=True),
    "mu_i": Candidate(
        "mu_i", "mu_i", 0.0, (0.0, 0.4),
        "rate-dependent friction: fast thin fronts brake more, slow parts less (velocity-depth dependent)",
        open_range=True),
    "release_volume": Candidate(
        "release_volume", "release_scale", 0.0, (0.0, 0.5),
        "more mass than the stated release (up to +50 %), from the start: larger depths, deposit and volumes "
        "everywhere, no growth along the path (an input error, not a missing term)", open_range=True),
    "deposition": Candidate(
        "deposition", "deposition", 0.0, (0.0, 0.5),
        "mass left behind along the path where the flow slows: trail deposit, reduced front volume", open_range=True),
}
"""Candidate terms of the diagnosis: each ``param`` at ``baseline`` (0) gives plain Voellmy."""
