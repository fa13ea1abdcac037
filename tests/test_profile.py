"""profile.switch_profile: the profile of a refit along its switch finds the rest of a ridge."""
from types import SimpleNamespace

import numpy as np
import torch

from torchslide.diagnose.polish import local_search
from torchslide.diagnose.profile import ridge_trend, switch_ladder, switch_profile

BOX = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 10.0]])


def ridge_z(x):
    """A curved ridge: mu follows the switch s, the profile max_mu,xi z is -0.5 ((s - 3) / 2)^2."""
    x = np.asarray(x, float)
    mu, xi, s = x[:, 0], x[:, 1], x[:, 2]
    return (-0.5 * ((mu - (0.2 + 0.03 * s + 0.002 * (s - 3) ** 2)) / 0.005) ** 2 - 0.5 * ((xi - 0.5) / 0.05) ** 2
            - 0.5 * ((s - 3) / 2) ** 2)


def make_ev(calls, z_of=ridge_z):
    def ev(x):
        x = np.asarray(torch.as_tensor(x, dtype=torch.float64))
        calls.append(len(x))
        return SimpleNamespace(z=torch.as_tensor(z_of(x)), failed=torch.zeros(len(x), dtype=torch.bool))
    return ev


def test_ridge_trend_and_ladder():
    rng = np.random.default_rng(0)
    s = rng.normal(5.0, 0.1, 500)
    d = np.column_stack([0.1 + 0.02 * s + 1e-4 * rng.standard_normal(500), np.full(500, 0.5), s])
    m, slope, sd = ridge_trend(d)
    assert abs(slope[0] - 0.02) < 2e-3 and abs(slope[1]) < 1e-9 and abs(sd - 0.1) < 0.02
    S = switch_ladder([4.6, 5.0], (0.0, 10.0), n_values=5)
    assert np.allclose(S, [3.8, 4.3, 4.8, 5.3, 5.8])          # half-width 0.1 x prior width (> 1.5 x 0.4)
    assert np.allclose(switch_ladder([0.0, 0.2], (0.0, 10.0), 5), [0.0, 0.5, 1.0, 1.5, 2.0])   # shifted off the bound
    assert np.allclose(switch_ladder([0.0, 10.0], (0.0, 10.0), 3), [0.0, 5.0, 10.0])


def test_local_search_holds_axes():
    calls = []
    ev = make_ev(calls)
    x0 = np.array([[0.3, 0.4, 6.0], [0.25, 0.6, 2.0]])
    r = local_search(ev, x0, ridge_z(x0), BOX, n_iter=3, pop=5, n_starts=None, step0=[0.05, 0.05, 0.05],
                     hold=[False, False, True])
    assert calls == [10] * 3
    assert set(np.round(r["x"][:, 2], 9)) == {6.0, 2.0}        # every start searched, its switch never moved
    assert r["best_z"] > ridge_z(x0).max()


def test_switch_profile_follows_the_ridge_beyond_a_narrow_posterior():
    """Draws on one stretch of the ridge (s ~ 4.8, slightly off it in mu), truth-like peak at s = 3:
    the profile climbs back onto the ridge at every ladder value and extends the ladder towards 3."""
    rng = np.random.default_rng(1)
    s = rng.normal(4.8, 0.12, 400)
    draws = np.column_stack([0.2 + 0.03 * s + 0.008 + 0.002 * rng.standard_normal(400),
                             0.5 + 0.02 * rng.standard_normal(400), s])
    calls = []
    p = switch_profile(make_ev(calls), draws, [4.6, 5.0], BOX, n_values=5, n_iter=3, pop=6, extend=2, drop=2.0)
    S, z = p["switch"], p["z"]
    assert np.all(np.diff(S) > 0) and S.min() <= 3.0 + 1e-9 and len(S) == 9      # 5 + 2 per side
    prof = -0.5 * ((S - 3) / 2) ** 2
    assert np.all(z <= prof + 1e-9) and np.all(z > prof - 1.0)       # on the ridge at every value
    assert abs(S[np.argmax(z)] - 3.0) < 0.6
    assert np.allclose(p["x"][:, 2], S) and len(p["runs_z"]) == len(p["runs_x"]) == sum(calls)
    # a profile that falls off at both ends is not extended
    calls.clear()
    q = switch_profile(make_ev(calls), np.column_stack([0.2 + 0.03 * 3 + np.zeros(50), np.full(50, 0.5),
                                                        rng.normal(3.0, 0.05, 50)]),
                       [2.9, 3.1], BOX, n_values=5, n_iter=1, pop=4, extend=2, drop=0.01)
    assert len(q["switch"]) == 5


