"""bench.bench_solver: its rows on the CPU, and the Triton launch settings of a --launch row; bench.triton_profile."""
import json

import pytest
import torch

from bench import bench_solver


def test_bench_solver_measures_each_kernel(tmp_path):
    out = tmp_path / "solver.json"
    bench_solver.main(["--out", str(out), "--batches", "1", "--kernels", "eager,fused", "--dtypes", "float64",
                       "--repeats", "1", "--t-short", "1", "--full-configs", "", "--cellsize", "80"])
    d = json.loads(out.read_text())
    assert [r["kernel"] for r in d["throughput"]] == ["eager", "fused"]
    assert all(r["cell_updates_per_s_median"] > 0 and r["steps_per_member"] >= 1 and r["failed_members"] == 0
               for r in d["throughput"])
    assert set(d["speedup_vs_eager"]) == {"fused_float64_B1"}


def test_a_row_whose_members_failed_says_so(monkeypatch, capsys):
    import torch

    from torchslide.terrain.synthetic import bondo_like

    class Failed:
        steps, failed = torch.tensor([2, 48]), torch.tensor([True, False])
        failure_reason = ["non-finite state (NaN/inf) at t=2 s after 2 steps", None]

    monkeypatch.setattr(bench_solver, "_timed", lambda *a: (Failed(), 0.1))
    row = bench_solver.throughput(bondo_like(120.0), 2, "fused", "float32", "cpu", 1.0, 1)
    assert row["failed_members"] == 1 and "not a throughput" in capsys.readouterr().out


def test_a_launch_setting_holds_for_its_row_only(monkeypatch):
    from torchslide.solver import fused_triton

    settings = lambda: tuple(getattr(fused_triton, k) for k in bench_solver.LAUNCH)
    default = settings()
    seen = []
    monkeypatch.setattr(bench_solver, "_throughput", lambda *a: seen.append(settings()) or {"kernel": "fused"})
    launch = (128, 8, "lines")
    row = bench_solver.throughput(None, 1, "fused", "float32", "cuda", 1.0, 1, launch=launch)
    assert seen == [launch] and (row["block"], row["num_warps"], row["faces"]) == launch
    assert settings() == default
    assert fused_triton._launch(torch.float32)["num_warps"] == default[1]


def test_a_launch_spec_names_block_warps_and_the_faces():
    from torchslide.solver import fused_triton

    assert bench_solver.parse_launch("512x4:lines") == (512, 4, "lines")
    assert bench_solver.parse_launch("256x8") == (256, 8, fused_triton.FACES)
    assert bench_solver.parse_launch("128x4:march") == (128, 4, "march")
    for bad in ("512", "512x4:cached", "ax4", "128x4:lines:march", "128x4:tiled"):
        with pytest.raises(SystemExit, match="--launch"):
            bench_solver.parse_launch(bad)


def test_a_full_config_names_kernel_dtype_domain_members_and_graphs():
    assert bench_solver.parse_full_config("fused-f32-crop:10:graphs", 8) == ("fused", "float32", True, 10, True)
    assert bench_solver.parse_full_config("eager-f64-whole", 8) == ("eager", "float64", False, 8, False)
    assert bench_solver.parse_full_config("compiled-f64-crop:graphs:32", 8) == ("compiled", "float64", True, 32, True)
    for bad in ("fused-f16-crop", "fused-f32", "fast-f32-crop", "fused-f32-crop:0", "fused-f32-crop:10:20",
                "fused-f32-crop:graph", "fused-f32-tile:10"):
        with pytest.raises(SystemExit, match="--full-configs"):
            bench_solver.parse_full_config(bad, 8)


def test_a_bad_spec_stops_the_bench_before_its_first_run(monkeypatch, tmp_path):
    """Every --full-configs and --launch entry is checked before any row runs (the case is not even built)."""
    def no_run(*a, **k):
        raise AssertionError("a run started before the specs were checked")

    for name in ("bondo_like", "_throughput", "full_run"):
        monkeypatch.setattr(bench_solver, name, no_run)
    for argv in (["--full-configs", "fused-f64-crop,fused-f32-tile"], ["--launch", "128x4:tiled"]):
        with pytest.raises(SystemExit, match="--full-configs|--launch"):
            bench_solver.main(argv + ["--out", str(tmp_path / "x.json")])


def test_the_triton_profile_adds_each_kernel_as_often_as_a_step_runs_it():
    from bench import triton_profile

    rows = [{"kernel": k, "runs_per_step": runs, "design": "march", "dtype": "fp32", "terms": "voellmy",
             "instructions_per_cell": n, "fp_per_cell": n / 2, "mufu_per_cell": m}
            for (k, runs), n, m in zip(triton_profile.KERNELS["march"], (500, 490, 180, 250), (14, 14, 10, 12))]
    assert triton_profile.per_cell_update(rows) == {
        "march-fp32-voellmy": {"instructions": 1420.0, "fp": 710.0, "mufu": 50.0}}


def test_the_full_runs_on_the_msh2021_event(tmp_path):
    """--terrain msh2021: the embedded event's DEM and release as `torchslide example` writes them, each
    member at --mu, --xi; a row per configuration with every repeat's wall time."""
    out = tmp_path / "event.json"
    bench_solver.main(["--out", str(out), "--terrain", "msh2021", "--skip-throughput", "--kernels", "fused",
                       "--full-configs", "fused-f64-crop:2", "--full-t-end", "4", "--mu", "0.4", "--xi", "2500"])
    d = json.loads(out.read_text())
    assert d["terrain"] == "torchslide example msh2021" and d["cellsize_m"] == 10.0
    (row,) = d["full_run"]
    assert (row["B"], row["mu"], row["xi"], len(row["wall_s_repeats"])) == (2, 0.4, 2500.0, 1)
    assert row["release_volume_m3"] > 1e3 and row["h_max_max_m"] > 0 and row["steps"] > 1
