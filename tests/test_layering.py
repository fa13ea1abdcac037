"""The package's one-way data flow: terrain -> solver -> observe -> bayes -> emulator -> acquisition ->
active, diagnose on top, the commands on top of all (each command standing alone)."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchslide"
LOWER = ["terrain", "solver", "physics", "result", "observe", "observe_series", "bayes", "discrepancy", "posterior", "emulator"]
UPPER = ["active", "calibration", "diagnose", "commands", "cli", "acquisition", "predict", "figures"]


def imported_modules(path: Path) -> set[str]:
    """Absolute names of the torchslide / acquisition modules that ``path`` imports (relative imports resolved)."""
    rel = path.relative_to(ROOT).with_suffix("")
    pkg = list(rel.parts[:-1]) if rel.name != "__init__" else list(rel.parts[:-1])
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg[: len(pkg) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return {m for m in out if m.split(".")[0] in ("torchslide", "acquisition")}


def _files(*parts: str):
    for part in parts:
        p = PACKAGE / part
        yield from ([p.with_suffix(".py")] if p.with_suffix(".py").exists() else sorted(p.rglob("*.py")))


@pytest.mark.parametrize("lower", LOWER)
def test_lower_layers_import_nothing_above_them(lower):
    for f in _files(lower):
        bad = sorted(m for m in imported_modules(f)
                     if m.split(".")[0] == "acquisition" or (m.startswith("torchslide.") and m.split(".")[1] in UPPER))
        assert not bad, f"{f.relative_to(ROOT)} imports {bad}"


def test_commands_do_not_import_each_other():
    commands = {f.stem for f in (PACKAGE / "commands").glob("*.py") if f.stem != "__init__"}
    for f in (PACKAGE / "commands").glob("*.py"):
        bad = sorted(m for m in imported_modules(f) if m.startswith("torchslide.commands.")
                     and m.split(".")[2] in commands and m.split(".")[2] != f.stem)
        assert not bad, f"{f.relative_to(ROOT)} imports {bad}"


def test_acquisition_stands_alone():
    """acquisition (BoTorch acquisition functions) imports no torchslide module: no package cycle."""
    for f in (ROOT / "acquisition").glob("*.py"):
        assert not any(m.startswith("torchslide") for m in imported_modules(f)), f
    code = "import sys, acquisition; print(sorted(m for m in sys.modules if m.startswith('torchslide')))"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_candidate_library_lives_with_the_diagnosis():
    import torchslide.physics as physics
    from torchslide.diagnose.candidates import CANDIDATES

    assert not hasattr(physics, "CANDIDATES")
    assert all(c.param in physics.Params.names() for c in CANDIDATES.values())


def test_the_distribution_ships_torchslide_and_acquisition_only():
    """pyproject's package list: the wheel holds torchslide and acquisition; experiments run from the repo."""
    import sys
    from setuptools import find_packages

    tomllib = __import__("tomllib" if sys.version_info >= (3, 11) else "tomli")
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    include = cfg["tool"]["setuptools"]["packages"]["find"]["include"]
    tops = {p.split(".")[0] for p in find_packages(where=str(ROOT), include=include)}
    assert tops == {"torchslide", "acquisition"}
