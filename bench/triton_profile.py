"""Static profile of the Triton step's kernels for a GPU, compiled ahead of time on any machine (Triton's
own ptxas and cuobjdump; no GPU needed): per kernel, registers per thread, local memory (spills), and the
SASS instructions of the kernel's body per cell, with the MUFU among them (the special-function unit's
approximations: each exactly rounded division and square root starts with one).

    python -m bench.triton_profile [--arch 90] [--block 512] [--warps 4] [--out bench/results/triton_profile.json]
    TORCHSLIDE_EXACT_FLOAT32=1 python -m bench.triton_profile --out bench/results/triton_profile_exact_float32.json

Rows: every kernel of both designs of the faces (fused_triton.FACES: "tiled", whose _tiled kernel counts per
cell it holds, its halo's positions included in the cost; "lines", the velocities recomputed and stored:
fused_triton.VELOCITIES), float32 and float64, the switches of a default Voellmy run (TERMS["voellmy"]: the
slope metric and the no-creep rule, what bench.bench_solver times) and every term on. Instruction counts are
static (the kernels have no loops; the slow paths of division and sqrt, called rarely, are not counted):
what a change to the kernels costs in arithmetic, before a GPU measures its speed (bench.bench_solver
--device cuda). ``fp_per_cell``: the floating-point instructions among them (FADD, FMUL, FFMA, FMNMX,
FSETP, FSEL, MUFU; the D-prefixed ones in float64): the scheme's own arithmetic, which no layout removes.
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
"""The kernels of a step with FACES = "lines" (fused_triton), in launch order (_carried: with the slope
metric, on in every row)."""

TILED = ("_tiled", "_drain", "_update", "_combine")
"""The kernels of a step with FACES = "tiled" (the velocities stored by _tiled)."""

FP = ("FADD", "FMUL", "FFMA", "FMNMX", "FSETP", "FSEL", "MUFU", "DADD", "DMUL", "DFMA", "DSETP", "DMNMX", "FCHK")
"""The floating-point SASS opcodes (fp_per_cell)."""

TERMS = {"voellmy": {"SLOPE": True, "NO_CREEP": True}, "all": None}
"""Switches on per row set: a default SolverConfig's Voellmy run (mu, xi only); every switch (None)."""


def switches(name: str) -> list[str]:
    """The compile-time switches of kernel ``name`` (its tl.constexpr parameters but BLOCK and AXIS)."""
    from torchslide.solver import fused_triton

    params = inspect.signature(getattr(fused_triton, name).fn).parameters
    return [p for p, v in params.items() if v.annotation in ("tl.constexpr", "constexpr")
            and p not in ("BLOCK", "AXIS", "TY", "TX")]


