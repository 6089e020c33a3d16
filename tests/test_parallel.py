"""Work side by side: the same answers, in the same order, as one after another."""

from __future__ import annotations

import threading

from tiereg.parallel import map_threads


def test_map_threads_keeps_the_order_and_uses_several_threads():
    seen: set[int] = set()
    barrier = threading.Barrier(2, timeout=10)

    def square(x: int) -> int:
        seen.add(threading.get_ident())
        if x < 2:
            barrier.wait()  # the first two items meet: they run at the same time
        return x * x

    assert map_threads(square, range(7), workers=2) == [x * x for x in range(7)]
    assert len(seen) == 2
    assert map_threads(square, [5], workers=2) == [25]
    assert map_threads(lambda x: -x, range(4), workers=1) == [0, -1, -2, -3]
