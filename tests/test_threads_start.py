"""threads.start (issue 23): a task begun on a pool thread while the caller goes on (the pan-MS plots drawn while the
rasters are written); its result or exception at join; with one thread it runs in join, on the calling thread."""
from __future__ import annotations

import threading

import pytest

from gdal_gf4cal import threads


def test_start_runs_beside_the_caller_with_two_threads():
    started, go = threading.Event(), threading.Event()
    seen = {}

    def task():
        seen["thread"] = threading.get_ident()
        seen["serial"] = threads.num_threads()
        started.set()
        # waits for the caller, which lets it go only once it has begun: run in start or in join it would time out
        return go.wait(10)

    with threads.limit(2):
        join = threads.start(task)
        assert started.wait(10)            # begun while the caller goes on
        go.set()
        assert join() is True
    assert seen["thread"] != threading.get_ident()
    assert seen["serial"] == 1             # serial kernels inside, as a run_tasks task


def test_start_runs_in_join_with_one_thread():
    order = []
    with threads.limit(1):
        join = threads.start(lambda: order.append(("task", threading.get_ident())) or 42)
        order.append(("caller", threading.get_ident()))
        assert join() == 42
    assert order == [("caller", threading.get_ident()), ("task", threading.get_ident())]


@pytest.mark.parametrize("k", [1, 2])
def test_start_raises_the_tasks_error_at_join(k):
    def task():
        raise ValueError("boom")

    with threads.limit(k):
        join = threads.start(task)
        with pytest.raises(ValueError, match="boom"):
            join()
