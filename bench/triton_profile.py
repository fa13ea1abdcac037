"""Static profile of the Triton step's kernels for a GPU, compiled ahead of time on any machine (Triton's
own ptxas and cuobjdump; no GPU needed): per kernel, registers per thread, local memory (spills), and the
SASS instructions per cell, with the floating-point ones and the MUFU among them (the special-function
unit: a reciprocal, square root or reciprocal square root each).

    python -m bench.triton_profile [--arch 90] [--out bench/results/triton_profile.json]
    TORCHSLIDE_EXACT_FLOAT32=1 python -m bench.triton_profile --out bench/results/triton_profile_exact_float32.json

Rows: every kernel of both designs of the faces (fused_triton.FACES: "march", "lines") and the update (after
the first stage, and with the step's combine after the second), float32 and float64, the switches of a
default Voellmy run (TERMS["voellmy"]: the slope metric and the no-creep rule, what bench.bench_solver
times) and every term on. Counts are static: what a change to the kernels costs in instructions, before a
GPU measures its speed (bench.bench_solver --device cuda). A straight-line kernel counts its body up to
its exit (the slow paths of exactly rounded division and sqrt, called rarely, not counted) per cell a
thread holds. The marching kernel counts the body of its loop over rows per cell it writes (the W - 4 owned
of every W positions), and its prologue once per band of MARCH rows (``prologue_per_cell``), both in
``instructions_per_cell``. ``fp_per_cell``: the floating-point instructions (FADD, FMUL, FFMA, FMNMX,
FSETP, FSEL, MUFU; the D-prefixed ones in float64): the scheme's own arithmetic.
"""
from __future__ import annotations

import argparse
import inspect
import json
import os
import re
import subprocess
import tempfile

KERNELS = {"march": (("_march", 1), ("_march+second", 1), ("_update", 1), ("_update+combine", 1)),
           "lines": (("_velocities", 2), ("_facesx", 1), ("_facesx+second", 1), ("_facesy", 1), ("_facesy+second", 1),
                     ("_cells", 2), ("_update", 1), ("_update+combine", 1))}
"""The kernels of a step per design of the faces (fused_triton.FACES), each with how often a step runs it: the
first stage's faces find the time step (CFL), the second's ("+second") do not; the second stage's update
averages and records ("+combine")."""

FP = ("FADD", "FMUL", "FFMA", "FMNMX", "FSETP", "FSEL", "MUFU", "DADD", "DMUL", "DFMA", "DSETP", "DMNMX", "FCHK")
"""The floating-point SASS opcodes (fp_per_cell)."""

TERMS = {"voellmy": {"SLOPE": True, "NO_CREEP": True}, "all": None}
"""Switches on per row set: a default SolverConfig's Voellmy run (mu, xi only); every switch (None)."""

POINTERS = {"inside_ptr": "*i1", "active_ptr": "*i1"}
"""The kernels' pointers that are not to the state's dtype (bool tensors)."""

SKIP = {"INFLOW", "GONE_OUT", "WALLS"}
"""Switches the "all" rows leave off: boundary and domain settings, not terms."""


def kernel_fn(name: str):
    """The @triton.jit function of kernel ``name`` (a KERNELS entry: "_facesx" is _faces on AXIS 0)."""
    from torchslide.solver import triton_lines, triton_march, triton_update

    base = name.split("+")[0]
    base = base.rstrip("xy") if base.startswith("_faces") else base
    for module in (triton_march, triton_update, triton_lines):
        if hasattr(module, base):
            return getattr(module, base)
    raise KeyError(name)


def switches(name: str) -> list[str]:
    """The compile-time switches of kernel ``name`` (its tl.constexpr parameters but the launch shape)."""
    params = inspect.signature(kernel_fn(name).fn).parameters
    return [p for p, v in params.items() if v.annotation in ("tl.constexpr", "constexpr")
            and p not in ("BLOCK", "AXIS", "W", "BAND", "COMBINE", "FIRST", "UNROLL", "CFL")]


