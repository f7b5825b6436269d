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
