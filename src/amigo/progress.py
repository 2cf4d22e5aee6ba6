"""Progress reporting for long steps.

On a terminal a rich progress bar is drawn on stderr; elsewhere (CI, pipes, log files) each
step prints one plain line, so logs stay readable. Library code calls :func:`track` and
never needs to know which.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def _interactive() -> bool:
    return sys.stderr.isatty()


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Yield ``items`` while showing progress.

    Parameters
    ----------
    items
        Anything iterable.
    description
        What is being done, e.g. ``"process jw..._uncal.fits"``.
    total
        Number of items, when ``items`` has no ``len``.
    """
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    if _interactive():
        from rich.progress import Progress

        with Progress(transient=True) as progress:
            task = progress.add_task(description, total=total)
            for item in items:
                yield item
                progress.advance(task)
        print(f"{description}: done", file=sys.stderr)
        return
    # One line per step (the interface's rule off a terminal): the next step's line, or
    # the command's end, says that this one finished.
    print(f"{description} ...", file=sys.stderr, flush=True)
    yield from items


def step(message: str) -> None:
    """Report one step of a longer job (one line on stderr)."""
    print(message, file=sys.stderr, flush=True)


def warn(message: str) -> None:
    """Report something the user should look at, which did not stop the job: one line
    ``warning: <message>`` on stderr."""
    print(f"warning: {message}", file=sys.stderr, flush=True)
