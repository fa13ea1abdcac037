"""On a CUDA device the solver, a calibration and a diagnosis give what they give on the CPU.

Skipped where torch sees no CUDA device (CI has none). On a GPU machine: ``make test-gpu`` (or
``pytest tests/test_gpu.py``). ``TORCHSLIDE_TEST_DEVICE`` picks another device ("cuda:1"; "cpu" checks
the tests themselves on a machine without a GPU). Relative differences are ||a - b|| / ||b|| over
whole rasters.
"""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate

from .conftest import TERMS_T_END as T_END, all_terms_case as _all_terms

DEVICE = os.environ.get("TORCHSLIDE_TEST_DEVICE", "cuda")
ON_CUDA = DEVICE.startswith("cuda")
pytestmark = pytest.mark.skipif(ON_CUDA and not torch.cuda.is_available(), reason="no CUDA device")


def _reset_memory() -> None:
    if ON_CUDA:
        torch.cuda.reset_peak_memory_stats(DEVICE)


def _used_the_gpu() -> bool:
    """True when the device's allocator served memory since _reset_memory (always True on the CPU)."""
    return torch.cuda.max_memory_allocated(DEVICE) > 0 if ON_CUDA else True


CFG = SolverConfig(output_interval=5.0)


def _rel(a, b) -> float:
    a, b = torch.as_tensor(a).double().cpu(), torch.as_tensor(b).double().cpu()
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


def _fields(r):
    out = {"h_max": r.h_max, "v_max": r.v_max, "h_final": r.h_final, "final_volume": r.final_volume,
           "bed_change": r.bed_change, "gauge_h": r.gauges["G"].h,
           "arrival_time": torch.where(torch.isfinite(r.arrival_time), r.arrival_time, torch.zeros_like(r.arrival_time))}
    return out


@pytest.fixture(scope="module")
def cpu_run():
    dem, rel, p, kw = _all_terms()
    return simulate(dem, rel, p, t_end=T_END, config=CFG, **kw)


def test_solver_float64_on_cuda_matches_the_cpu(cpu_run):
    dem, rel, p, kw = _all_terms()
    _reset_memory()
    r = simulate(dem, rel, p, t_end=T_END, config=CFG, device=DEVICE, **kw)
    assert _used_the_gpu()
    assert not bool(r.failed.any())
    for name, ref in _fields(cpu_run).items():
        assert _rel(_fields(r)[name], ref) < 1e-6, name
    assert (r.steps.cpu() - cpu_run.steps).abs().max() <= 1
    # every term changed its member on the GPU as on the CPU (the switch is applied there too)
    for b in range(1, p.B):
        assert not torch.equal(r.h_final[b].cpu(), r.h_final[0].cpu()), b


def test_solver_float32_on_cuda_is_close_and_keeps_the_mass(cpu_run):
    dem, rel, p, kw = _all_terms()
    r = simulate(dem, rel, p, t_end=T_END, config=CFG, device=DEVICE, dtype=torch.float32, **kw)
    assert r.h_max.dtype == torch.float32 and not bool(r.failed.any())
    f32, f64 = _fields(r), _fields(cpu_run)
    for name in ("h_max", "h_final", "final_volume"):
        assert _rel(f32[name], f64[name]) < 0.02, name
    bal = (r.final_volume.double() + r.outflow_volume.double() - r.release_volume.double()
           - r.entrained_volume.double()).cpu() / r.release_volume.double().cpu()
    assert float(bal.abs().max()) < 1e-4


def test_compiled_solver_on_cuda_matches_eager(cpu_run):
    dem, rel, p, kw = _all_terms()
    cfg = SolverConfig(output_interval=5.0, compile=True)
    r = simulate(dem, rel, p, t_end=T_END, config=cfg, device=DEVICE, **kw)
    for name, ref in _fields(cpu_run).items():
        assert _rel(_fields(r)[name], ref) < 1e-6, name