def compile_kernel(name: str, dtype: str, on: dict, arch: int = 90, block: int | None = None,
                   num_warps: int | None = None, march: tuple | None = None):
    """Kernel ``name`` (a KERNELS entry) compiled for sm_``arch`` with the step's launch options (fused multiply-add
    in float32 on the fast paths only); ``dtype``: 'fp32' or 'fp64'; ``on``: switch -> value (switches not
    named are off); ``march``: (W, BAND) of _march (default fused_triton.MARCH)."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from torchslide.solver import fused_triton

    fn = kernel_fn(name)
    params = list(inspect.signature(fn.fn).parameters)
    if name.startswith("_march"):
        w, band = march or fused_triton.MARCH
        consts = {"W": w, "BAND": band, "UNROLL": fused_triton.MARCH_UNROLL}
        num_warps = max(1, w // 32)
    elif name.startswith("_update"):
        w, band = fused_triton.UPDATE
        consts = {"W": w, "BAND": band, "UNROLL": fused_triton.UPDATE_UNROLL}
        num_warps = max(1, w // 32)
    else:
        consts = {"BLOCK": block or default_block(dtype)}
        num_warps = num_warps or fused_triton.NUM_WARPS
    if name.startswith("_faces"):
        consts["AXIS"] = "xy".index(name.split("+")[0][-1])
    if "COMBINE" in params:
        consts["COMBINE"] = name.endswith("+combine")
        consts["FIRST"] = not name.endswith("+combine")
    if "CFL" in params:
        consts["CFL"] = not name.endswith("+second")
    consts.update({s: bool(on.get(s, False)) for s in switches(name)})
    sig = {p: "constexpr" if p in consts else POINTERS.get(p, f"*{dtype}") if p.endswith("_ptr") else "i32"
           for p in params}
    src = ASTSource(fn=fn, signature=sig, constexprs={(params.index(k),): v for k, v in consts.items()})
    options = {"enable_fp_fusion": fused_triton.fp_fusion(dtype), "num_warps": num_warps}
    return triton.compile(src, target=GPUTarget("cuda", arch, 32), options=options)


def default_block(dtype: str) -> int:
    """fused_triton.BLOCK of ``dtype`` ('fp32' or 'fp64')."""
    from torchslide.solver import fused_triton

    block = fused_triton.BLOCK
    return block[{"fp32": "float32", "fp64": "float64"}[dtype]] if isinstance(block, dict) else block


def _cuobjdump(cubin: bytes, flag: str) -> str:
    import triton

    tool = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", "cuobjdump")
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "kernel.cubin")
        with open(path, "wb") as f:
            f.write(cubin)
        return subprocess.run([tool, flag, path], capture_output=True, text=True, check=True).stdout


def _body(sass: str) -> list[tuple[int, str, str]]:
    """(address, opcode, operands) of every instruction of the kernel up to its last EXIT, and before the first
    called subroutine (the slow paths of exactly rounded division and sqrt)."""
    body = []
    for line in sass.splitlines():
        m = re.match(r"\s+/\*([0-9a-f]{4,})\*/\s+(.*?);", line)
        if m:
            text = re.sub(r"^@!?U?P\w+\s+", "", m.group(2))
            body.append((int(m.group(1), 16), text.split()[0].split(".")[0], text))
    targets = [int(t, 16) for t in re.findall(r"CALL\.REL\.NOINC\s+0x([0-9a-f]+)", sass)]
    end = min(targets) if targets else max(a for a, op, _ in body if op == "EXIT") + 1
    return [b for b in body if b[0] < end]


def _counts(ops: list[str]) -> tuple[int, int, int]:
    return len(ops), sum(op in FP for op in ops), ops.count("MUFU")


def sass_profile(kernel, cells_per_thread: float, band: tuple | None = None) -> dict:
    """Registers, local memory bytes, shared memory bytes, and SASS, floating-point and MUFU instructions per
    cell of a compiled kernel whose threads hold ``cells_per_thread`` cells. A kernel with a loop over rows
    (``band``: (rows per program, iterations of its loop per program, rows per pass of the unrolled loop))
    counts what a full band executes, per row: the main loop's body once per pass, the remainder loop's once
    per iteration left over, and the code outside the loops once."""
    res = _cuobjdump(kernel.asm["cubin"], "-res-usage")
    regs, local = (int(re.search(rf"{k}:(\d+)", res).group(1)) for k in ("REG", "LOCAL"))
    body = _body(_cuobjdump(kernel.asm["cubin"], "-sass"))
    out = {"registers": regs, "local_bytes": local, "shared_bytes": int(kernel.metadata.shared)}
    if band is None:
        n, fp, mufu = _counts([op for _, op, _ in body])
    else:
        rows, iterations, unroll = band
        branches = [(a, int(m.group(1), 16)) for a, op, text in body if op == "BRA"
                    for m in [re.search(r"0x([0-9a-f]+)", text)] if m and int(m.group(1), 16) < a]
        loops = sorted(([b for b in body if start <= b[0] <= end] for end, start in branches), key=len, reverse=True)
        if not loops:
            raise ValueError("no loop in the kernel")
        main = loops[0]
        # the unrolled loop's remainder (about a pass over unroll of its body) runs the iterations left over;
        # a small loop (a reduction over a member's programs, at most one pass of W in practice) once
        weights = [(main, iterations // unroll)] + [
            (loop, iterations % unroll if 2 * unroll * len(loop) >= len(main) else 1) for loop in loops[1:]]
        inside = {a for loop in loops for a, _, _ in loop}
        weights.append(([b for b in body if b[0] not in inside], 1))
        counts = [0.0, 0.0, 0.0]
        for block, w in weights:
            for i, k in enumerate(_counts([op for _, op, _ in block])):
                counts[i] += w * k
        n, fp, mufu = (k / rows for k in counts)
        out["loop_per_cell"] = round(len(main) * (iterations // unroll) / rows / cells_per_thread, 1)
    out.update(instructions_per_cell=round(n / cells_per_thread, 1), fp_per_cell=round(fp / cells_per_thread, 1),
               mufu_per_cell=round(mufu / cells_per_thread, 2))
    return out


def profile(arch: int = 90, block: int | None = None, num_warps: int | None = None,
            march: tuple | None = None) -> list[dict]:
    from torchslide.solver import fused_triton

    num_warps = num_warps or fused_triton.NUM_WARPS
    w, band = march or fused_triton.MARCH
    rows = []
    for dtype in ("fp32", "fp64"):
        block_d = block or default_block(dtype)
        for terms, switched in TERMS.items():
            for design, names in KERNELS.items():
                for name, runs in names:
                    on = {s: (s not in SKIP) if switched is None else switched.get(s, False) for s in switches(name)}
                    k = compile_kernel(name, dtype, on, arch, block_d, num_warps, (w, band))
                    if name.startswith("_march"):
                        prof = sass_profile(k, (w - 4) / (32 * max(1, w // 32)), (band, band + 1, fused_triton.MARCH_UNROLL))
                        launch = {"W": w, "BAND": band, "num_warps": max(1, w // 32)}
                    elif name.startswith("_update"):
                        uw, ub = fused_triton.UPDATE
                        prof = sass_profile(k, (uw - 2) / (32 * max(1, uw // 32)), (ub, ub, fused_triton.UPDATE_UNROLL))
                        launch = {"W": uw, "BAND": ub, "num_warps": max(1, uw // 32)}
                    else:
                        prof = sass_profile(k, max(1, block_d // (32 * num_warps)))
                        launch = {"block": block_d, "num_warps": num_warps}
                    rows.append({"kernel": name, "runs_per_step": runs, "design": design, "dtype": dtype, "terms": terms,
                                 **launch, **prof})
    return rows


def per_cell_update(rows: list[dict]) -> dict:
    """Instructions, floating-point instructions and MUFU per cell-update (a step: each kernel as often as the step
    runs it), per design-dtype-terms."""
    out = {}
    for r in rows:
        key = f"{r['design']}-{r['dtype']}-{r['terms']}"
        s = out.setdefault(key, {"instructions": 0.0, "fp": 0.0, "mufu": 0.0})
        n = r["runs_per_step"]
        s["instructions"] += n * r["instructions_per_cell"]
        s["fp"] += n * r["fp_per_cell"]
        s["mufu"] += n * r["mufu_per_cell"]
    return {k: {q: round(v, 1) for q, v in s.items()} for k, s in out.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90, help="compute capability x 10 (90: H100 / H200)")
    ap.add_argument("--block", type=int, default=None, help="BLOCK of the cell-wise kernels (fused_triton.BLOCK)")
    ap.add_argument("--warps", type=int, default=None, help="their num_warps (fused_triton.NUM_WARPS)")
    ap.add_argument("--march", default=None, help="WxBAND of the marching kernel (fused_triton.MARCH)")
    ap.add_argument("--out", default="bench/results/triton_profile.json")
    args = ap.parse_args(argv)
    import triton

    march = tuple(int(a) for a in args.march.lower().split("x")) if args.march else None
    rows = profile(args.arch, args.block, args.warps, march)
    for r in rows:
        print(json.dumps(r), flush=True)
    from torchslide.solver import fused_triton

    res = {"arch": f"sm_{args.arch}", "triton": triton.__version__, "fast_float32": fused_triton.FAST_FLOAT32,
           "faces": fused_triton.FACES, "rows": rows, "per_cell_update": per_cell_update(rows)}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=2)
    for key, s in res["per_cell_update"].items():
        print(f"{key}: {s['instructions']:.0f} SASS instructions ({s['fp']:.0f} floating-point), {s['mufu']:.0f} MUFU "
              f"per cell-update")


if __name__ == "__main__":
    main()
