"""localization.parallel: results in the items' order on any number of threads, and a pool that survives a fork."""
import multiprocessing
import sys
import threading

import pytest

from localization.parallel import mapped


def _square_on_thread(x):
    return x * x, threading.current_thread().name


def test_mapped_keeps_the_items_order_and_uses_the_pool_only_for_several_items():
    items = list(range(20))
    one = mapped(_square_on_thread, items, 1)
    two = mapped(_square_on_thread, items, 2)
    assert [r for r, _ in one] == [r for r, _ in two] == [x * x for x in items]
    assert {t for _, t in one} == {threading.current_thread().name}
    assert all(t.startswith("lipmap") for _, t in two)
    assert mapped(_square_on_thread, [3], 2)[0][1] == threading.current_thread().name  # one item: no hand-off
    assert mapped(_square_on_thread, [], 2) == []


def _in_child(_):
    return [r for r, _ in mapped(_square_on_thread, [1, 2, 3], 2)]


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_a_forked_child_gets_a_pool_of_its_own():
    """A child forked after the parent made its pool inherits the pool without its threads: work handed to it would
    wait forever."""
    mapped(_square_on_thread, [1, 2, 3], 2)  # the parent's pool exists
    with multiprocessing.get_context("fork").Pool(1) as pool:
        assert pool.map_async(_in_child, [0]).get(timeout=30) == [[1, 4, 9]]
