"""How many threads the BLAS libraries run: one inside a window fit, one for good in a process that forks the fits
(and in those it forks), and every core the process may use in a render database's search, the one large product."""

from __future__ import annotations

import os

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from service import blas
from service.analysis.results import FitSettings
from service.pipeline.windows import JobRunner


def blas_threads() -> list[int]:
    """The threads each BLAS this process loaded runs."""
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def worker_blas() -> tuple[list[int], int]:
    """In a worker: each BLAS's threads, and the process's threads (its own and any BLAS pool's)."""
    return blas_threads(), len(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else 1


@pytest.mark.parametrize("count", [1, 2])
def test_threads_sets_every_blas_inside_and_leaves_it_as_it_found_it(count: int) -> None:
    """Inside, every BLAS the process loaded runs ``count``; after, each runs as many as before."""
    assert blas._LIBS, "no BLAS found to set"
    for found in (1, 2):
        with threadpool_limits(found, user_api="blas"):
            before = blas_threads()
            with blas.threads(count):
                assert set(blas_threads()) == {count}
            assert blas_threads() == before == [found] * len(before)


def test_the_fit_workers_fork_without_blas_threads_and_their_maker_keeps_none() -> None:
    """A fit runs its BLAS on one thread anyway; a library left at two kept idle threads, which each forked worker
    re-created and spun at its start (3-4 us of CPU per frame of an analysis). The workers fork with every BLAS on
    one thread and no thread beside their own, and the process that made them stays at one (raising it again would
    start its threads again)."""
    with threadpool_limits(2, user_api="blas"):
        with JobRunner(FitSettings(), workers=2) as runner:
            threads, tasks = runner.call(worker_blas).result()
        assert set(threads) == {1} and tasks == 1
        assert set(blas_threads()) == {1}


def test_a_database_search_multiplies_on_every_core_where_the_process_holds_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The search's product of frames and database is large (a 20,000-render database: ~230 against ~440 us a frame
    on two cores and one): it runs the process's cores while it searches, even in an analysis that holds one."""
    from service.inverse import nearest

    seen: list[list[int]] = []
    normalise = nearest.normalise

    def watched(frames: np.ndarray, factor: int) -> np.ndarray:
        seen.append(blas_threads())
        return normalise(frames, factor)

    monkeypatch.setattr(nearest, "normalise", watched)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 4096, (40, 96, 96), dtype=np.uint16)
    with threadpool_limits(1, user_api="blas"):
        database = nearest.NearestDatabase(frames, rng.random((40, 4)), rng.random(40))
        seen.clear()
        found = database.search(frames[:5], k=1)
        assert set(blas_threads()) == {1}
    assert seen and all(set(s) == {blas.usable_cores()} for s in seen)
    assert found.index[:, 0].tolist() == [0, 1, 2, 3, 4]
