"""``results/<session>/metrics.json``: stage -> metric -> value, merged by every stage.

Several Snakemake jobs may merge at the same time, so the read-modify-write is done under an
exclusive ``fcntl`` lock on a side file and the JSON is replaced atomically.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
from pathlib import Path
from typing import Any, Iterator, Mapping

from rigbuild.io.atomic import write_json


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_suffix(path.suffix + ".lock"), "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def read_metrics(path: str | os.PathLike) -> dict[str, dict[str, Any]]:
    """Read a metrics file; an absent file is an empty dict."""
    path = Path(path)
    if not path.exists():
        return {}
    with open(path, encoding="utf-8") as fh:
        return json.load(fh)


def _clean(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _clean(v) for k, v in value.items()}
    if hasattr(value, "item") and getattr(value, "shape", None) == ():
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def merge_metrics(path: str | os.PathLike, stage: str, values: Mapping[str, Any]) -> dict:
    """Merge ``values`` into ``metrics[stage]`` of the file at ``path`` and return the whole dict.

    Keys are dotted-free metric names within the stage (``calibration`` -> ``rms_px`` is written as
    ``{"calibration": {"rms_px": 0.1}}`` and read as ``calibration.rms_px``). Non-finite floats are
    stored as ``null``.
    """
    path = Path(path)
    with _locked(path):
        metrics = read_metrics(path)
        metrics.setdefault(stage, {}).update(_clean(dict(values)))
        write_json(path, metrics)
    return metrics


def flatten_metrics(metrics: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (nested dicts are flattened recursively)."""
    flat: dict[str, Any] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, Mapping):
            for k, v in node.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        else:
            flat[prefix] = node

    walk("", metrics)
    return flat
