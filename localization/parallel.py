"""The thread pools a query's independent parts share: PoseLib's solvers and OpenCV work outside Python's lock, and
much of numpy's, so on a few cores one query's rescue starts (and its hypotheses' parts) run side by side."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Optional

_POOLS: dict = {}


def thread_pool(threads: int) -> Optional[ThreadPoolExecutor]:
    """The process's pool of ``threads`` threads (made once), or None for one thread: work in the caller's."""
    if threads <= 1:
        return None
    if threads not in _POOLS:
        _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix="lipmap")
    return _POOLS[threads]


def mapped(f, items: list, threads: int) -> list:
    """``[f(x) for x in items]``, on ``threads`` threads when there are several items. Results come in the items'
    order, so a seeded ``f`` gives the same list on any number of threads."""
    pool = thread_pool(threads)
    if pool is None or len(items) <= 1:
        return [f(x) for x in items]
    return list(pool.map(f, items))
