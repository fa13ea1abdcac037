"""bench.bench_solver: its rows on the CPU, and the Triton launch settings of a --launch row."""
import json

from bench import bench_solver


def test_bench_solver_measures_each_kernel(tmp_path):
    out = tmp_path / "solver.json"
    bench_solver.main(["--out", str(out), "--batches", "1", "--kernels", "eager,fused", "--dtypes", "float64",
                       "--repeats", "1", "--t-short", "1", "--full-configs", "", "--cellsize", "80"])
    d = json.loads(out.read_text())
    assert [r["kernel"] for r in d["throughput"]] == ["eager", "fused"]
    assert all(r["cell_updates_per_s_median"] > 0 and r["steps_per_member"] >= 1 for r in d["throughput"])
    assert set(d["speedup_vs_eager"]) == {"fused_float64_B1"}


def test_a_launch_setting_holds_for_its_row_only(monkeypatch):
    from torchslide.solver import fused_triton

    default, seen = (fused_triton.BLOCK, fused_triton.NUM_WARPS), []
    monkeypatch.setattr(bench_solver, "_throughput",
                        lambda *a: seen.append((fused_triton.BLOCK, fused_triton.NUM_WARPS)) or {"kernel": "fused"})
    row = bench_solver.throughput(None, 1, "fused", "float32", "cuda", 1.0, 1, launch=(128, 8))
    assert seen == [(128, 8)] and (row["block"], row["num_warps"]) == (128, 8)
    assert (fused_triton.BLOCK, fused_triton.NUM_WARPS) == default
    assert fused_triton._launch(None)["num_warps"] == default[1]
