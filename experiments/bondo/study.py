"""The study: Table 1, the shared initial design, Algorithm 1 for every Table 2 case in lockstep,
the LHS-only comparison, brute-force references, and all saved results.

Lockstep active learning: every case has its own torchslide.active.ActiveLearner (own GP, own
checkpoint, own TensorBoard log), but in each iteration the q new points of ALL cases are simulated
together in one batched solver call through the shared CachedSimulator. The 40 initial maximin-LHS
points are identical for all cases (same seed), so they are simulated once. Rerunning resumes from
the per-case checkpoints and the simulator cache.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from torchslide.active import ActiveConfig, ActiveLearner, maximin_lhs
from torchslide.emulator import LogPosteriorEmulator
from torchslide.posterior import cell_volume, grid_posterior, hdr_mask, summarise_grid, tv_distance

from .config import CASES, BondoConfig
from .data import CaseLogPosterior, table1
from .simulator import CachedSimulator


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _sweep_solver_seconds(path) -> float | None:
    try:
        return float(json.loads(str(np.load(path)["meta"]))["solver_seconds"])
    except Exception:  # noqa: BLE001 - informational only
        return None


def _load_sweep(cfg: BondoConfig, path: Path, n: int):
    """A finished sweep from disk (no new runs), or None if it is incomplete."""
    from experiments.sweep.core import SweepResult, sweep_axes

    from torchslide.posterior import grid_points

    sim = CachedSimulator(cfg, path)
    axes = sweep_axes(cfg.bounds_array(), n)
    pts = grid_points(axes).numpy()
    if any(p not in sim for p in pts):
        return None
    y, failed, _ = sim.get(pts)
    return SweepResult(axes=axes, y=y.reshape(n, n, -1), failed=failed.reshape(n, n), names=list(sim.names),
                       seconds=0.0, path=str(path))


def truth_cell(cfg: BondoConfig, axes) -> tuple[int, int]:
    return tuple(int(np.argmin(np.abs(a - cfg.truth[n]))) for a, n in zip(axes, cfg.names))


def fit_density(cfg: BondoConfig, x, z):
    """Grid posterior of a GP fitted (fresh) to runs x (n, 2), z (n,) (failed runs dropped)."""
    x = torch.as_tensor(np.asarray(x), dtype=torch.float64)
    z = torch.as_tensor(np.asarray(z), dtype=torch.float64)
    ok = torch.isfinite(z)
    em = LogPosteriorEmulator(torch.as_tensor(cfg.bounds_array()))
    em.fit(x[ok], z[ok])
    return grid_posterior(em.mean, torch.as_tensor(cfg.bounds_array()), cfg.grid_size).density


class _Given:
    """The evaluator of a case's learner: the result the main process computed for the points it is
    asked about (the learner never runs the solver itself; the main process batches all cases' runs)."""

    def __init__(self):
        self.result = None

    def __call__(self, x):
        r, self.result = self.result, None
        if r is None or r.z.numel() != x.shape[0]:
            raise RuntimeError("a case's learner asked for a result the study did not hand it")
        return r


class CaseRunner:
    """One Table 2 case's Algorithm 1 (its ActiveLearner, snapshots and timings), stepped by run_active."""

    def __init__(self, c: int, cfg: BondoConfig, x0: torch.Tensor, res0):
        rd = cfg.run_dir
        self.c, self.cfg = c, cfg
        acfg = ActiveConfig(n_initial=cfg.n_initial, n_total=cfg.n_total, batch_size=cfg.batch_size, seed=cfg.seed,
                            grid_size=cfg.grid_size, tv_lag=cfg.tv_lag, num_restarts=cfg.num_restarts,
                            raw_samples=cfg.raw_samples, image_every=cfg.tv_lag)
        self.given = _Given()
        self.L = ActiveLearner(self.given, torch.as_tensor(cfg.bounds_array()), acfg,
                               checkpoint=rd / f"case_{c}" / "checkpoint.pt", progress=False, names=cfg.names)
        self.given.result = res0
        self.L.initialise(x0)
        self.given.result = None
        if cfg.tensorboard:
            self.L.open_log(rd / "tb" / f"case_{c}")
        sp = rd / f"case_{c}" / "snapshots.npz"
        self.snaps = dict(np.load(sp)) if sp.exists() else {}
        tp = rd / f"case_{c}" / "seconds.json"
        self.secs = json.loads(tp.read_text()) if tp.exists() else {"gp_acq_s": 0.0, "solver_share_s": 0.0}
        # a case that already finished (resume) is not refitted: its final posterior is in its snapshots
        self.done = self.L.state.n_runs >= cfg.n_total and f"a{cfg.n_adaptive}" in self.snaps
        self.pending = None

    @property
    def n_runs(self) -> int:
        return self.L.state.n_runs

    def step(self):
        """Fit, snapshot, and either finish (None) or propose the next points (q, 2)."""
        cfg, L = self.cfg, self.L
        t0 = time.perf_counter()
        density, cvol, tv = L.update()
        n_ad = L.state.n_runs - cfg.n_initial
        if n_ad in cfg.snapshots:
            self.snaps[f"a{n_ad}"] = density
            np.savez(cfg.run_dir / f"case_{self.c}" / "snapshots.npz", **self.snaps)
        x_new = None
        if L.state.n_runs >= cfg.n_total:
            L.finish("n_total reached", tv, density)
            self.done = True
        else:
            x_new, vals = L.propose(min(cfg.batch_size, cfg.n_total - L.state.n_runs))
            self.pending = (vals, tv, density)
        self.secs["gp_acq_s"] += time.perf_counter() - t0
        return x_new

    def tell(self, x_new: torch.Tensor, res, solver_share_s: float) -> None:
        vals, tv, density = self.pending
        self.secs["solver_share_s"] += solver_share_s
        self.given.result = res
        self.L.tell(x_new, self.L.evaluate(x_new), acq_max=vals[0], tv=tv, density=density)
        (self.cfg.run_dir / f"case_{self.c}" / "seconds.json").write_text(json.dumps(self.secs))

    def close(self) -> dict:
        (self.cfg.run_dir / f"case_{self.c}" / "seconds.json").write_text(json.dumps(self.secs))
        self.L.close_log()
        return {"state": self.L.state, "snapshots": self.snaps, "seconds": self.secs}


class LocalCases:
    """Cases' CaseRunners stepped in this process: start_step / end_step -> {case: new points or None},
    tell, close (the interface of RemoteCases)."""

    def __init__(self, runners: dict):
        self.runners = runners

    def status(self) -> dict:
        """{case: (done, n_runs)}."""
        return {c: (r.done, r.n_runs) for c, r in self.runners.items()}

    def start_step(self) -> None:
        self._stepped = {c: r.step() for c, r in self.runners.items() if not r.done}

    def end_step(self) -> dict:
        return self._stepped

    def tell(self, c: int, x_new, res, solver_share_s: float) -> None:
        self.runners[c].tell(x_new, res, solver_share_s)

    def close(self) -> dict:
        return {c: r.close() for c, r in self.runners.items()}


def _cases_worker(conn, cases: list, cfg: BondoConfig, x0, res0: dict) -> None:
    """A worker process holding the CaseRunners of ``cases`` (LocalCases), answering ("step",),
    ("tell", case, x, res, s) and ("close",) (then waiting for one more message before it exits)."""
    torch.set_num_threads(1)
    try:
        local = LocalCases({c: CaseRunner(c, cfg, x0, res0[c]) for c in cases})
        conn.send(("ready", local.status()))
        while True:
            msg = conn.recv()
            if msg[0] == "step":
                local.start_step()
                conn.send(("step", local.end_step(), local.status()))
            elif msg[0] == "tell":
                local.tell(*msg[1:])
                conn.send(("told", local.status()))
            else:   # torch hands tensors over by file descriptor: stay until the main process has them
                conn.send(("closed", local.close()))
                conn.recv()
                return
    except BaseException as e:  # noqa: BLE001 - reported in the main process, which stops the study
        conn.send(("error", f"cases {cases}: {type(e).__name__}: {e}"))


class RemoteCases:
    """Cases' CaseRunners in one spawned process (one torch thread), with LocalCases' interface."""

    def __init__(self, cases: list, cfg: BondoConfig, x0, res0: dict, ctx):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_cases_worker, args=(child, cases, cfg, x0, {c: res0[c] for c in cases}),
                                daemon=True)
        self.proc.start()
        self._status = None

    def _recv(self, kind: str):
        msg = self.conn.recv()
        if msg[0] == "error":
            raise RuntimeError(msg[1])
        assert msg[0] == kind, msg
        return msg[1:]

    def status(self) -> dict:
        if self._status is None:
            (self._status,) = self._recv("ready")
        return self._status

    def start_step(self) -> None:
        self.conn.send(("step",))

    def end_step(self) -> dict:
        stepped, self._status = self._recv("step")
        return stepped

    def tell(self, c: int, x_new, res, solver_share_s: float) -> None:
        self.conn.send(("tell", c, x_new, res, solver_share_s))
        (self._status,) = self._recv("told")

    def close(self) -> dict:
        self.conn.send(("close",))
        (out,) = self._recv("closed")
        self.conn.send(("bye",))
        self.proc.join()
        return out


