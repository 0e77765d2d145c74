"""How many threads the BLAS libraries run (numpy's, scipy's and OpenCV's OpenBLAS): meniscope's own matrices are
small (a window fit's 190 x 12) and its parallelism is threads and processes of its own, with which a BLAS's threads
only fight for the cores; the one large product, a render database's search, asks for them.

A BLAS's threads cost CPU even idle: made or raised again, OpenBLAS starts them, and they spin before they sleep; a
process forked from one re-creates them. So a process that forks window fits holds every BLAS to one thread for good
(:func:`hold_one_thread`; lowering a library again later would start its threads again), and a call that needs
another count sets it around itself (:func:`threads`), by threadpoolctl's controllers found once.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import ThreadpoolController

#: The BLAS libraries loaded when this module was first imported, and those found by :func:`hold_one_thread` since.
_LIBS = [lib for lib in ThreadpoolController().lib_controllers if lib.user_api == "blas"]


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity (a container's or ``taskset``'s share), not the machine's."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@contextmanager
def threads(count: int) -> Iterator[None]:
    """Each BLAS on ``count`` threads inside, as it was after: threadpoolctl's ``limit`` without its query of every
    library's version and path each time (~30 us); nothing set where a BLAS already runs ``count``."""
    before = [lib.get_num_threads() for lib in _LIBS]
    for lib, now in zip(_LIBS, before):
        if now != count:
            lib.set_num_threads(count)
    try:
        yield
    finally:
        for lib, now in zip(_LIBS, before):
            if now != count:
                lib.set_num_threads(now)


def hold_one_thread() -> None:
    """Every BLAS of this process (those loaded since the first look too) on one thread from now on: in a process
    that exists to fit windows or that forks those that do (3-4 us of CPU per frame of ``meniscope analyze`` on two
    cores went to the threads of BLAS libraries left at two: docs/benchmarks.md)."""
    _LIBS[:] = [lib for lib in ThreadpoolController().lib_controllers if lib.user_api == "blas"]
    for lib in _LIBS:
        lib.set_num_threads(1)