def _max_rel(a, b) -> float:
    """max |a - b| over max |b| on the finite entries (both finite in the same places)."""
    a, b = torch.as_tensor(a).double().cpu(), torch.as_tensor(b).double().cpu()
    fin = torch.isfinite(b)
    assert torch.equal(fin, torch.isfinite(a))
    return float((a[fin] - b[fin]).abs().max() / b[fin].abs().max().clamp_min(1e-300)) if fin.any() else 0.0


OBSERVABLES = ("peak h_max", "peak v_max", "mean arrival", "deposit", "final volume", "outflow volume")


def _observables(r) -> torch.Tensor:
    """(B, 6) whole-run observables in float64: peak h_max, peak v_max, mean arrival over the reached cells,
    deposit volume (sum of h_final), final and outflow volumes."""
    a = r.arrival_time.double()
    fin = torch.isfinite(a)
    arrival = torch.where(fin, a, torch.zeros_like(a)).sum(dim=(1, 2)) / fin.sum(dim=(1, 2)).clamp_min(1)
    return torch.stack([r.h_max.double().amax(dim=(1, 2)), r.v_max.double().amax(dim=(1, 2)), arrival,
                        r.h_final.double().sum(dim=(1, 2)), r.final_volume.double(), r.outflow_volume.double()], 1)


@pytest.mark.parametrize("case", ["all_terms", "bondo_like"])
def test_float32_on_the_fast_paths_is_judged_by_physics(case):
    """The Triton step in float32 (approximate division and sqrt, fused multiply-add: fused_triton.FAST_FLOAT32)
    against float64: whole-run observables within 1e-3 relative, or within the spread float64 itself shows
    when the release changes by one ulp, whichever is larger (an outflow volume within a millionth of the
    final volume: float64 gives 1e-29 m^3 where nothing leaves)."""
    from torchslide.terrain.synthetic import bondo_like

    if not ON_CUDA:
        pytest.skip("the Triton step runs on CUDA")
    if case == "all_terms":
        dem, rel, p, kw = _all_terms()
        t_end, cfg = T_END, SolverConfig(output_interval=5.0)
    else:
        c = bondo_like(20.0)
        dem, rel, kw = c.dem, c.release, {}
        p = Params.make(mu=[0.18, 0.23, 0.3], xi=[600.0, 1000.0, 2000.0])
        t_end, cfg = 120.0, SolverConfig()

    def run(dtype, release):
        return _observables(simulate(dem, release, p.to(dtype=dtype), t_end=t_end, config=cfg, device=DEVICE,
                                     dtype=dtype, **kw))

    o64 = run(torch.float64, rel)
    bumped = np.nextafter(np.asarray(rel, dtype=np.float64), np.inf)
    spread = (run(torch.float64, np.where(np.asarray(rel) > 0, bumped, rel)) - o64).abs()
    o32 = run(torch.float32, rel)
    tol = torch.maximum(1e-3 * o64.abs(), spread)
    tol[:, 5] = torch.maximum(tol[:, 5], 1e-6 * o64[:, 4])     # an outflow of 1e-29 m^3 is no outflow
    bad = ((o32 - o64).abs() > tol).nonzero().tolist()
    assert not bad, [(m, OBSERVABLES[j], float(o64[m, j]), float(o32[m, j]), float(tol[m, j])) for m, j in bad]