def run_active(cfg: BondoConfig, sim: CachedSimulator, fns: dict) -> dict:
    """Algorithm 1 for all cases in lockstep; returns case -> {"state", "snapshots", "seconds"}.

    Each iteration fits every case's GP and optimises its acquisition (the cases split over cfg.workers
    spawned processes when that is above 1: they are independent), then simulates all cases' new points
    in one solver call.
    """
    x0 = torch.as_tensor(cfg.bounds_array()[0] + maximin_lhs(cfg.n_initial, 2, cfg.seed)
                         * np.diff(cfg.bounds_array(), axis=0)[0])
    _log(f"initial design: {cfg.n_initial} maximin-LHS runs shared by {len(fns)} cases")
    sim.run(x0.numpy())
    res0 = {c: fn(x0) for c, fn in fns.items()}
    cases = list(fns)
    workers = min(cfg.workers, len(cases))
    if workers > 1:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        groups = [RemoteCases(cases[k::workers], cfg, x0, res0, ctx) for k in range(workers)]
    else:
        groups = [LocalCases({c: CaseRunner(c, cfg, x0, res0[c]) for c in cases})]
    from tqdm.auto import tqdm

    try:
        bar = tqdm(total=cfg.n_total * len(cases), initial=sum(n for g in groups for _, n in g.status().values()),
                   desc="active (all cases)", unit="run")
        try:
            _lockstep(sim, fns, groups, bar)
        finally:
            bar.close()
    except BaseException:
        for g in groups:
            if isinstance(g, RemoteCases):
                g.proc.terminate()
        raise
    return {c: v for g in groups for c, v in g.close().items()}


