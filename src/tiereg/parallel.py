"""Running independent pieces of work side by side on the machine's cores."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def map_threads(fn: Callable[[T], R], items: Iterable[T], *, workers: int | None = None) -> list[R]:
    """``[fn(x) for x in items]``, in order, on ``workers`` threads (default: one per core).

    Threads, not processes: the callers' work is transforms and array operations, which release
    the interpreter's lock, on data the threads share. Measured on the coarse sweep: 1.5 times
    faster on 2 cores. ``fn`` must not mutate shared state without a lock.
    """
    items = list(items)
    n = min(workers or os.cpu_count() or 1, len(items))
    if n <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(n) as pool:
        return list(pool.map(fn, items))