def compile_kernel(name: str, dtype: str, on: dict, axis: int | None = None, arch: int = 90,
                   block: int | None = None, num_warps: int | None = None, tile: tuple | None = None):
    """Kernel ``name`` of fused_triton compiled for sm_``arch`` with the launch options of the step (fused
    multiply-add in float32 on the fast paths only); ``dtype``: 'fp32' or 'fp64'; ``on``: switch -> value
    (switches not named are off); _tiled: ``tile`` (rows, columns; default fused_triton.TILE) and
    ``num_warps`` (default fused_triton.TILE_WARPS)."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from torchslide.solver import fused_triton

    fn = getattr(fused_triton, name)
    params = list(inspect.signature(fn.fn).parameters)
    if name == "_tiled":
        ty, tx = tile or fused_triton.TILE
        consts = {"TY": ty, "TX": tx}
        num_warps = num_warps or fused_triton.TILE_WARPS
    else:
        consts = {"BLOCK": block or fused_triton.BLOCK}
    consts.update({s: bool(on.get(s, False)) for s in switches(name)})
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


def sass_profile(kernel, cells_per_thread: float) -> dict:
    """Registers, local memory bytes, shared memory bytes, and the body's SASS, floating-point and MUFU
    instructions per cell of a compiled kernel whose threads hold ``cells_per_thread`` cells (BLOCK /
    (32 num_warps); for _tiled the cells a tile holds per thread)."""
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
    return {"registers": regs, "local_bytes": local, "shared_bytes": int(kernel.metadata.shared),
            "instructions_per_cell": round(len(ops) / cells_per_thread, 1),
            "fp_per_cell": round(sum(op in FP for op in ops) / cells_per_thread, 1),
            "mufu_per_cell": round(ops.count("MUFU") / cells_per_thread, 2)}


def tile_cells_per_thread(tile: tuple, num_warps: int) -> float:
    """Cells a _tiled program holds ((rows - 3) (columns - 3)) per thread."""
    return (tile[0] - 3) * (tile[1] - 3) / (32 * num_warps)


def profile(arch: int = 90, block: int | None = None, num_warps: int | None = None, tile: tuple | None = None,
            tile_warps: int | None = None) -> list[dict]:
    from torchslide.solver import fused_triton

    block, num_warps = block or fused_triton.BLOCK, num_warps or fused_triton.NUM_WARPS
    tile, tile_warps = tile or fused_triton.TILE, tile_warps or fused_triton.TILE_WARPS
    cells_per_thread = max(1, block // (32 * num_warps))
    rows = []
    for dtype in ("fp32", "fp64"):
        for terms, switched in TERMS.items():
            for design, velocities in (("tiled", "stored"), ("lines", "recomputed"), ("lines", "stored")):
                for name in TILED if design == "tiled" else KERNELS:
                    if name == "_velocities" and velocities == "recomputed":
                        continue
                    on = {s: switched is None or switched.get(s, False) for s in switches(name)}
                    on["STORED"] = velocities == "stored"
                    for axis in ((0, 1) if name == "_faces" else (None,)):
                        tiled = name == "_tiled"
                        k = compile_kernel(name, dtype, on, axis, arch, block, tile_warps if tiled else num_warps,
                                           tile if tiled else None)
                        per = tile_cells_per_thread(tile, tile_warps) if tiled else cells_per_thread
                        launch = {"tile": list(tile), "num_warps": tile_warps} if tiled else \
                            {"block": block, "num_warps": num_warps}
                        rows.append({"kernel": name + ("" if axis is None else "xy"[axis]), "design": design,
                                     "dtype": dtype, "terms": terms, "velocities": velocities, **launch,
                                     **sass_profile(k, per)})
    return rows


def per_cell_update(rows: list[dict]) -> dict:
    """Instructions, floating-point instructions and MUFU per cell-update (a step: two stages of the faces,
    drain and update, then the combine), per design-dtype-terms-velocities."""
    out = {}
    for r in rows:
        key = f"{r['design']}-{r['dtype']}-{r['terms']}-{r['velocities']}"
        s = out.setdefault(key, {"instructions": 0.0, "fp": 0.0, "mufu": 0.0})
        n = 1 if r["kernel"] == "_combine" else 2
        s["instructions"] += n * r["instructions_per_cell"]
        s["fp"] += n * r["fp_per_cell"]
        s["mufu"] += n * r["mufu_per_cell"]
    return {k: {q: round(v, 1) for q, v in s.items()} for k, s in out.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90, help="compute capability x 10 (90: H100 / H200)")
    ap.add_argument("--block", type=int, default=None, help="BLOCK (default: fused_triton.BLOCK)")
    ap.add_argument("--warps", type=int, default=None, help="num_warps (default: fused_triton.NUM_WARPS)")
    ap.add_argument("--tile", default=None, help="_tiled's ROWSxCOLUMNS (default: fused_triton.TILE)")
    ap.add_argument("--tile-warps", type=int, default=None, help="_tiled's num_warps (default: fused_triton.TILE_WARPS)")
    ap.add_argument("--out", default="bench/results/triton_profile.json")
    args = ap.parse_args(argv)
    import triton

    tile = tuple(int(a) for a in args.tile.lower().split("x")) if args.tile else None
    rows = profile(args.arch, args.block, args.warps, tile, args.tile_warps)
    for r in rows:
        print(json.dumps(r), flush=True)
    from torchslide.solver import fused_triton

    res = {"arch": f"sm_{args.arch}", "triton": triton.__version__, "fast_float32": fused_triton.FAST_FLOAT32,
           "faces": fused_triton.FACES, "rows": rows,
           "per_cell_update": per_cell_update(rows)}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=2)
    for key, s in res["per_cell_update"].items():
        print(f"{key}: {s['instructions']:.0f} SASS instructions ({s['fp']:.0f} floating-point), {s['mufu']:.0f} MUFU "
              f"per cell-update")


if __name__ == "__main__":
    main()