def _lockstep(sim: CachedSimulator, fns: dict, groups: list, bar) -> None:
    """The iterations of run_active until every case has n_total runs."""
    while not all(done for g in groups for done, _ in g.status().values()):
        for g in groups:
            g.start_step()
        proposals = {c: (g, x) for g in groups for c, x in g.end_step().items() if x is not None}
        if not proposals:
            break
        allx = torch.cat([x for _, x in proposals.values()])
        t0 = time.perf_counter()
        sim.run(allx.numpy())  # ONE batched solver call for all cases' new points
        dt = time.perf_counter() - t0
        for c, (g, x_new) in proposals.items():
            g.tell(c, x_new, fns[c](x_new), dt * x_new.shape[0] / allx.shape[0])
            bar.update(x_new.shape[0])
        runs = {c: n for g in groups for c, (_, n) in g.status().items()}
        _log(f"iteration done: {allx.shape[0]} new runs in {dt:.1f} s; runs per case "
             + ", ".join(f"{c}:{runs[c]}" for c in sorted(runs)))


def run_study(cfg: BondoConfig, with_sweep: bool = True) -> dict:
    """The whole study for ``cfg``; writes results.json and per-case npz under cfg.run_dir. Returns results."""
    from experiments.sweep import reference_posterior, run_sweep

    t_start = time.perf_counter()
    machine = {"cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "load_average_start": os.getloadavg()[0]}
    if torch.device(cfg.device).type == "cuda":
        machine["gpu"] = torch.cuda.get_device_name(torch.device(cfg.device))
    rd = cfg.run_dir
    rd.mkdir(parents=True, exist_ok=True)
    (rd / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2))
    torch.set_num_threads(max(1, torch.get_num_threads()))
    extra = [] if cfg.name == "full" else [Path(cfg.work_dir) / f"full_{cfg.tag}" / "cache.npz"]
    sim = CachedSimulator(cfg, rd / "cache.npz", extra=extra)
    _log(f"study {cfg.name}: cell size {cfg.cellsize} m, t_end {cfg.t_end} s, cases {list(cfg.cases)}")
    # First solver call: the truth (Table 1, map), the shared initial design and the LHS-only design together.
    xt = np.array([[cfg.truth[n] for n in cfg.names]])
    lo, span = cfg.bounds_array()[0], np.diff(cfg.bounds_array(), axis=0)[0]
    x0 = lo + maximin_lhs(cfg.n_initial, 2, cfg.seed) * span
    x_lhs = lo + maximin_lhs(cfg.n_total, 2, cfg.lhs_only_seed) * span
    t0 = time.perf_counter()
    maps = rd / "truth_maps.npz"
    if not maps.exists():
        pts = np.vstack([xt] + [p[None] for p in np.vstack([x0, x_lhs]) if p not in sim])
        pts = pts[:cfg.max_batch]
        _log(f"first solver call: truth + {len(pts) - 1} design runs")
        y, f, r = sim.simulate_batch(pts)
        for i in range(len(pts)):
            sim._add(pts[i], y[i], f[i], r[i])
        sim.save()
        res_t = sim.last_result
        np.savez_compressed(maps, h_max=res_t.h_max[0].double().cpu().numpy(),
                            h_final=res_t.h_final[0].double().cpu().numpy())
    sim.run(np.vstack([x0, x_lhs]))
    design_s = time.perf_counter() - t0
    t1 = table1(sim, cfg)
    _log("Table 1: " + ", ".join(f"{k}={v:.4g}" for k, v in t1["simulated"].items()))
    fns = {c: CaseLogPosterior(c, sim, t1["data"], cfg) for c in cfg.cases}

    t0 = time.perf_counter()
    act = run_active(cfg, sim, fns)
    active_s = time.perf_counter() - t0

    # LHS-only comparison: GP on n_total maximin-LHS runs (another seed); simulated in the first call above.
    sweep = None
    if with_sweep:
        _log(f"brute-force sweep {cfg.sweep_n} x {cfg.sweep_n}")
        sweep = run_sweep(cfg, cfg.sweep_n)

    from torchslide.posterior import grid_axes

    axes = grid_axes(torch.as_tensor(cfg.bounds_array()), cfg.grid_size)
    cvol = cell_volume(axes)
    ti = truth_cell(cfg, axes)
    results = {"config": cfg.to_dict(), "table1": t1, "cases": {},
               "timing": {"active_s": active_s, "design_s": design_s,
                          "sweep_s": None if sweep is None else sweep.seconds,
                          "solver_s_this_process": sim.solver_seconds, "solver_calls": sim.n_solver_calls}}
    for c, a in act.items():
        fn, s = fns[c], a["state"]
        x, z = s.x.numpy(), s.z.numpy()
        dens = dict(a["snapshots"])
        for k in cfg.snapshots:  # refit where a snapshot is missing (e.g. after a resume)
            if f"a{k}" not in dens:
                dens[f"a{k}"] = fit_density(cfg, x[:cfg.n_initial + k], z[:cfg.n_initial + k])
        z_lhs = fns[c](x_lhs).z.numpy()
        dens["lhs_only"] = fit_density(cfg, x_lhs, z_lhs)
        entry = {"description": CASES[c][0], "data": list(CASES[c][1]), "n_runs": int(s.n_runs),
                 "n_failed": int(s.failed.sum()), "tv_history": [[int(n), float(t)] for n, t in s.tv_history],
                 "seconds": a["seconds"]}
        final = dens[f"a{cfg.snapshots[-1]}"]
        entry["summary"] = summarise_grid(final, axes, cfg.names).to_dict()
        entry["truth_in_hdr90"] = bool(hdr_mask(final, 0.9)[ti])
        entry["truth_in_hdr90_lhs_only"] = bool(hdr_mask(dens["lhs_only"], 0.9)[ti])
        if sweep is not None:
            _, ref, _ = reference_posterior(sweep, fn, cfg.bounds_array(), cfg.grid_size)
            dens["reference"] = ref
            entry["tv_ref"] = {str(k): tv_distance(dens[f"a{k}"], ref, cvol) for k in cfg.snapshots}
            entry["tv_ref_lhs_only"] = tv_distance(dens["lhs_only"], ref, cvol)
            entry["truth_in_hdr90_reference"] = bool(hdr_mask(ref, 0.9)[ti])
            # reference check: TV between this reference and one from every other (finished) sweep on disk
            entry["tv_ref_other_sweeps"] = {}
            for other in sorted(Path(cfg.work_dir).glob(f"sweep_{cfg.tag}_*x*.npz")):
                n_o = int(other.stem.rsplit("_", 1)[1].split("x")[0])
                if n_o == cfg.sweep_n:
                    continue
                so = _load_sweep(cfg, other, n_o)
                if so is not None:
                    _, ref_o, _ = reference_posterior(so, fn, cfg.bounds_array(), cfg.grid_size)
                    entry["tv_ref_other_sweeps"][str(n_o)] = tv_distance(ref_o, ref, cvol)
        np.savez_compressed(rd / f"case_{c}" / "posteriors.npz", x=x, z=z, is_initial=s.is_initial.numpy(),
                            x_lhs=x_lhs, axis_0=axes[0], axis_1=axes[1], **dens)
        results["cases"][str(c)] = entry
        _log(f"case {c}: truth in HDR90 {entry['truth_in_hdr90']}, TV to reference "
             f"{entry.get('tv_ref')}, LHS-only {entry.get('tv_ref_lhs_only')}")
    results["timing"]["total_s"] = time.perf_counter() - t_start
    results["timing"]["machine"] = machine
    results["timing"]["n_simulations_cached"] = len(sim)
    results["timing"]["solver_s_all_invocations"] = sim.solver_seconds
    prev = rd / "results.json"
    sp = rd / "invocations.json"  # wall time of every invocation (an interrupted study is resumed in several)
    invocations = json.loads(sp.read_text()) if sp.exists() else []
    if not invocations and prev.exists():
        old = json.loads(prev.read_text()).get("timing", {})
        invocations.append({"total_s": old.get("total_s"), "solver_calls": old.get("solver_calls"),
                         "source": "earlier results.json"})
    invocations.append({"total_s": results["timing"]["total_s"], "solver_calls": sim.n_solver_calls,
                     "new_simulations": sim.n_simulated, "ended": time.strftime("%Y-%m-%d %H:%M:%S")})
    sp.write_text(json.dumps(invocations, indent=2))
    results["timing"]["invocations"] = invocations
    results["timing"]["total_s_all_invocations"] = float(sum(x.get("total_s") or 0.0 for x in invocations))
    if sweep is not None:
        results["timing"]["sweep_solver_s"] = _sweep_solver_seconds(sweep.path)
    prev.write_text(json.dumps(results, indent=2))
    _log(f"results written to {prev} (total {results['timing']['total_s']:.0f} s)")
    return results
