"""Where the study's executions run: this process, local worker processes, or a Dask
distributed cluster (issue 19: sweeps and replications run many studies).

An :class:`Executor` maps a module-level function over a list of jobs and yields the
results as they finish, in any order; the caller sorts them.  Every execution is
deterministic given its job (user, approach, seed, configuration), so the results are
byte-identical whatever ran them (``tests/test_study_executor.py`` compares
``results.csv`` from each).

* :class:`InProcess`: one after the other, here (``--jobs 1``; debugging, profiling);
* :class:`LocalProcesses`: a ``multiprocessing`` pool of ``jobs`` processes (the
  default: ``--jobs`` = the machine's CPUs);
* :class:`DaskExecutor`: the workers of a running Dask distributed scheduler
  (``--cluster tcp://HOST:8786``; ``dask-scheduler`` / ``dask-worker`` on the machines,
  each with mmctl installed, or any ``distributed`` deployment); needs the ``cluster``
  extra (``pip install mmctl[cluster]``).
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, TypeVar

from mmctl.errors import MmctlError

J = TypeVar("J")
R = TypeVar("R")


class Executor(Protocol):
    """Runs ``fn`` on every job; yields the results as they finish (any order)."""

    name: str

    def map_unordered(self, fn: Callable[[J], R], jobs: Sequence[J]) -> Iterator[R]: ...

    def close(self) -> None: ...


class InProcess:
    """Every job in this process, in order."""

    name = "in-process"

    def map_unordered(self, fn: Callable[[J], R], jobs: Sequence[J]) -> Iterator[R]:
        for job in jobs:
            yield fn(job)

    def close(self) -> None:
        pass


class LocalProcesses:
    """A pool of ``jobs`` worker processes on this machine (fork where there is one)."""

    def __init__(self, jobs: int) -> None:
        if jobs < 1:
            raise MmctlError(f"--jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.name = f"{jobs} local processes"

    def map_unordered(self, fn: Callable[[J], R], jobs: Sequence[J]) -> Iterator[R]:
        if len(jobs) <= 1 or self.jobs == 1:
            yield from InProcess().map_unordered(fn, jobs)
            return
        methods = mp.get_all_start_methods()
        ctx = mp.get_context("fork" if "fork" in methods else "spawn")
        with ctx.Pool(min(self.jobs, len(jobs))) as pool:
            yield from pool.imap_unordered(fn, jobs)

    def close(self) -> None:
        pass


class DaskExecutor:
    """The workers of the Dask distributed scheduler at ``address`` (tcp://HOST:PORT),
    or of a :class:`distributed.Client` given as ``client`` (tests: a LocalCluster's)."""

    def __init__(self, address: str | None = None, client: Any = None,
                 timeout: float = 30.0) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise MmctlError("--cluster needs Dask distributed: pip install "
                             "'mmctl[cluster]'") from None
        if client is None:
            try:
                client = Client(address, timeout=timeout)  # type: ignore[no-untyped-call]
            except (OSError, TimeoutError) as exc:
                raise MmctlError(f"no Dask scheduler answers at {address} ({exc})") from None
            self._own = True
        else:
            self._own = False
        self.client = client
        self.name = f"Dask cluster {client.scheduler.address}"

    def map_unordered(self, fn: Callable[[J], R], jobs: Sequence[J]) -> Iterator[R]:
        from distributed import as_completed

        # pure=False: every job runs, none is served from the cache of an equal key
        futures = self.client.map(fn, list(jobs), pure=False)
        try:
            for fut in as_completed(futures):  # type: ignore[no-untyped-call]
                yield fut.result()
        finally:
            self.client.cancel(futures)

    def close(self) -> None:
        if self._own:
            self.client.close()


def make_executor(jobs: int = 1, cluster: str | None = None) -> Executor:
    """The executor for ``--jobs`` / ``--cluster``."""
    if cluster:
        return DaskExecutor(cluster)
    if jobs == 1:
        return InProcess()
    return LocalProcesses(jobs)


def run_all(fn: Callable[[J], R], jobs: Sequence[J], executor: Executor | None = None,
            workers: int = 1, progress: Callable[[int, str], None] | None = None,
            describe: Callable[[R], str] | None = None) -> list[R]:
    """``fn`` over ``jobs`` on ``executor`` (None: :func:`make_executor` of ``workers``,
    closed afterwards); the results in the order they finished, with
    ``progress(done, describe(result))`` after each."""
    run = executor if executor is not None else make_executor(workers)
    done: list[R] = []
    try:
        for r in run.map_unordered(fn, jobs):
            done.append(r)
            if progress is not None:
                progress(len(done), describe(r) if describe is not None else "")
    finally:
        if executor is None:
            run.close()
    return done
