"""Progress for long steps: a tqdm bar on a terminal; off a terminal (Snakemake jobs, CI) one short line on the
``rigbuild.progress`` logger at the first item, every :data:`LOG_INTERVAL_S` seconds and at the last, which
:func:`rigbuild.logs.run_logged` shows on Snakemake's terminal and writes to the job's log."""

from __future__ import annotations

import logging
import sys
import time
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")

#: the logger progress lines go to
LOGGER = "rigbuild.progress"
#: seconds between two progress lines off a terminal
LOG_INTERVAL_S = 10.0


def progress_line(desc: str, done: int, total: int | None, unit: str, elapsed_s: float) -> str:
    """``"ROM images: sequence 3/12 (25%), 61 s, about 183 s left"`` (``total`` None: no share, no estimate)."""
    if total:
        left = elapsed_s / done * (total - done) if done else float("nan")
        return f"{desc}: {unit} {done}/{total} ({100 * done / total:.0f}%), {elapsed_s:.0f} s, about {left:.0f} s left"
    return f"{desc}: {unit} {done}, {elapsed_s:.0f} s"


def _logged(iterable: Iterable[T], desc: str, total: int | None, unit: str) -> Iterator[T]:
    log = logging.getLogger(LOGGER)
    t0 = last = time.perf_counter()
    done = 0
    for item in iterable:
        yield item
        done += 1
        now = time.perf_counter()
        if done == 1 or done == total or now - last >= LOG_INTERVAL_S:
            last = now
            log.info("%s", progress_line(desc, done, total, unit, now - t0))


def progress(iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "step") -> Iterable[T]:
    """Wrap ``iterable``: a tqdm bar when stderr is a terminal, else progress lines (see the module); the same
    items come out either way."""
    if total is None and hasattr(iterable, "__len__"):
        total = len(iterable)
    if not sys.stderr.isatty():
        return _logged(iterable, desc, total, unit)
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, unit=unit, leave=False)
