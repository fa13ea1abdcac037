"""torchslide.executor: sweep, predict and calibrate on a Dask LocalCluster of 2 worker processes give
exactly the local results; a worker killed in the middle of a chunk costs that chunk only."""
from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import numpy as np
import pytest

from torchslide.cli import main

from .conftest import CALIBRATE_BASE as BASE, CALIBRATE_CAL as CAL, CALIBRATE_OBS as OBS, CALIBRATE_PRIOR as PRIOR
from .conftest import truth_velocity, write_config as write

distributed = pytest.importorskip("distributed")

# max_batch 1: every batch is several chunks, so the workers share them
SMALL = CAL.replace("batch_size = 2", "batch_size = 2\nmax_batch = 1")


@pytest.fixture(scope="module")
def cluster():
    c = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                 env={"OMP_NUM_THREADS": "1"})
    yield c
    c.close()


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("executor")
    v = truth_velocity(d)
    return d, write(d, BASE + PRIOR + OBS.format(value=v, sigma=0.1 * v) + SMALL)


def _dask(cluster) -> list[str]:
    return ["--executor", "dask", "--scheduler", cluster.scheduler_address]


def test_sweep_and_predict_on_two_workers_equal_the_local_runs(case, cluster):
    d, cfg = case
    assert main(["sweep", str(cfg), "--out", str(d / "sw_local"), "--n", "3", "--quiet"]) == 0
    assert main(["sweep", str(cfg), "--out", str(d / "sw_dask"), "--n", "3", "--quiet"] + _dask(cluster)) == 0
    assert (d / "sw_local" / "sweep.csv").read_text() == (d / "sw_dask" / "sweep.csv").read_text()
    a, b = np.load(d / "sw_local" / "sweep.npz"), np.load(d / "sw_dask" / "sweep.npz")
    assert np.array_equal(a["z"], b["z"]) and np.array_equal(a["density"], b["density"])

    assert main(["calibrate", str(cfg), "--out", str(d / "cal"), "--quiet"]) == 0
    for name, extra in (("pr_local", []), ("pr_dask", _dask(cluster))):
        assert main(["predict", str(cfg), "--calibration", str(d / "cal"), "--out", str(d / name), "--n", "5",
                     "--quiet"] + extra) == 0
    assert (d / "pr_local" / "draws.csv").read_text() == (d / "pr_dask" / "draws.csv").read_text()
    for f in sorted(p.name for p in (d / "pr_local").glob("*.asc")):
        assert (d / "pr_local" / f).read_text() == (d / "pr_dask" / f).read_text(), f


def test_calibrate_spreads_each_iteration_over_the_workers(case, cluster):
    """batch_size 2 with max_batch 1: each iteration's two points run on two workers; the posterior and
    every run equal the local calibration's."""
    d, cfg = case
    assert main(["calibrate", str(cfg), "--out", str(d / "c_local"), "--quiet"]) == 0
    assert main(["calibrate", str(cfg), "--out", str(d / "c_dask"), "--quiet"] + _dask(cluster)) == 0
    a, b = (json.loads((d / n / "posterior.json").read_text()) for n in ("c_local", "c_dask"))
    assert a["runs"] == b["runs"] and a["map"] == b["map"] and a["hdr90"] == b["hdr90"]
    assert a["log_evidence"] == b["log_evidence"]


def _die_once(marker: str, fn, chunk):
    """fn(chunk), except that the first call anywhere kills its worker process mid-chunk (the marker is
    created atomically, so that two workers starting at once do not both die)."""
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return fn(chunk)
    os._exit(1)


def test_a_worker_killed_mid_chunk_loses_only_that_chunk(case, cluster, tmp_path):
    import cloudpickle
    import torch

    from torchslide.calibration_config import load_calibration_config, make_evaluator
    from torchslide.executor import DaskExecutor

    cloudpickle.register_pickle_by_value(__import__(__name__))
    d, cfg = case
    ev = make_evaluator(load_calibration_config(cfg))
    x = torch.tensor([[0.15, 800.0], [0.2, 1000.0], [0.25, 1200.0], [0.3, 600.0]], dtype=torch.float64)
    local, p_local = ev.evaluate(x)
    ex = DaskExecutor(scheduler=cluster.scheduler_address)
    try:
        chunks = ev.value_chunks({n: x[:, i].numpy() for i, n in enumerate(ev.names)})
        marker = str(tmp_path / "killed")
        out = ex.map(functools.partial(_die_once, marker, ev._predictions_chunk), chunks)
    finally:
        ex.close()
    assert Path(marker).exists()                    # a worker did die in the middle of a chunk
    assert torch.equal(torch.cat([o[0] for o in out]), p_local)
    assert not torch.cat([o[1] for o in out]).any() and not local.failed.any()


def test_executor_settings_are_checked(tmp_path, capsys):
    from torchslide.config import ConfigError, parse_executor
    from torchslide.executor import make_executor

    assert parse_executor({}, Path("c.toml")) == ("local", None, None)
    assert parse_executor({"executor": "dask", "workers": 2}, Path("c.toml")) == ("dask", None, 2)
    for r, msg in (({"executor": "ray"}, 'executor must be "local" or "dask", got \'ray\''),
                   ({"executor": "dask", "workers": 0}, "workers must be an integer >= 1, got 0"),
                   ({"executor": "dask", "scheduler": "host"}, "scheduler must be an address"),
                   ({"workers": 2}, 'need executor = "dask"'),
                   ({"executor": "dask", "workers": 2, "scheduler": "tcp://h:1"}, "not both")):
        with pytest.raises(ConfigError, match=msg):
            parse_executor(r, Path("c.toml"))
    with pytest.raises(ValueError, match="executor must be one of"):
        make_executor("ray")
    v = truth_velocity(tmp_path)
    cfg = write(tmp_path, BASE.replace("t_end = 60.0", 't_end = 60.0\nexecutor = "dask"\nworkers = 0')
                + PRIOR + OBS.format(value=v, sigma=0.1 * v) + SMALL)
    capsys.readouterr()
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "s"), "--n", "2", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "[run] workers must be an integer >= 1, got 0" in err and len(err.strip().splitlines()) == 1
