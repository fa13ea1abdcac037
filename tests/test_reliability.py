"""Output folders: one writer at a time, files replaced whole, checkpoints that say when they cannot be
used, and a resume that does not mix two cases."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from torchslide.cli import main
from torchslide.files import atomic_path, folder_lock, lock_file, write_text_atomic

BUDGET = {"n_initial": "4", "n_total": "6", "batch_size": "2"}


@pytest.fixture
def case(tmp_path) -> Path:
    case = tmp_path / "case"
    assert main(["example", "bondo", "--out", str(case), "--cellsize", "300"]) == 0
    cal = (case / "calibrate.toml").read_text().replace("t_end = 300.0", "t_end = 120.0")
    for k, v in BUDGET.items():
        cal = re.sub(rf"^{k} = .*$", f"{k} = {v}", cal, flags=re.M)
    (case / "calibrate.toml").write_text(cal)
    return case


def test_a_second_writer_is_refused_and_a_dead_ones_lock_taken_over(tmp_path):
    out = tmp_path / "run"
    with folder_lock(out):
        assert lock_file(out).read_text() == str(os.getpid())
        child = subprocess.run([sys.executable, "-c", "import sys; from torchslide.files import folder_lock\n"
                                f"with folder_lock({str(out)!r}): pass"], capture_output=True, text=True)
        assert child.returncode != 0 and "is being written by another torchslide process" in child.stderr
    assert not lock_file(out).exists()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    lock_file(out).write_text(dead.stdout.strip())        # a lock whose process is gone
    with folder_lock(out):
        assert lock_file(out).read_text() == str(os.getpid())


def test_the_cli_refuses_a_folder_another_process_writes(case, capsys):
    lock_file(case.parent / "cal").write_text(str(os.getppid()))     # a live process: the test's parent
    assert main(["calibrate", str(case / "calibrate.toml"), "--out", str(case.parent / "cal"), "--quiet"]) == 2
    assert "is being written by another torchslide process" in capsys.readouterr().err
    assert not (case.parent / "cal").exists()


def test_atomic_write_leaves_the_old_file_when_the_writer_fails(tmp_path):
    p = tmp_path / "a.json"
    write_text_atomic(p, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert p.read_text() == "old" and [q.name for q in tmp_path.iterdir()] == ["a.json"]


def test_resume_refuses_corrupt_checkpoints_and_other_cases(case, capsys):
    cfg, out = case / "calibrate.toml", case.parent / "cal"
    assert main(["calibrate", str(cfg), "--out", str(out), "--quiet"]) == 0
    before = {n: (out / n).read_bytes() for n in ("posterior.json", "posterior.npz", "runs.csv")}
    # a finished calibration resumed: nothing is run or rewritten
    capsys.readouterr()
    assert main(["calibrate", str(cfg), "--out", str(out), "--quiet", "--resume"]) == 0
    assert "nothing to resume" in capsys.readouterr().err
    assert {n: (out / n).read_bytes() for n in before} == before
    # another recorded value: the resumed calibration would mix two likelihoods (also when it has finished)
    changed = case / "changed.toml"
    changed.write_text(cfg.read_text().replace("value = 63.4", "value = 50.0"))
    assert main(["calibrate", str(changed), "--out", str(out), "--quiet", "--resume"]) == 2
    assert "was calibrated with other observations" in capsys.readouterr().err
    other = case / "other.toml"
    other.write_text(cfg.read_text().replace("value = 63.4", "value = 50.0").replace("n_total = 6", "n_total = 8"))
    assert main(["calibrate", str(other), "--out", str(out), "--quiet", "--resume"]) == 2
    assert "was calibrated with other observations" in capsys.readouterr().err
    # a truncated checkpoint
    ck = out / "checkpoint.pt"
    ck.write_bytes(ck.read_bytes()[:200])
    more = case / "more.toml"
    more.write_text(cfg.read_text().replace("n_total = 6", "n_total = 8"))
    assert main(["calibrate", str(more), "--out", str(out), "--quiet", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "checkpoint" in err and "is corrupt or truncated" in err and len(err.strip().splitlines()) == 1


def test_sweep_names_a_truncated_checkpoint(case, capsys):
    out = case.parent / "sweep"
    assert main(["sweep", str(case / "calibrate.toml"), "--out", str(out), "--n", "3", "--quiet"]) == 0
    ck = out / "sweep_checkpoint.npz"
    ck.write_bytes(ck.read_bytes()[:100])
    capsys.readouterr()
    assert main(["sweep", str(case / "calibrate.toml"), "--out", str(out), "--n", "3", "--quiet", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "sweep checkpoint" in err and "is corrupt or truncated" in err


def _outputs(folder: Path, files: dict) -> dict:
    """The comparable content of a command's results: JSON without its timing keys, npz arrays, text."""
    import numpy as np

    out = {}
    for name, drop in files.items():
        p = folder / name
        if name.endswith(".json"):
            j = json.loads(p.read_text())
            out[name] = {k: v for k, v in j.items() if k not in drop}
        elif name.endswith(".npz"):
            with np.load(p) as f:
                out[name] = {k: f[k].tolist() for k in f.files}
        else:
            out[name] = p.read_text()
    return out


