"""The Triton step (torchslide.solver.fused_triton) against the torch step, run by Triton's interpreter on
the CPU: ``TRITON_INTERPRET=1 python -m tests.triton_interpret CASE``, one case of CASES per process (the
interpreter is chosen when triton is imported). tests/test_solver_triton.py runs each case; the cases are
short runs (a few steps: the interpreter takes about a second per step) that switch on every term."""
from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np
import torch

from torchslide.solver import SolverConfig as _Config
from torchslide.terrain.grid import DEM

from .conftest import cap_release, tilted_plane
from .test_solver_fused import _channel, _compare, compare_plane_settings


def SolverConfig(**kw) -> _Config:
    """The run's settings, the host checking every 4 steps (a step call costs the interpreter about a second
    even where every member has ended)."""
    return _Config(check_every=4, **kw)


def terms():
    """Every friction- and pressure-side term on in one member, off in the other (switch 0)."""
    dem, rel, gauges = _channel()
    params = {"mu": [0.2, 0.25], "xi": 800.0, "tau_y": [2.0, 0.0], "earth_pressure": [1.0, 0.0], "phi_int": 35.0,
              "curvature": [1.0, 0.0], "mu_i": [0.3, 0.0]}
    _compare(dem, rel, params, SolverConfig(), gauges, t_end=4.0)


def moving_bed():
    """Entrainment and deposition: the bed and its metric change every stage."""
    dem, rel, gauges = _channel()
    erod = np.full(dem.shape, 0.5)
    params = {"mu": [0.2, 0.25], "xi": 800.0, "kappa": [0.004, 0.0], "deposition": [0.3, 0.0]}
    ref = _compare(dem, rel, params, SolverConfig(), gauges, t_end=4.0, erodible_depth=erod)
    assert float(ref.entrained_volume[0]) > 0


def nodata():
    """Cells outside the DEM's domain, both rules (the walls' switch)."""
    dem, rel, gauges = _channel()
    outside = np.zeros(dem.shape, dtype=bool)
    outside[:, 10:12] = True                 # a band of nodata across the path, beside the release
    outside[:8, 4:10] = True
    dem = DEM(dem.z, dem.cellsize, outside=outside)
    lost = {rule: _compare(dem, rel, {"mu": [0.15, 0.25], "xi": 1500.0}, SolverConfig(nodata=rule),
                           t_end=4.0).outflow_volume for rule in ("outflow", "wall")}
    assert float(lost["outflow"].min()) > 0 and float(lost["wall"].max()) == 0    # the flow reached the band


def plane():
    """A plane dipping 30 degrees off the grid axes: an open boundary, no slope metric and no no-creep
    rule, a friction map, no turbulent friction (xi = inf) with k_ap 1.5."""
    dem = tilted_plane(12, 20.0, 35.0, plan_deg=30.0)[0]
    rel = cap_release(dem, -20.0, -10.0, 50.0, 4.0)
    compare_plane_settings(dem, rel, t_end=1.5, config=SolverConfig)
    _compare(dem, rel, {"mu": 0.3, "xi": float("inf"), "k_ap": 1.5}, SolverConfig(), t_end=1.5)


def float32():
    dem, rel, gauges = _channel()
    _compare(dem, rel, {"mu": [0.2, 0.3], "xi": [500.0, 2000.0]}, SolverConfig(), gauges, t_end=4.0,
             dtype=torch.float32, rtol=1e-5)


def flushed_float32():
    """float32 on the fast paths with subnormals flushed to zero in division and sqrt, as the card does
    (run with TORCHSLIDE_FLUSH_SUBNORMALS=1): the Bondo-like run stays finite and within 1e-3 of the torch
    step (a guard that let a subnormal divisor through gave NaN in the second step on an H200)."""
    from torchslide.physics import Params
    from torchslide.solver import fused_triton, simulate
    from torchslide.terrain.synthetic import bondo_like

    assert fused_triton.FAST_FLOAT32 and fused_triton.FLUSH_SUBNORMALS
    c = bondo_like(80.0)
    p = Params.make(mu=[0.15, 0.23], xi=[500.0, 1000.0], dtype=torch.float32)
    runs = [simulate(c.dem, c.release, p, t_end=4.0, dtype=torch.float32, config=SolverConfig(kernel=k))
            for k in ("fused", "eager")]
    assert runs[0].kernel == "fused-triton" and not bool(runs[0].failed.any()), runs[0].failure_reason
    for f in ("h_max", "v_max", "h_final"):
        a, b = (getattr(r, f).double() for r in runs)
        assert float((a - b).norm() / b.norm()) < 1e-3, f


def _exact_sqrt() -> None:
    """torch.sqrt rounded exactly in float64 on the CPU, as it is on CUDA (torch's vectorised CPU sqrt is
    not correctly rounded; Triton's interpreter rounds exactly)."""
    sqrt = torch.sqrt

    def exact(x, *args, **kw):
        if x.device.type == "cpu" and x.dtype == torch.float64 and not args and not kw:
            return torch.from_numpy(np.sqrt(x.detach().numpy()))
        return sqrt(x, *args, **kw)

    torch.sqrt = exact


