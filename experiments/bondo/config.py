"""Typed configuration of the Bondo-like synthetic case study (paper sections "Case study",
"Parameter calibration setup"): truth, prior box, noise, Table 2 cases and run settings."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: Names of every observable stored per run (Table 1 rows), with units and labels.
OBSERVABLES: dict[str, tuple[str, str]] = {
    "impact_area": ("m^2", "Impact area (h_max > 0.5 m)"),
    "deposit_area": ("m^2", "Deposit area (h > 0.5 m)"),
    "deposit_volume": ("m^3", "Deposit volume (h > 0.5 m)"),
    "vmax_L1": ("m/s", "Max velocity at L1"),
    "vmax_L2": ("m/s", "Max velocity at L2"),
    "vmax_L3": ("m/s", "Max velocity at L3"),
    "hdep_L2": ("m", "Deposit height at L2"),
    "hdep_L3": ("m", "Deposit height at L3"),
}

#: Synthetic observed data: (data id, observable, noise sd as a fraction of the simulated value).
#: The first eight are the 10 % rows of Table 1; the last two are the extra rows for L1 (20 %, 30 %).
DATA: list[tuple[str, str, float]] = [(k, k, 0.10) for k in OBSERVABLES] + [
    ("vmax_L1_20", "vmax_L1", 0.20),
    ("vmax_L1_30", "vmax_L1", 0.30),
]

#: Table 2: case number -> (description, data ids used).
CASES: dict[int, tuple[str, tuple[str, ...]]] = {
    1: ("max velocity at L1", ("vmax_L1",)),
    2: ("max velocity at L2", ("vmax_L2",)),
    3: ("max velocity at L3", ("vmax_L3",)),
    4: ("deposit height at L3", ("hdep_L3",)),
    5: ("impact area", ("impact_area",)),
    6: ("deposit volume", ("deposit_volume",)),
    7: ("max velocity at L1, sd 20 %", ("vmax_L1_20",)),
    8: ("max velocity at L1, sd 30 %", ("vmax_L1_30",)),
    9: ("max velocity at L1 + deposit volume", ("vmax_L1", "deposit_volume")),
    10: ("max velocity at L3 + deposit height at L3", ("vmax_L3", "hdep_L3")),
}


@dataclass
class BondoConfig:
    """Settings of the study.

    Attributes:
        truth: underlying true parameters (mu -, xi m/s^2).
        bounds: uniform prior box per parameter.
        cellsize: terrain cell size, m (the paper's DEM is finer; see README for what was run).
        t_end: simulated time, s.
        n_initial: b0 maximin-LHS runs shared by all cases; n_adaptive: adaptive runs per case.
        batch_size: q points per iteration per case (all cases' points run in one solver call); 1 is
            the paper's Algorithm 1.
        snapshots: adaptive-run counts at which the posterior is stored (Fig. 3, TV tables).
        grid_size: posterior grid per axis.
        seed: LHS / acquisition seed; lhs_only_seed: seed of the 120-run LHS-only comparison design.
        noise_seed: seed of the synthetic observation noise.
        sweep_n: nodes per axis of the brute-force sweep (edges included).
        cases: case numbers to run.
        max_batch: most solver members per call (points are sorted by mu first, so that one call's
            members have similar run-outs and share a small cropped window).
        dtype: "float64" or "float32" (the solver's precision; the GP is always float64).
        kernel: the solver step (SolverConfig.kernel: "fused" default, "eager", "compiled").
        stop_quiet_time: SolverConfig.stop_quiet_time (the footprint stop rule); 0 ends a run on its
            kinetic energy alone (1e-4 of its peak), the rule this study's page was made with.
        device: where the solver runs ("cpu", "cuda"); the GP and acquisition stay on the CPU.
        workers: processes that fit the cases' GPs and optimise their acquisitions in parallel (the cases
            split over them, one torch thread each; 1: all in this process).
        work_dir: caches, checkpoints, results (git-ignored); figures_dir: PNG output.
        tensorboard: write TensorBoard logs per case under work_dir/tb/case_N.
        num_restarts, raw_samples: acquisition optimiser settings.
    """

    truth: dict = field(default_factory=lambda: {"mu": 0.23, "xi": 1000.0})
    bounds: dict = field(default_factory=lambda: {"mu": (0.02, 0.3), "xi": (100.0, 2200.0)})
    cellsize: float = 40.0
    t_end: float = 300.0
    n_initial: int = 40
    n_adaptive: int = 80
    batch_size: int = 1
    snapshots: tuple = (0, 20, 50, 80)
    grid_size: int = 100
    seed: int = 0
    lhs_only_seed: int = 1
    noise_seed: int = 2017
    sweep_n: int = 30
    cases: tuple = tuple(CASES)
    max_batch: int = 25
    dtype: str = "float32"
    kernel: str = "fused"
    stop_quiet_time: float = 0.0
    device: str = "cpu"
    workers: int = 1
    work_dir: str = str(HERE / "_work")
    figures_dir: str = str(HERE / "figures")
    tensorboard: bool = True
    num_restarts: int = 8
    raw_samples: int = 256
    tv_lag: int = 10
    name: str = "full"

    @property
    def names(self) -> list[str]:
        return list(self.bounds)

    @property
    def n_total(self) -> int:
        return self.n_initial + self.n_adaptive

    @property
    def tag(self) -> str:
        """Identifies the simulator setup (cache files are only shared between equal tags)."""
        return f"cs{self.cellsize:g}_t{self.t_end:g}_{self.dtype}"

    @property
    def run_dir(self) -> Path:
        return Path(self.work_dir) / f"{self.name}_{self.tag}"

    def bounds_array(self):
        import numpy as np

        return np.array([[self.bounds[n][0] for n in self.names], [self.bounds[n][1] for n in self.names]],
                        dtype=np.float64)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["snapshots"] = list(self.snapshots)
        d["cases"] = list(self.cases)
        return d

    @classmethod
    def quick(cls, work_dir: str | None = None, **kw) -> "BondoConfig":
        """A few-minute (or less) configuration of the whole pipeline: coarse terrain, few runs."""
        base = dict(cellsize=120.0, t_end=300.0, n_initial=8, n_adaptive=4, batch_size=2, snapshots=(0, 2, 4),
                    grid_size=30, sweep_n=6, cases=(1, 10), num_restarts=2, raw_samples=32, tv_lag=2,
                    name="quick", lhs_only_seed=1, dtype="float64")
        if work_dir is not None:
            base["work_dir"] = work_dir
            base["figures_dir"] = str(Path(work_dir) / "figures")
        base.update(kw)
        return cls(**base)

    @classmethod
    def from_saved(cls, d: dict) -> "BondoConfig":
        """The config of a saved results.json (a run saved with ``compile`` ran kernel "compiled" or "eager")."""
        d = dict(d)
        if "compile" in d:
            d.setdefault("kernel", "compiled" if d.pop("compile") else "eager")
        return cls(**{k: (tuple(v) if k in ("snapshots", "cases") else v) for k, v in d.items()})

    def with_(self, **kw) -> "BondoConfig":
        return replace(self, **kw)
