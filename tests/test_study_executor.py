"""The study's executions on a Dask distributed cluster (a LocalCluster on loopback, its
workers in processes of their own) give byte-identical results to this process."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from mmctl.errors import MmctlError
from mmctl.study.config import StudyConfig
from mmctl.study.executor import DaskExecutor, InProcess, LocalProcesses, make_executor
from mmctl.study.report import results_csv
from mmctl.study.runner import run_study

distributed = pytest.importorskip("distributed")
pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    """A scheduler and two single-threaded worker processes on 127.0.0.1."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None) as lc:
        yield lc


def test_results_are_byte_identical_whatever_the_executor(cluster: Any) -> None:
    study = StudyConfig.make(quick=True, users=2, seed=5, t_max=20.0)
    here = results_csv(run_study(study, executor=InProcess()).executions)
    pool = results_csv(run_study(study, executor=LocalProcesses(2)).executions)
    dask = DaskExecutor(cluster.scheduler_address)
    try:
        assert dask.name.startswith("Dask cluster tcp://127.0.0.1:")
        done = run_study(study, executor=dask).executions
        remote = results_csv(done)
        # the executions ran on the workers, not here
        workers = dask.client.run(lambda: __import__("os").getpid())
    finally:
        dask.close()
    assert len(workers) == 2
    assert here == pool == remote
    assert here.count("\n") == 1 + 2 * len(study.strategies)


def test_the_cli_runs_a_study_on_the_cluster(cluster: Any, tmp_path: Any,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    from mmctl.cli import main

    rc = main(["study", "--quick", "--users", "2", "--seed", "5", "--no-figures",
               "--cluster", cluster.scheduler_address, "--out", str(tmp_path)])
    assert rc == 0
    assert "on Dask cluster tcp://127.0.0.1:" in capsys.readouterr().err
    assert (tmp_path / "results.csv").read_text().count("\n") == 1 + 2 * 3


def test_no_scheduler_is_one_line() -> None:
    with pytest.raises(MmctlError, match="no Dask scheduler answers at tcp://127.0.0.1:9"):
        DaskExecutor("tcp://127.0.0.1:9", timeout=1.0)


def test_jobs_choose_the_local_executors() -> None:
    assert isinstance(make_executor(1), InProcess)
    assert isinstance(make_executor(3), LocalProcesses)
    with pytest.raises(MmctlError, match="--jobs must be >= 1"):
        LocalProcesses(0)
