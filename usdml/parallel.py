"""Work over every CPU core: Warp runs a CPU launch on one thread, and Embree and NumPy release the GIL
while they work, so independent launches or calls from a thread pool run on all cores (DESIGN.md).

Every module that splits work goes through here, so the thread count has one home:

* :func:`cpu_workers` — how many threads: ``USDML_THREADS`` where set (a render-farm worker's share),
  else the cores this *process* may use (its CPU affinity, which a container or ``taskset`` narrows;
  ``os.cpu_count()`` would count the whole machine), 1 for a GPU device (its launches are asynchronous
  and go one after another);
* :func:`run_parallel` (a list) and :func:`iter_parallel` (results as they come, for progress) —
  ``fn`` over items on that many threads, results in order, a worker's exception raised in the caller;
* :func:`spans` — ``[lo, hi)`` blocks of a range to hand out; :func:`run_bands` — a launch over
  near-equal bands of a range, on those threads.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

#: environment variable a process's thread count is taken from when set (a Dask worker's ``--nthreads``)
THREADS_ENV = "USDML_THREADS"

T = TypeVar("T")
R = TypeVar("R")


def cpu_workers(device: object = "cpu", requested: int | None = None) -> int:
    """Threads to run ``device``'s work on: ``requested`` if given (at least 1), else the cores this
    process may run on; 1 for a device that is not a CPU (``"cuda"``, ``"cuda:0"``, a Warp device)."""
    if not str(device).startswith("cpu"):
        return 1
    if requested:
        return max(1, int(requested))
    given = os.environ.get(THREADS_ENV, "")
    if given.strip().isdigit() and int(given) > 0:
        return int(given)          # a farm worker's share of the machine (usdml.render.farm)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):      # no affinity on macOS / Windows
        return os.cpu_count() or 1


def iter_parallel(fn: Callable[[T], R], items: Iterable[T], workers: int, *,
                  first_on_caller: bool = False) -> Iterator[R]:
    """``fn(x)`` for ``x`` in ``items``, yielded in order as they finish, on up to ``workers`` threads.

    ``first_on_caller``: the first item runs alone on the calling thread before the others start
    (its Warp launch compiles or loads the module there, before threads race for it). One worker or
    one item: everything runs inline. A worker's exception is raised here, at its item.
    """
    items = list(items)
    if first_on_caller and items:
        yield fn(items[0])
        items = items[1:]
    if workers <= 1 or len(items) <= 1:
        for x in items:
            yield fn(x)
        return
    pool = _shared_pool(workers)
    if pool is not None:
        yield from pool.map(fn, items)
        return
    # named as the pool's: a call made from these threads is nested too, and gets threads of its own
    with ThreadPoolExecutor(max_workers=min(workers, len(items)), thread_name_prefix=f"{_POOL_PREFIX}-call") as pool:
        yield from pool.map(fn, items)


#: the process's pool for calls that ask for every core (most of them): started once, not per call (a frame made
#: some 30 calls, and starting their threads cost 20-70 ms of a 0.2 s indirect pass on 2 cores); keyed by the
#: process id, as a fork does not carry threads over
_POOL: dict = {}
_POOL_LOCK = threading.Lock()
_POOL_PREFIX = "usdml-parallel"      #: the names of the threads this module starts (the pool's, and a call's own)


def _shared_pool(workers: int) -> ThreadPoolExecutor | None:
    """The shared pool where ``workers`` is this process's core count (:func:`cpu_workers`) and the caller is not
    a thread this module started (a nested call, at any depth, gets threads of its own, as waiting on the pool
    from inside it could leave no thread to run what it waits for); None otherwise."""
    if workers != cpu_workers() or threading.current_thread().name.startswith(_POOL_PREFIX):
        return None
    pid = os.getpid()
    with _POOL_LOCK:
        pool = _POOL.get(pid)
        if pool is None:
            _POOL.clear()
            pool = _POOL[pid] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"{_POOL_PREFIX}-pool")
        return pool


def run_parallel(fn: Callable[[T], R], items: Iterable[T], workers: int, *,
                 first_on_caller: bool = False) -> list[R]:
    """``[fn(x) for x in items]`` over up to ``workers`` threads (:func:`iter_parallel`)."""
    return list(iter_parallel(fn, items, workers, first_on_caller=first_on_caller))


def run_bands(n: int, launch: Callable[[int, int], None], workers: int, bands_per_worker: int, *,
              first_on_caller: bool = False) -> None:
    """``launch(first, count)`` over ``[0, n)`` cut into ``workers × bands_per_worker`` near-equal bands
    (fewer when ``n`` is smaller), on ``workers`` threads (:func:`run_parallel`)."""
    if n <= 0:
        return
    import numpy as np

    edges = np.linspace(0, n, min(n, workers * bands_per_worker) + 1).astype(np.int64)
    jobs = [(int(a), int(b - a)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    run_parallel(lambda j: launch(*j), jobs, workers, first_on_caller=first_on_caller)


def spans(n: int, parts: int, min_size: int = 1) -> list[tuple[int, int]]:
    """``[lo, hi)`` ranges covering ``[0, n)`` in at most ``parts`` pieces of at least ``min_size``
    (the last may be shorter), in order."""
    step = max(int(min_size), -(-int(n) // max(int(parts), 1)), 1)
    return [(lo, min(n, lo + step)) for lo in range(0, int(n), step)]


__all__ = ["cpu_workers", "iter_parallel", "run_bands", "run_parallel", "spans"]