def test_verification_cases_pass_in_float32_on_the_fast_paths():
    """Cases 4, 5 and 7 of docs/verification.md in float32 on the Triton step, at their own tolerances."""
    from .test_solver_reference import _energy_line, _mangeney, _similarity_run

    kw = {"device": DEVICE, "dtype": torch.float32}
    for theta, delta in [(22.0, 21.0), (40.0, 30.0)]:
        e1, fn1, fr1, r1 = _mangeney(1.0, theta=theta, delta=delta, **kw)
        assert e1 < 0.03 and abs(fn1 - fr1) <= 5 * 1.0
        assert abs(float(r1.final_volume[0] + r1.outflow_volume[0] - r1.release_volume[0])) \
            < 1e-5 * float(r1.release_volume[0])
    e5, c5, ref, a5 = _similarity_run(5.0, 0.0, **kw)
    assert e5 < 0.03 and abs(c5 - ref) < 0.2 * 5.0 and abs(a5[0.1] - 1) < 0.03
    com, x_line, x0, r = _energy_line(**kw)
    assert bool(r.stopped[0]) and not bool(r.failed[0])
    assert x_line - 0.1 * (x_line - x0) < com < x_line


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-12)])
def test_triton_step_on_cuda_equals_eager(dtype, rtol):
    """The fused kernel on CUDA (the Triton step) against the torch step on the same device, every term on."""
    from torchslide.solver import fused_triton

    if not ON_CUDA:
        pytest.skip("the Triton step runs on CUDA")
    assert fused_triton.supported(None, DEVICE) is None
    dem, rel, p, kw = _all_terms()
    p = p.to(dtype=dtype)
    runs = [simulate(dem, rel, p, t_end=T_END, config=SolverConfig(output_interval=5.0, kernel=k), device=DEVICE,
                     dtype=dtype, **kw) for k in ("eager", "fused")]
    assert torch.equal(runs[0].steps, runs[1].steps) and not bool(runs[1].failed.any())
    for name, ref in _fields(runs[0]).items():
        assert _max_rel(_fields(runs[1])[name], ref) <= rtol, name


@pytest.mark.parametrize("faces", ["march", "lines"])
@pytest.mark.parametrize("dtype", [torch.float64])
def test_one_triton_step_on_cuda_is_the_torch_step_to_the_last_bit(dtype, faces, monkeypatch):
    """One step of every term from a state 5 steps into the all-terms chute run: in float64 the same
    arithmetic (IEEE division and sqrt, no fused multiply-add) gives the same bits, on either design of the
    faces (float32 takes the fast paths: test_float32_on_the_fast_paths_is_judged_by_physics)."""
    from torchslide.solver import fused_triton, stepping

    from .conftest import assert_steps_equal, step_state

    if not ON_CUDA:
        pytest.skip("the Triton step runs on CUDA")
    monkeypatch.setattr(fused_triton, "FACES", faces)
    S, P, F = step_state(5, DEVICE, dtype)
    assert_steps_equal(stepping.make_step(F)(dict(S), P), fused_triton.triton_step(F)(dict(S), P))


@pytest.mark.parametrize("kernel,crop", [("fused", True), ("fused", False), ("eager", True)])
def test_cuda_graphs_replay_the_same_steps(kernel, crop, monkeypatch):
    """Steps replayed as CUDA graphs give the same bits as steps launched one by one, cropped or not."""
    from torchslide.solver import graphs

    if not ON_CUDA:
        pytest.skip("CUDA graphs")
    recorded = []
    record = graphs.StepGraphs._record
    monkeypatch.setattr(graphs.StepGraphs, "_record", lambda self, S, n: recorded.append(n) or record(self, S, n))
    dem, rel, p, kw = _all_terms()
    runs = [simulate(dem, rel, p, t_end=T_END, device=DEVICE, **kw,
                     config=SolverConfig(output_interval=5.0, kernel=kernel, crop=crop, cuda_graphs=on))
            for on in (False, True)]
    assert recorded and torch.equal(runs[0].steps, runs[1].steps)
    for name, ref in _fields(runs[0]).items():
        assert torch.equal(_fields(runs[1])[name], ref), name


def test_triton_step_on_cuda_equals_eager_on_the_bondo_like_run():
    """The 20 m Bondo-like valley (bench.bench_solver's case), cropped as a calibration runs it."""
    from torchslide.terrain.synthetic import bondo_like

    if not ON_CUDA:
        pytest.skip("the Triton step runs on CUDA")
    case = bondo_like(20.0)
    p = Params.make(mu=[0.18, 0.23, 0.3], xi=[600.0, 1000.0, 2000.0])
    runs = [simulate(case.dem, case.release, p, t_end=120.0, config=SolverConfig(kernel=k), device=DEVICE)
            for k in ("eager", "fused")]
    assert torch.equal(runs[0].steps, runs[1].steps)
    for name in ("h_max", "v_max", "h_final", "final_volume", "outflow_volume"):
        assert _max_rel(getattr(runs[1], name), getattr(runs[0], name)) <= 1e-12, name


