"""Static profile of the Triton step's kernels for a GPU, compiled ahead of time on any machine (Triton's
own ptxas and cuobjdump; no GPU needed): per kernel, registers per thread, local memory (spills), and the
SASS instructions of the kernel's body per cell, with the MUFU among them (the special-function unit's
approximations: each exactly rounded division and square root starts with one).

    python -m bench.triton_profile [--arch 90] [--block 512] [--warps 4] [--out bench/results/triton_profile.json]
    TORCHSLIDE_EXACT_FLOAT32=1 python -m bench.triton_profile --out bench/results/triton_profile_exact_float32.json

Rows: every kernel, float32 and float64, the switches of a default Voellmy run (TERMS["voellmy"]: the slope
metric and the no-creep rule, what bench.bench_solver times) and every term on, the velocities recomputed
and stored (fused_triton.VELOCITIES). Instruction counts are static (the kernels have no loops;
the slow paths of division and sqrt, called rarely, are not counted): what a change to the kernels costs in
arithmetic, before a GPU measures its speed (bench.bench_solver --device cuda).
"""
from __future__ import annotations

import argparse
import inspect
import json
import os
import re
import subprocess
import tempfile

KERNELS = ("_velocities", "_carried", "_faces", "_drain", "_update", "_combine")
"""The kernels of a step (fused_triton), in launch order (_carried: with the slope metric, on in every row)."""

TERMS = {"voellmy": {"SLOPE": True, "NO_CREEP": True}, "all": None}
"""Switches on per row set: a default SolverConfig's Voellmy run (mu, xi only); every switch (None)."""


def switches(name: str) -> list[str]:
    """The compile-time switches of kernel ``name`` (its tl.constexpr parameters but BLOCK and AXIS)."""
    from torchslide.solver import fused_triton

    params = inspect.signature(getattr(fused_triton, name).fn).parameters
    return [p for p, v in params.items() if v.annotation in ("tl.constexpr", "constexpr")
            and p not in ("BLOCK", "AXIS")]


def compile_kernel(name: str, dtype: str, on: dict, axis: int | None = None, arch: int = 90,
                   block: int | None = None, num_warps: int | None = None):
    """Kernel ``name`` of fused_triton compiled for sm_``arch`` with the launch options of the step (fused
    multiply-add in float32 on the fast paths only); ``dtype``: 'fp32' or 'fp64'; ``on``: switch -> value
    (switches not named are off)."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from torchslide.solver import fused_triton

    fn = getattr(fused_triton, name)
    params = list(inspect.signature(fn.fn).parameters)
    consts = {"BLOCK": block or fused_triton.BLOCK, **{s: bool(on.get(s, False)) for s in switches(name)}}
    if axis is not None:
        consts["AXIS"] = axis
    sig = {p: "constexpr" if p in consts else ("*i1" if p == "inside_ptr" else f"*{dtype}")
           if p.endswith("_ptr") else "i32" for p in params}
    src = ASTSource(fn=fn, signature=sig, constexprs={(params.index(k),): v for k, v in consts.items()})
    options = {"enable_fp_fusion": fused_triton.fp_fusion(dtype), "num_warps": num_warps or fused_triton.NUM_WARPS}
    return triton.compile(src, target=GPUTarget("cuda", arch, 32), options=options)


def _cuobjdump(cubin: bytes, flag: str) -> str:
    import triton

    tool = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", "cuobjdump")
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "kernel.cubin")
        with open(path, "wb") as f:
            f.write(cubin)
        return subprocess.run([tool, flag, path], capture_output=True, text=True, check=True).stdout


def sass_profile(kernel, cells_per_thread: int) -> dict:
    """Registers, local memory bytes, and the body's SASS and MUFU instructions per cell of a compiled
    kernel whose threads hold ``cells_per_thread`` cells (BLOCK / (32 num_warps))."""
    res = _cuobjdump(kernel.asm["cubin"], "-res-usage")
    regs, local = (int(re.search(rf"{k}:(\d+)", res).group(1)) for k in ("REG", "LOCAL"))
    sass = _cuobjdump(kernel.asm["cubin"], "-sass")
    body = []       # (address, opcode) of every instruction
    for line in sass.splitlines():
        m = re.match(r"\s+/\*([0-9a-f]{4,})\*/\s+(.*?);", line)
        if m:
            body.append((int(m.group(1), 16), re.sub(r"^@!?U?P\w+\s+", "", m.group(2)).split()[0]))
    # the body ends where the first called subroutine (a slow path of division or sqrt) begins
    targets = [int(t, 16) for t in re.findall(r"CALL\.REL\.NOINC\s+0x([0-9a-f]+)", sass)]
    end = min(targets) if targets else max(a for a, op in body if op == "EXIT") + 1
    ops = [op.split(".")[0] for a, op in body if a < end]
    return {"registers": regs, "local_bytes": local,
            "instructions_per_cell": len(ops) / cells_per_thread,
            "mufu_per_cell": ops.count("MUFU") / cells_per_thread}


def profile(arch: int = 90, block: int | None = None, num_warps: int | None = None) -> list[dict]:
    from torchslide.solver import fused_triton

    block, num_warps = block or fused_triton.BLOCK, num_warps or fused_triton.NUM_WARPS
    cells_per_thread = max(1, block // (32 * num_warps))
    rows = []
    for dtype in ("fp32", "fp64"):
        for terms, switched in TERMS.items():
            for velocities in ("recomputed", "stored"):
                for name in KERNELS:
                    if name == "_velocities" and velocities == "recomputed":
                        continue
                    on = {s: switched is None or switched.get(s, False) for s in switches(name)}
                    on["STORED"] = velocities == "stored"
                    for axis in ((0, 1) if name == "_faces" else (None,)):
                        k = compile_kernel(name, dtype, on, axis, arch, block, num_warps)
                        rows.append({"kernel": name + ("" if axis is None else "xy"[axis]), "dtype": dtype,
                                     "terms": terms, "velocities": velocities, "block": block,
                                     "num_warps": num_warps, **sass_profile(k, cells_per_thread)})
    return rows


def per_cell_update(rows: list[dict]) -> dict:
    """Instructions and MUFU per cell-update (a step: two stages of the x and y faces, velocities, drain
    and update, then the combine), per dtype-terms-velocities."""
    out = {}
    for r in rows:
        key = f"{r['dtype']}-{r['terms']}-{r['velocities']}"
        s = out.setdefault(key, {"instructions": 0.0, "mufu": 0.0})
        n = 1 if r["kernel"] == "_combine" else 2
        s["instructions"] += n * r["instructions_per_cell"]
        s["mufu"] += n * r["mufu_per_cell"]
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90, help="compute capability x 10 (90: H100 / H200)")
    ap.add_argument("--block", type=int, default=None, help="BLOCK (default: fused_triton.BLOCK)")
    ap.add_argument("--warps", type=int, default=None, help="num_warps (default: fused_triton.NUM_WARPS)")
    ap.add_argument("--out", default="bench/results/triton_profile.json")
    args = ap.parse_args(argv)
    import triton

    rows = profile(args.arch, args.block, args.warps)
    for r in rows:
        print(json.dumps(r), flush=True)
    from torchslide.solver import fused_triton

    res = {"arch": f"sm_{args.arch}", "triton": triton.__version__, "fast_float32": fused_triton.FAST_FLOAT32, "rows": rows,
           "per_cell_update": per_cell_update(rows)}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=2)
    for key, s in res["per_cell_update"].items():
        print(f"{key}: {s['instructions']:.0f} SASS instructions, {s['mufu']:.0f} MUFU per cell-update")


if __name__ == "__main__":
    main()
