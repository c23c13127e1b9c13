"""The thread pools that a query's line-rescue starts run on: PoseLib's RANSAC works outside Python's lock, so on a
few cores the starts run side by side."""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

_POOLS: dict = {}


def thread_pool(threads: int) -> Optional[ThreadPoolExecutor]:
    """The process's pool of ``threads`` threads (made once), or None for one thread: work in the caller's."""
    if threads <= 1:
        return None
    # keyed by the process too: a child forked after the pool was made inherits it without its threads
    key = (os.getpid(), threads)
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(threads, thread_name_prefix="lipmap")
    return _POOLS[key]


def mapped(f, items: list, threads: int) -> list:
    """``[f(x) for x in items]``, on ``threads`` threads when there are several items. Results come in the items'
    order, so a seeded ``f`` gives the same list on any number of threads."""
    pool = thread_pool(threads)
    if pool is None or len(items) <= 1:
        return [f(x) for x in items]
    return list(pool.map(f, items))
