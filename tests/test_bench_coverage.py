"""bench.coverage's bookkeeping: every case measured anew unless --resume keeps the ones already written."""
from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor

from bench import coverage


def _fake_run_case(ran: list, covers: bool):
    def run_case(terrain, kind, seed, discrepancy, inference="auto"):
        ran.append((terrain, kind, seed, discrepancy))
        return {"terrain": terrain, "kind": kind, "seed": seed, "discrepancy": discrepancy,
                "inference_asked": inference, "inference": "local", "map": {"mu": 0.25, "xi": 500.0},
                "intervals": [{"quantity": "mu", "type": "parameter", "interval": [0.2, 0.3], "truth": 0.25,
                               "covers": covers}],
                "wall_s": 1.0}
    return run_case


def _run(monkeypatch, out, covers: bool, extra=()) -> list:
    ran = []
    monkeypatch.setattr(coverage, "run_case", _fake_run_case(ran, covers))
    monkeypatch.setattr(coverage, "ProcessPoolExecutor", ThreadPoolExecutor)
    assert coverage.main(["--out", str(out), "--terrains", "narrow", "--kinds", "grid,release", "--seeds", "0",
                          "--discrepancy", "learnt", "--workers", "1", *extra]) == 0
    return ran


def test_a_coverage_run_measures_every_case_again_and_resume_keeps_the_written_ones(monkeypatch, tmp_path):
    out = tmp_path / "coverage.json"
    assert len(_run(monkeypatch, out, covers=False)) == 2
    assert json.loads(out.read_text())["summary"]["learnt"]["all"]["covered"] == 0

    assert len(_run(monkeypatch, out, covers=True)) == 2            # the code changed: every case runs again
    assert json.loads(out.read_text())["summary"]["learnt"]["all"]["covered"] == 2

    cases = json.loads(out.read_text())["cases"]
    out.write_text(json.dumps({"cases": cases[:1]}))                 # an interrupted run: one case written
    assert _run(monkeypatch, out, covers=False, extra=["--resume"]) == [("narrow", "release", 0, "learnt")]
    assert json.loads(out.read_text())["summary"]["learnt"]["all"]["covered"] == 1
