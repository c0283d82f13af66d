"""Which retargeting path a studio should use on a session: one row per method from ``metrics.json``'s
``retarget.<method>.<character>.*`` numbers, and the recommended one.

With ground truth (synthetic sessions) the method with the highest mean per-shape correlation over the
characters wins (ties: the lower weight MAE). Without it, the most plausible weights win: the fewest frames with
an antagonist pair active together, then the fewest shapes active per frame (:mod:`rigbuild.retarget.plausible`);
the previews decide the rest. ``retarget.ribera`` (the primary Ribera variant reported a second time) and
per-take numbers without characters (``retarget.<source>_weights``) are not methods of their own here.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np


def method_rows(flat: Mapping[str, Any]) -> list[dict[str, Any]]:
    """``[{method, characters, mean_correlation, weight_mae, antagonist_fraction, mean_active}]`` (means over the
    characters; NaN where a method has no such number), in the order the methods appear in ``flat``."""
    from rigbuild.retarget.methods import PRIMARY_PREFIX

    values: dict[str, dict[str, list[float]]] = {}
    chars: dict[str, set] = {}
    for key, v in flat.items():
        parts = key.split(".")
        if len(parts) != 4 or parts[0] != "retarget" or parts[1] == PRIMARY_PREFIX:
            continue
        _, method, character, metric = parts
        if metric not in ("mean_correlation", "weight_mae", "antagonist_fraction", "mean_active"):
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            continue
        values.setdefault(method, {}).setdefault(metric, []).append(float(v))
        chars.setdefault(method, set()).add(character)
    rows = []
    for method, m in values.items():
        if "mean_correlation" not in m and "antagonist_fraction" not in m:
            continue  # Seol's per-frame baselines: a velocity error only
        row = {"method": method, "characters": len(chars[method])}
        for metric in ("mean_correlation", "weight_mae", "antagonist_fraction", "mean_active"):
            row[metric] = float(np.mean(m[metric])) if metric in m else float("nan")
        rows.append(row)
    return rows


def recommend(rows: list[dict[str, Any]]) -> tuple[str | None, str]:
    """(recommended method or None, the basis in words)."""
    scored = [r for r in rows if np.isfinite(r["mean_correlation"])]
    if scored:
        best = max(scored, key=lambda r: (r["mean_correlation"], -np.nan_to_num(r["weight_mae"], nan=np.inf)))
        return best["method"], "highest mean correlation with this session's ground-truth weights"
    plaus = [r for r in rows if np.isfinite(r["antagonist_fraction"])]
    if plaus:
        best = min(plaus, key=lambda r: (r["antagonist_fraction"], np.nan_to_num(r["mean_active"], nan=np.inf)))
        return best["method"], ("no ground truth: the most plausible weights (fewest antagonist pairs active "
                                "together, then fewest active shapes); check its previews")
    return None, "no retargeting numbers"