class _RidgeEvaluator:
    """Toy evaluator whose 'solver' predicts y = (mu - 0.03 s, xi, s) against data (0.2, 0.5, 3):
    a straight ridge mu = 0.2 + 0.03 s along the switch s (sd 2 along it), Uniform prior on
    [0, 1] x [0, 1] x [0, 10]; log Z = ln(P(0 < s < 10) / 10) in closed form."""

    def __init__(self):
        from torchslide.bayes import GaussianLikelihood, Prior, Uniform
        self.likelihood = GaussianLikelihood(torch.tensor([0.2, 0.5, 3.0]), sigma=torch.tensor([0.02, 0.05, 2.0]))
        self.prior = Prior({"mu": Uniform(0.0, 1.0), "xi": Uniform(0.0, 1.0), "s": Uniform(0.0, 10.0)})

    @staticmethod
    def predict(x):
        x = torch.as_tensor(x, dtype=torch.float64)
        return torch.stack([x[:, 0] - 0.03 * x[:, 2], x[:, 1], x[:, 2]], dim=1)

    def evaluate(self, x):
        return SimpleNamespace(failed=torch.zeros(len(x), dtype=torch.bool)), self.predict(x)

    def __call__(self, x):
        x = torch.as_tensor(x, dtype=torch.float64)
        return SimpleNamespace(z=self.likelihood.log_likelihood(self.predict(x)) + self.prior.log_prob(x),
                               failed=torch.zeros(len(x), dtype=torch.bool))


def test_profile_refit_widens_a_posterior_stuck_on_one_stretch_of_the_ridge():
    """A refit whose posterior covers s in ~[4.6, 5.0] of a ridge whose mass spans s ~ 0-6.3:
    pipeline.profile_refit finds profile optima that its proposal underweights by far, refines with
    the profile's runs, and the refined 90 % interval covers s = 3 with a verified log Z near the
    closed form; profiled again until no optimum is underweighted, it is then left as it is."""
    from math import erf, log, sqrt

    from torchslide.active import maximin_lhs
    from torchslide.diagnose import pipeline
    from torchslide.diagnose.predictive import posterior_predictive
    from torchslide.diagnose.verify import verified_evidence

    ev = _RidgeEvaluator()
    z_of = lambda x: ev(x).z
    rng = np.random.default_rng(3)
    s = rng.normal(4.8, 0.1, 300)
    stuck = np.column_stack([0.2 + 0.03 * s + 0.01 * rng.standard_normal(300), 0.5 + 0.03 * rng.standard_normal(300), s])
    box = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 10.0]])
    x = np.vstack([box[0] + maximin_lhs(20, 3, seed=2) * (box[1] - box[0]), stuck[:6]])
    cal = SimpleNamespace(names=["mu", "xi", "s"], x=x, z=z_of(x).numpy(), failed=np.zeros(len(x), bool), bounds=box,
                          samples=stuck, log_evidence=-5.0, posterior_grid=None, n_runs=len(x),
                          emulator=SimpleNamespace(mean=lambda t: z_of(t)),
                          summary={"mean": {}, "hdr90": {n: [0, 1] for n in ("mu", "xi", "s")}, "map": {}})
    for i, n in enumerate(cal.names):
        cal.summary["mean"][n] = cal.summary["map"][n] = float(stuck[:, i].mean())
    p_c = posterior_predictive(ev, stuck[:12])
    ver = verified_evidence(ev, cal, p_c.x, p_c.draws, seed=0)
    hist = [{"n_runs": len(x), "log_evidence": ver["log_evidence"], "kept": True}]
    bud = pipeline.Budgets(n_posterior_samples_after=16, refit_refine_rounds=3, refit_grid=(48, 40), mode_search_pop=6)
    res, p_r, v_r, h_r, out = pipeline.profile_refit(ev, cal, p_c, ver, hist, bud, log=lambda s: None, name="s")
    assert out["refined"] and out["adopted"] and out["max_log_weight_excess"] > bud.profile_outside
    assert out["interval_before"][0] > 4.0 and min(out["switch"]) < 3.5
    lo, hi = pipeline._params(res)["s"]["hdi90"]
    assert lo < 3.0 < hi and hi - lo > 3.0
    truth = log((0.5 * (erf(7 / 2 / sqrt(2)) - erf(-3 / 2 / sqrt(2)))) / 10)
    assert abs(v_r["log_evidence"] - truth) < 0.5
    assert not h_r[0]["kept"] and all(h.get("profile") for h in h_r[1:])
    # profiled again (the pipeline's profile_rounds): the first refinement's zoomed grid still cut the
    # tail at large s short (weights there e^7 above the draws'); the rounds stop once no profile
    # optimum weighs more than e^1 above them, with log Z at the closed form
    for _ in range(2):
        res, p_r, v2, h2, out2 = pipeline.profile_refit(ev, res, p_r, v_r, h_r, bud, log=lambda s: None, name="s")
        if not out2["refined"]:
            assert v2 is v_r and h2 is h_r and out2["max_log_weight_excess"] <= bud.profile_outside
            break
        v_r, h_r = v2, h2
    assert not out2["refined"] and abs(v_r["log_evidence"] - truth) < 0.3
    assert pipeline._params(res)["s"]["hdi90"][0] < 1.0