def _killed_then_resumed(cmd: list, out: Path, kill_after: list, timeout: float = 300.0) -> None:
    """Run ``cmd`` (torchslide arguments writing ``out``) in a subprocess, SIGKILL it after each delay in
    ``kill_after`` (s), resuming each time with --resume, then let it finish."""
    import signal
    import time

    env = dict(os.environ, OMP_NUM_THREADS="1")
    base = [sys.executable, "-m", "torchslide.cli", *cmd, "--out", str(out), "--quiet"]
    for i, delay in enumerate(kill_after):
        p = subprocess.Popen(base + (["--resume"] if i else []), env=env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
        time.sleep(delay)
        if p.poll() is None:
            p.send_signal(signal.SIGKILL)
        p.wait()
    assert subprocess.run(base + ["--resume"], env=env, capture_output=True, timeout=timeout).returncode == 0


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_sigkill_at_random_points_then_resume_gives_the_uninterrupted_results(case, seed):
    """A calibration and a sweep killed (SIGKILL) at random moments, during solver calls, checkpoint writes
    or the final writes, and resumed: the same results as an uninterrupted run (timings aside)."""
    import random
    import time

    rng = random.Random(seed)
    cfg = case / "calibrate.toml"
    cfg.write_text(cfg.read_text().replace("n_total = 6", "n_total = 12"))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    for cmd, files in ((["calibrate", str(cfg)], {"posterior.json": ("timings", "solver_seconds_this_invocation"),
                                                 "posterior.npz": (), "runs.csv": ()}),
                       (["sweep", str(cfg), "--n", "5"], {"sweep.json": ("solver_seconds",), "sweep.npz": (),
                                                          "sweep.csv": ()})):
        ref = case.parent / f"ref_{cmd[0]}"
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "torchslide.cli", *cmd, "--out", str(ref), "--quiet"], env=env,
                       check=True, capture_output=True)
        wall = time.perf_counter() - t0
        got = case.parent / f"killed_{cmd[0]}"
        _killed_then_resumed(cmd, got, sorted(rng.uniform(0.3, 1.0) * wall for _ in range(3)))
        assert _outputs(got, files) == _outputs(ref, files), cmd[0]


def test_a_corrupt_calibration_folder_is_named(case, capsys):
    """predict / sweep --calibration on a folder whose posterior.json or .npz is corrupt: one line naming
    the file."""
    import shutil

    cal = case.parent / "cal"
    assert main(["calibrate", str(case / "calibrate.toml"), "--out", str(cal), "--quiet"]) == 0
    for name, damage in (("posterior.json", lambda p: p.write_text('{"names": ["mu", "xi"], "n')),
                         ("posterior.npz", lambda p: p.write_bytes(p.read_bytes()[:300]))):
        bad = case.parent / f"bad_{name}"
        shutil.copytree(cal, bad)
        damage(bad / name)
        capsys.readouterr()
        assert main(["predict", str(case / "calibrate.toml"), "--calibration", str(bad), "--out",
                     str(case.parent / "p"), "--n", "2", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert str(bad / name) in err and len(err.strip().splitlines()) == 1, err


KILL_CASES = {
    "calibrate": ([], {"posterior.json", "posterior.npz", "runs.csv", "posterior.png", "tv.png"},
                  {"posterior.json": ("timings", "solver_seconds_this_invocation"), "posterior.npz": (), "runs.csv": ()},
                  5),     # this budget is too short for a TV history: no tv.png
    "sweep": (["--n", "3"], {"sweep.csv", "sweep.npz", "sweep.json", "posterior.png"},
              {"sweep.json": ("solver_seconds",), "sweep.npz": (), "sweep.csv": ()}, 4),
}


@pytest.mark.parametrize("command", list(KILL_CASES))
def test_a_command_killed_after_each_final_write_resumes_to_every_file(case, monkeypatch, command):
    """Killed right after each of its final writes (for calibrate: posterior.json, .npz, the rewritten
    posterior.json, runs.csv, the figures), a calibration or sweep resumes to every result file, equal to an
    uninterrupted run's; a calibration says there is nothing to resume only once finished.json, written
    last, is there. (predict writes its folder whole or not at all; diagnose: tests/test_diagnose_cli.py.)"""
    from .conftest import killed_after_write

    extra, finals, compare, n_writes = KILL_CASES[command]
    cmd = [command, str(case / "calibrate.toml"), *extra, "--quiet"]
    ref = case.parent / "ref"
    assert main([*cmd, "--out", str(ref)]) in (0, 1)
    k = 0
    while True:
        k += 1
        out = case.parent / f"killed_{k}"
        if not killed_after_write(monkeypatch, finals, k, lambda: main([*cmd, "--out", str(out)])):
            break
        assert not (out / "finished.json").exists()
        assert main([*cmd, "--out", str(out), "--resume"]) in (0, 1)
        assert _outputs(out, compare) == _outputs(ref, compare), k
        assert all((out / f).is_file() for f in finals if (ref / f).is_file()), k
    assert k == n_writes + 1       # every final write was a kill point
