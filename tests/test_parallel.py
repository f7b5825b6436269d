"""usdml.parallel: the one place work is split over CPU threads."""

import threading

import pytest

from usdml.parallel import cpu_workers, iter_parallel, run_parallel, spans


def test_cpu_workers_counts_this_process_cores_and_one_for_a_gpu():
    import os
    n = cpu_workers()
    assert n >= 1
    if hasattr(os, "sched_getaffinity"):
        assert n == len(os.sched_getaffinity(0))
    assert cpu_workers("cpu", 3) == 3
    assert cpu_workers("cuda:0") == 1 and cpu_workers("cuda", 8) == 1


def test_results_in_order_on_several_threads():
    seen = set()

    def square(x):
        seen.add(threading.get_ident())
        return x * x

    assert run_parallel(square, range(40), 4) == [x * x for x in range(40)]
    assert run_parallel(square, [], 4) == []
    assert run_parallel(square, [3], 4) == [9]


def test_first_item_runs_alone_on_the_calling_thread():
    caller = threading.get_ident()
    started = []

    def job(x):
        started.append(x)
        return threading.get_ident()

    threads = run_parallel(job, range(6), 3, first_on_caller=True)
    assert threads[0] == caller and started[0] == 0


def test_a_worker_exception_reaches_the_caller():
    def fail(x):
        if x == 5:
            raise ValueError("item 5")
        return x

    with pytest.raises(ValueError, match="item 5"):
        run_parallel(fail, range(10), 2)
    got = []
    with pytest.raises(ValueError):
        for r in iter_parallel(fail, range(10), 2):
            got.append(r)
    assert got == [0, 1, 2, 3, 4]


@pytest.mark.parametrize("n,parts,min_size", [(10, 3, 1), (10, 20, 1), (100, 4, 40), (0, 4, 1), (7, 1, 1)])
def test_spans_cover_the_range_once(n, parts, min_size):
    s = spans(n, parts, min_size)
    assert [i for lo, hi in s for i in range(lo, hi)] == list(range(n))
    assert len(s) <= max(parts, 1)
    assert all(hi - lo >= min(min_size, n) for lo, hi in s[:-1])


def test_calls_for_every_core_share_one_pool_and_nested_calls_get_their_own():
    """A call on every core runs on the process's pool (the same threads call after call: none started per
    call); a call made from one of those threads, which would wait on the pool from inside it, gets threads of
    its own and finishes (with two workers, both pool threads blocked on inner calls would otherwise hang)."""
    n = cpu_workers()
    if n < 2:
        pytest.skip("one core: every call runs on the calling thread")

    def names(_):
        return threading.current_thread().name

    first, second = set(run_parallel(names, range(8 * n), n)), set(run_parallel(names, range(8 * n), n))
    assert all(t.startswith("usdml-parallel-pool") for t in first | second)
    assert first | second and len(first | second) <= n

    def outer(x):
        return sum(run_parallel(lambda y: x * y, range(10), n))

    done = []
    worker = threading.Thread(target=lambda: done.append(run_parallel(outer, range(4 * n), n)), daemon=True)
    worker.start()
    worker.join(timeout=30)
    assert done == [[45 * x for x in range(4 * n)]]
    # fewer workers than cores: threads of its own (not the pool's), at most that many
    assert not any(t.startswith("usdml-parallel-pool") for t in run_parallel(names, range(8), n - 1))


def test_a_forked_child_gets_a_pool_of_its_own():
    """The pool is the process's: a child forked after it started (a Dask worker, multiprocessing) runs its calls
    on new threads instead of waiting on threads the fork did not carry."""
    import multiprocessing
    import os

    if not hasattr(os, "fork"):
        pytest.skip("no fork here")
    n = max(2, cpu_workers())
    run_parallel(lambda x: x, range(8), n)               # the parent's pool exists
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(1) as pool:
        got = pool.apply_async(_child_squares, (n,)).get(timeout=60)
    assert got == [x * x for x in range(20)]


def _child_squares(n):
    return run_parallel(lambda x: x * x, range(20), n)


def test_calls_nested_three_deep_finish():
    """A call inside a call inside a call on every core: the middle one runs on threads of its own, and so must
    the innermost (were it to wait on the process's pool, whose threads all wait on the middle one, it would
    never run)."""
    n = cpu_workers()
    if n < 2:
        pytest.skip("one core: every call runs on the calling thread")

    def middle(x):
        return sum(run_parallel(lambda y: sum(run_parallel(lambda z: x + y + z, range(4), n)), range(4), n))

    done = []
    worker = threading.Thread(target=lambda: done.append(run_parallel(middle, range(2 * n), n)), daemon=True)
    worker.start()
    worker.join(timeout=30)
    assert done == [[sum(x + y + z for y in range(4) for z in range(4)) for x in range(2 * n)]]
