"""Progress bars for long steps: tqdm on a terminal, silent otherwise (Snakemake logs, CI)."""

from __future__ import annotations

import sys
from typing import Iterable, TypeVar

T = TypeVar("T")


def progress(iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "step") -> Iterable[T]:
    """Wrap ``iterable`` in a tqdm bar when stderr is a terminal; otherwise return it unchanged."""
    if not sys.stderr.isatty():
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, unit=unit, leave=False)