def bitwise():
    """One step from a state of the all-terms chute run 5 steps in, with every term and with plain Voellmy
    without the slope metric, on both designs of the faces (fused_triton.FACES; the marching kernel on strips
    and bands that split the 24 x 60 grid along both axes): every field of the Triton step equals the torch
    step's to the last bit, with both rounding sqrt exactly (as on CUDA). Only the per-member sums (kinetic
    energy, mass, boundary outflow) may differ, by their order of summation."""
    from torchslide.solver import fused_triton, stepping

    from .conftest import assert_steps_equal, step_state

    _exact_sqrt()
    S, P, F = step_state(5)
    assert F.use_ep and F.use_curv and F.use_ent and F.use_dep and F.use_mu_i and F.no_creep
    plain = dataclasses.replace(F, use_ep=False, use_curv=False, use_ent=False, use_dep=False, use_mu_i=False,
                                slope_correction=False)
    # strips and bands that split the 24 x 60 grid along both axes, for the faces and for the update
    fused_triton.INTERPRETED_MARCH, fused_triton.INTERPRETED_UPDATE = (64, 16), (32, 16)
    assert S["h"].shape[1:] == (24, 60)
    two = _members(S, P, [0, 1])     # plain Voellmy compiles the terms out: two members test it
    for fused_triton.FACES, cases in (("march", ((F, (S, P)), (plain, two))), ("lines", ((F, (S, P)),))):
        for flags, (S_, P_) in cases:
            assert_steps_equal(stepping.make_step(flags)(dict(S_), P_), fused_triton.triton_step(flags)(dict(S_), P_))


def _members(S: dict, P: dict, idx: list) -> tuple[dict, dict]:
    """The state and parameters of the members ``idx`` alone (every per-member tensor indexed along its first
    axis; what all members share kept)."""
    import torch

    B = S["h"].shape[0]
    pick = lambda d: {k: v[idx] if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == B else v for k, v in d.items()}
    return pick(S), pick(P)


CASES = {f.__name__: f for f in (terms, moving_bed, nodata, plane, float32, bitwise)}
"""The cases against the torch step (tests/test_solver_triton.py); flushed_float32 runs with its own setting.
Plain Voellmy runs in float64 on the plane (plane), in float32 on the channel (float32) and to the last bit for one
step of the channel (bitwise). The whole runs take the default design of the faces (fused_triton.FACES), bitwise
both."""

SETTINGS = {"flushed_float32": {"TORCHSLIDE_FLUSH_SUBNORMALS": "1"}}
"""Environment of the cases that need one (read when torchslide.solver.fused_triton is imported)."""


def _patch_language_once() -> None:
    """Triton's interpreter patches triton.language again at every call of a @triton.jit function inside a
    kernel (most of an interpreted step's time). The patches of a launch stay until it ends, so a call whose
    language modules (triton.language, triton.language.core, as its globals name them) the launch has patched
    already skips it (the same patched functions either way). Where the interpreter's internals differ, it is
    left as it is."""
    import inspect

    import triton.language as tl
    from triton.runtime import interpreter

    if not (callable(getattr(interpreter, "_patch_lang", None)) and hasattr(interpreter, "GridExecutor")):
        return
    patch_lang, launch = interpreter._patch_lang, interpreter.GridExecutor.__call__
    state = {"launch": False, "patched": set()}
    langs_of: dict = {}     # id of a function's globals -> the ids of the language modules it names

    def patch_once(fn):
        key = id(fn.__globals__)
        if key not in langs_of:
            langs_of[key] = {id(v) for v in fn.__globals__.values() if inspect.ismodule(v) and v in (tl, tl.core)}
        if state["launch"] and langs_of[key] <= state["patched"]:
            return None                            # a call within the launch: the scope is not used
        scope = patch_lang(fn)
        if state["launch"]:
            state["patched"] |= langs_of[key]
        return scope

    def run(self, *args, **kwargs):
        state.update(launch=True, patched=set())
        try:
            return launch(self, *args, **kwargs)
        finally:
            state.update(launch=False, patched=set())

    interpreter._patch_lang, interpreter.GridExecutor.__call__ = patch_once, run


def main(name: str) -> None:
    if os.environ.get("TRITON_INTERPRET") != "1":
        raise SystemExit("run with TRITON_INTERPRET=1")
    from torchslide.solver import fused_triton

    _patch_language_once()

    calls = []
    make = fused_triton.triton_step
    fused_triton.triton_step = lambda F: calls.append(F) or make(F)
    {**CASES, "flushed_float32": flushed_float32}[name]()
    if not calls:
        raise SystemExit(f"{name}: the Triton step was not used")
    print(f"{name}: the Triton step equals the torch step ({len(calls)} configurations)")


if __name__ == "__main__":
    main(sys.argv[1])
