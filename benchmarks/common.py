"""Shared by the benchmark scripts: a results table printer and the JSON writer."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Sequence

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

OUT = Path(__file__).resolve().parent / "out"
ROOT = Path(__file__).resolve().parents[1]
#: generated sessions of the benchmarks (git-ignored)
CACHE = OUT / "cache"


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict[str, Any]:
    return {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "commit": _git("rev-parse", "HEAD"),
            "uncommitted_changes": bool(_git("status", "--porcelain", "--untracked-files=no"))}


def cached_session(folder: Path, synthetic: dict[str, Any], make: Callable[[Path], Any]) -> Path:
    """A generated session in ``folder``: ``make(folder)`` runs again only when the ``synthetic`` block or the
    generator's committed sources (the git trees of rigbuild/synth and rigbuild/render) differ from the ones
    it was made with (``folder/bench_key.json``)."""
    key = json.dumps({"synthetic": synthetic, "sources": [_git("rev-parse", f"HEAD:rigbuild/{d}")
                                                          for d in ("synth", "render")]}, sort_keys=True)
    stamp = folder / "bench_key.json"
    if not (stamp.exists() and stamp.read_text() == key):
        t0 = time.perf_counter()
        make(folder)
        stamp.write_text(key)
        print(f"{folder.name}: generated in {time.perf_counter() - t0:.0f} s")
    return folder


def print_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> None:
    widths = [max(len(c), *(len(_fmt(r.get(c))) for r in rows)) for c in columns]
    print("  ".join(c.ljust(w) for c, w in zip(columns, widths)))
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print("  ".join(_fmt(r.get(c)).ljust(w) for c, w in zip(columns, widths)))


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def write_result(name: str, payload: dict[str, Any]) -> Path:
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"{name}.json"
    payload = {"benchmark": name, "machine": machine(), **payload}
    path.write_text(json.dumps(payload, indent=2, default=float) + "\n")
    print(f"wrote {path}")
    return path