# ------------------------------------------------------------------ calibration and diagnosis on the GPU
def _calibration_config(tmp_path, device: str):
    from .conftest import CALIBRATE_BASE as CBASE, CALIBRATE_CAL as CAL, CALIBRATE_OBS as OBS, CALIBRATE_PRIOR as PRIOR, write_config as write

    tmp_path.mkdir(parents=True)
    text = CBASE.replace("[run]\n", f'[run]\ndevice = "{device}"\n') + PRIOR + OBS.format(value=8.0, sigma=0.8) + CAL
    return write(tmp_path, text)


def test_calibrate_on_cuda_matches_the_cpu(tmp_path):
    """Same seeds on both devices: the same initial design, the same z to round-off, and a posterior
    that agrees (the GP and the acquisition run in float64 on the CPU in both cases)."""
    from torchslide.cli import main

    posts = {}
    for key, device in (("cpu", "cpu"), ("gpu", DEVICE)):
        cfg = _calibration_config(tmp_path / key, device)
        out = tmp_path / key / "cal"
        _reset_memory()
        assert main(["calibrate", str(cfg), "--out", str(out), "--quiet"]) == 0
        if key == "gpu":
            assert _used_the_gpu()      # the runs used the GPU
        posts[key] = json.loads((out / "posterior.json").read_text())
    c, g = posts["cpu"], posts["gpu"]
    n0 = 6
    for rc, rg in zip(c["runs"][:n0], g["runs"][:n0]):
        assert rc["x"] == pytest.approx(rg["x"], rel=1e-12)
        assert rc["z"] == pytest.approx(rg["z"], rel=1e-7, abs=1e-7)
    assert g["n_runs"] == c["n_runs"] == 10
    assert g["mean"]["mu"] == pytest.approx(c["mean"]["mu"], abs=0.02 * 0.45)
    assert g["mean"]["xi"] == pytest.approx(c["mean"]["xi"], abs=0.05 * 1800.0)


def test_diagnose_on_cuda_end_to_end(tmp_path):
    """`torchslide diagnose` with [run] device = "cuda": exit 0, the report's keys, the runs on the GPU."""
    from torchslide.cli import main

    from torchslide.terrain.synthetic import inclined_plane

    from .conftest import setup_diagnose_case as _setup, tiny_budgets

    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates=tiny_budgets())
    p.write_text(p.read_text().replace("[run]\n", f'[run]\ndevice = "{DEVICE}"\n'))
    _reset_memory()
    out = tmp_path / "out"
    assert main(["diagnose", str(p), "--out", str(out), "--quiet", "--null-runs", "0"]) == 0
    assert _used_the_gpu()
    j = json.loads((out / "report.json").read_text())
    assert j["verdict"] in ("missing_physics", "no_missing_physics", "unexplained")
    for key in ("missing_physics", "located", "candidates", "fit_before", "fit_after"):
        assert key in j
    assert np.isfinite(j["fit_before"]["misfit"])


def test_harness_case_on_cuda(tmp_path):
    """One blind-harness case with the inversion's runs on the GPU (the recording is made on the CPU)."""
    from experiments.hidden_physics.harness import run_case

    from .conftest import TINY_HARNESS_BUDGETS

    bud = dict(TINY_HARNESS_BUDGETS)
    _reset_memory()
    c = run_case("entrainment", 0, tmp_path / "res", budgets=bud, candidates=["entrainment", "mu_i"],
                 log=lambda s: None, device=DEVICE, max_batch=64)
    assert _used_the_gpu()
    assert c["device"] == DEVICE and c["compile_solver"] is False
    assert c["diagnosis"]["screening"]["ranking"][0] == "entrainment"
