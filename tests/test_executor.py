"""The executor interface: local processes and a Dask cluster give the same results."""

from __future__ import annotations

import numpy as np
import pytest

from mrft_gcs.design.executor import LocalExecutor, make_executor
from mrft_gcs.errors import UsageError


def seeded_cycle_period(seed: int) -> float:
    """A small, seeded piece of design work: one noisy MRFT cycle's period."""
    from mrft_gcs.simulate import find_cycle, simulate_mrft

    run = simulate_mrft(1.0, 0.05, 0.5, 0.01, beta=-0.5, h=1.0, noise_std=0.001, band=0.004,
                        duration_s=4.0, seed=seed)
    return find_cycle(run.u[0], run.y[0], run.dt).period_s


def test_local_serial_and_pool_agree():
    with LocalExecutor(1) as a, LocalExecutor(2) as b:
        assert a.map(seeded_cycle_period, range(4)) == b.map(seeded_cycle_period, range(4))


def test_dask_local_cluster_matches_local_run():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        with make_executor(dask=cluster.scheduler_address) as ex:
            remote = ex.map(seeded_cycle_period, range(4))
    with make_executor(workers=1) as ex:
        local = ex.map(seeded_cycle_period, range(4))
    assert np.allclose(remote, local, rtol=0, atol=0)


def test_bad_settings_are_usage_errors():
    with pytest.raises(UsageError):
        LocalExecutor(0)
    with pytest.raises(UsageError):
        make_executor(dask="tcp://127.0.0.1:1")