def test_switch_profile_searches_a_dip_again_from_its_neighbours():
    """A ladder value whose first search failed (its runs scored 30 too low during the first pass) lies
    far below the line between its neighbours: it is searched again from their optima and lands on the
    ridge; the profile of the others is untouched."""
    calls = []
    base = make_ev(calls)

    def ev(x):
        r = base(x)
        x = np.asarray(torch.as_tensor(x, dtype=torch.float64))
        if len(calls) <= 3:                                   # the first pass: 1 start call + 2 search iterations
            r.z = torch.where(torch.as_tensor(np.isclose(x[:, 2], 4.3)), r.z - 30.0, r.z)
        return r

    rng = np.random.default_rng(2)
    s = rng.normal(4.8, 0.12, 400)
    draws = np.column_stack([0.2 + 0.03 * s + 0.002 * (s - 3) ** 2 + 0.001 * rng.standard_normal(400),
                             0.5 + 0.01 * rng.standard_normal(400), s])
    p = switch_profile(ev, draws, [4.6, 5.0], BOX, n_values=5, n_iter=2, pop=6, extend=0, drop=2.0)
    assert p["repaired"] == [4.3] and len(calls) == 3 + 3
    k = int(np.flatnonzero(np.isclose(p["switch"], 4.3))[0])
    assert p["z"][k] > -0.5 * ((4.3 - 3) / 2) ** 2 - 1.0



def test_local_search_goes_on_while_it_climbs():
    """max_iter: a search started far down a curved ridge goes on after n_iter while it still climbs
    (more than tol over the last 4 iterations) and gets much closer to the top than n_iter iterations; at
    the top it stops after n_iter. Same seed: its first n_iter iterations are the fixed search's."""
    def z_of(x):
        mu, xi, s = np.asarray(x, float).T
        return -0.5 * ((mu - (0.2 + 0.03 * s)) / 0.01) ** 2 - 0.5 * ((xi - 0.5) / 0.05) ** 2 - 0.5 * (s - 3) ** 2

    def ev_of(calls):
        return make_ev(calls, z_of)

    x0 = np.array([[0.2 + 0.03 * 8, 0.5, 8.0]])                       # on the ridge at s = 8: z = -12.5
    kw = dict(pop=6, step0=[0.01] * 3, seed=2)
    calls = []
    fixed = local_search(ev_of(calls), x0, z_of(x0), BOX, n_iter=4, **kw)
    assert fixed["iters"] == 4 and len(fixed["trace"]) == 4 and calls == [6] * 4
    calls = []
    climb = local_search(ev_of(calls), x0, z_of(x0), BOX, n_iter=4, max_iter=40, tol=0.5, **kw)
    assert 4 < climb["iters"] <= 40 and calls == [6] * climb["iters"]
    assert climb["trace"][3] == fixed["trace"][3] and np.all(np.diff(climb["trace"]) >= 0)
    assert fixed["best_z"] < -8 and climb["best_z"] > -2                # 4 iterations: halfway up; climbing: the top
    if climb["iters"] < 40:                                              # it stopped: the last 4 gained <= tol
        assert climb["trace"][-1] - climb["trace"][-5] <= 0.5
    top = np.array([[0.29, 0.5, 3.0]])
    calls = []
    r = local_search(ev_of(calls), top, z_of(top), BOX, n_iter=2, max_iter=40, **kw)
    assert r["iters"] == 2 and calls == [6, 6] and r["improvement"] <= 0.0


def test_local_search_with_no_iterations_runs_nothing():
    """mode_search_iters = 0 (documented as off): no run, the best of the given runs, no improvement."""
    import numpy as np
    from torchslide.diagnose.polish import local_search

    def never(x):
        raise AssertionError("no run expected")

    X = np.array([[0.1, 0.2], [0.3, 0.4]])
    out = local_search(never, X, np.array([-3.0, -1.0]), np.array([[0.0, 0.0], [1.0, 1.0]]), n_iter=0)
    assert out["x"].shape == (0, 2) and out["improvement"] == 0.0 and out["best_z"] == -1.0
    assert np.array_equal(out["best_x"], X[1]) and out["iters"] == 0
