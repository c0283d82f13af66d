"""Metrics files: each job writes a *fragment* it declares as an output; one rule gathers them.

A fragment and ``results/<session>/metrics.json`` have the same shape: stage -> metric -> value, where a
value may be a nested mapping (``{"reconstruction": {"sequences": {"rom00": {"completeness": 0.97}}}}``,
read flat as ``reconstruction.sequences.rom00.completeness``). One convention for every key: nesting, never
dots or prefixes inside a name. Non-finite floats are stored as ``null``.

No job edits another job's file: the ``metrics`` rule (rules/report.smk) gathers every fragment of a session
with :func:`gather_metrics`, and a metric written by two fragments with different values is an error.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

from rigbuild.io.atomic import write_json


def read_metrics(path: str | os.PathLike) -> dict[str, dict[str, Any]]:
    """Read a metrics file; an absent file is an empty dict."""
    path = Path(path)
    if not path.exists():
        return {}
    with open(path, encoding="utf-8") as fh:
        return json.load(fh)


def clean_metrics(value: Any) -> Any:
    """Plain JSON values: numpy scalars to Python numbers, non-finite floats to None, keys to str."""
    if isinstance(value, Mapping):
        return {str(k): clean_metrics(v) for k, v in value.items()}
    if hasattr(value, "item") and getattr(value, "shape", None) == ():
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _check_scalars(values: Mapping[str, Any], where: str) -> None:
    for k, v in values.items():
        if isinstance(v, Mapping):
            _check_scalars(v, f"{where}.{k}")
        elif isinstance(v, (list, tuple)) or (hasattr(v, "shape") and getattr(v, "shape", ()) != ()):
            raise TypeError(f"metric '{where}.{k}' is a sequence: metrics are scalars (write curves and lists to "
                            "the job's own JSON output)")


def write_metrics_fragment(path: str | os.PathLike, stage: str, values: Mapping[str, Any]) -> dict:
    """Write ``{stage: values}`` atomically to ``path`` (a declared output of the calling rule); returns it.

    Values are scalars (numbers, booleans, strings, None) or nested mappings of them; a list raises TypeError."""
    _check_scalars(values, str(stage))
    fragment = {str(stage): clean_metrics(dict(values))}
    write_json(path, fragment)
    return fragment


def _merge_into(dst: dict, src: Mapping, where: str, sources: dict, source: str) -> None:
    for k, v in src.items():
        key = f"{where}.{k}" if where else str(k)
        if isinstance(v, Mapping):
            node = dst.setdefault(k, {})
            if not isinstance(node, dict):
                raise ValueError(f"metric '{key}' is a value in {sources[key]} and a mapping in {source}")
            sources.setdefault(key, source)
            _merge_into(node, v, key, sources, source)
        elif k in dst and dst[k] != v:
            raise ValueError(f"metric '{key}' is {dst[k]!r} in {sources[key]} and {v!r} in {source}")
        else:
            dst[k] = v
            sources.setdefault(key, source)


def gather_metrics(paths: Iterable[str | os.PathLike]) -> dict[str, dict[str, Any]]:
    """Deep-merge metric fragments (in the given order) into one metrics dict.

    Raises ValueError when two fragments give one metric different values (naming both files)."""
    out: dict = {}
    sources: dict[str, str] = {}
    for p in paths:
        with open(p, encoding="utf-8") as fh:
            fragment = json.load(fh)
        if not isinstance(fragment, Mapping):
            raise ValueError(f"{p}: a metrics fragment must be a mapping stage -> metrics")
        _merge_into(out, fragment, "", sources, str(p))
    return out


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
