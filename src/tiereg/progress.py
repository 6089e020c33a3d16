"""Progress reporting hooks: the library reports, the command line decides whether to show it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol


class ProgressBar(Protocol):
    """What a progress bar must offer (a ``tqdm`` instance qualifies)."""

    def update(self, n: int) -> object: ...

    def close(self) -> object: ...


ProgressFactory = Callable[[str, int], ProgressBar]
"""Called as ``factory(description, total)``; returns a :class:`ProgressBar`."""


class _Silent:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def no_progress(desc: str, total: int) -> ProgressBar:
    """The default: report nothing."""
    return _Silent()
