"""Progress bars for long commands (run, sweep, simulate, render, bench): one rule everywhere.

A bar (tqdm: count, rate and ETA) is drawn on stderr only when the caller asks for it (the
commands' ``--no-progress`` turns it off) and stderr is a terminal, so logs and CI stay quiet
while stdout remains free for what scripts read (a run directory, JSON lines).
"""
from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tqdm import tqdm


def shown(requested: bool = True) -> bool:
    """Whether a bar would be drawn: requested and stderr is a terminal."""
    return requested and sys.stderr.isatty()


def progress_bar(iterable: Iterable[Any] | None = None, *, total: int | None = None, desc: str,
                 unit: str = "it", initial: int = 0, show: bool = True) -> tqdm:
    """A tqdm bar on stderr, disabled (a silent pass-through) unless `shown(show)`."""
    from tqdm import tqdm

    return tqdm(iterable, total=total, initial=initial, desc=desc, unit=unit, file=sys.stderr,
                disable=not shown(show), dynamic_ncols=True)
