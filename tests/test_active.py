import numpy as np
import pytest
import torch

from torchslide.active import ActiveConfig, ActiveLearner, iteration_seed, maximin_lhs
from torchslide.bayes import EvaluationResult

B = [[-3.0, -3.0], [3.0, 3.0]]


def gauss(x):
    return -0.5 * (x[:, 0] ** 2 + (x[:, 1] - 0.5) ** 2 * 4)


def test_maximin_lhs_seeded_and_stratified():
    a, b = maximin_lhs(10, 2, seed=3), maximin_lhs(10, 2, seed=3)
    assert np.array_equal(a, b)
    for j in range(2):  # one point per stratum
        assert sorted(np.floor(a[:, j] * 10).astype(int).tolist()) == list(range(10))
    assert iteration_seed(0, 1) != iteration_seed(0, 2) and iteration_seed(1, 1) == iteration_seed(1, 1)


class Crashy:
    """Evaluator that raises (simulated crash) on its k-th call."""

    def __init__(self, crash_on=None):
        self.calls, self.crash_on = 0, crash_on

    def __call__(self, x):
        self.calls += 1
        if self.crash_on is not None and self.calls == self.crash_on:
            raise KeyboardInterrupt("simulated crash")
        return gauss(x)


CFG = dict(n_initial=10, n_total=22, batch_size=3, seed=5, grid_size=40, num_restarts=2, raw_samples=32, tv_lag=3)


def test_resume_after_crash_matches_uninterrupted(tmp_path):
    ref = ActiveLearner(Crashy(), B, ActiveConfig(**CFG), progress=False).run()
    ck = tmp_path / "ck.pt"
    ev = Crashy(crash_on=3)  # initial design + 1 batch done, crash in batch 2
    with pytest.raises(KeyboardInterrupt):
        ActiveLearner(ev, B, ActiveConfig(**CFG), checkpoint=ck, progress=False).run()
    assert ck.exists()
    ev2 = Crashy()
    learner = ActiveLearner(ev2, B, ActiveConfig(**CFG), checkpoint=ck, progress=False)
    s = learner.run()
    assert s.n_runs == ref.n_runs == 22
    assert torch.allclose(s.x, ref.x) and torch.allclose(s.z, ref.z)
    assert ev2.calls == 3  # only the unfinished batches were run: (22 - 10 - 3) / 3
    assert [t for _, t in s.tv_history] == pytest.approx([t for _, t in ref.tv_history])
    # resuming a finished run evaluates nothing
    ev3 = Crashy()
    ActiveLearner(ev3, B, ActiveConfig(**CFG), checkpoint=ck, progress=False).run()
    assert ev3.calls == 0
    with pytest.raises(ValueError, match="seed"):
        ActiveLearner(Crashy(), B, ActiveConfig(**{**CFG, "seed": 6}), checkpoint=ck, progress=False).run()


def test_failed_runs_flagged_excluded_and_logged(tmp_path):
    def ev(x):
        z = gauss(x)
        bad = x[:, 0] > 2.0
        z = torch.where(x[:, 0] < -2.5, torch.full_like(z, float("nan")), z)
        return EvaluationResult(z=z, failed=bad, reasons=["solver diverged" if b else "" for b in bad.tolist()])
    cfg = ActiveConfig(n_initial=12, n_total=18, batch_size=2, seed=0, grid_size=30, num_restarts=2,
                       raw_samples=32, tv_lag=2)
    L = ActiveLearner(ev, B, cfg, progress=False, log_dir=tmp_path / "tb")
    s = L.run()
    f = s.failed
    assert f.any() and torch.isnan(s.z[f]).all() and torch.isfinite(s.z[~f]).all()
    assert all(s.reasons[i] for i in torch.nonzero(f).flatten().tolist())
    assert L.emulator.model.train_inputs[0].shape[0] == int((~f).sum())
    assert any(p.name.startswith("events") for p in (tmp_path / "tb").iterdir())


def test_tv_stopping():
    cfg = ActiveConfig(n_initial=15, n_total=60, batch_size=3, seed=1, grid_size=40, num_restarts=2,
                       raw_samples=32, tv_lag=3, tv_threshold=0.05, tv_patience=2)
    s = ActiveLearner(gauss, B, cfg, progress=False).run()
    assert s.n_runs < 60 and "TV" in s.stopped_reason


def test_a_finished_run_resumed_gives_the_same_posterior(tmp_path):
    """A run killed during its final writes (its checkpoint says finished) is resumed to the same
    posterior, bit for bit: the final fit is repeated from its own warm start, no TV is recorded twice."""
    from torchslide.calibration import calibrate

    ck = tmp_path / "ck.pt"
    kw = dict(n_initial=8, n_total=14, batch_size=3, seed=2, grid_size=25, checkpoint=ck, progress=False)
    a = calibrate(gauss, B, **kw)
    b = calibrate(Crashy(crash_on=1), B, **kw)          # evaluates nothing: its first call would raise
    assert np.array_equal(a.posterior_grid, b.posterior_grid) and a.log_evidence == b.log_evidence
    assert a.tv_history == b.tv_history and np.array_equal(a.x, b.x)
