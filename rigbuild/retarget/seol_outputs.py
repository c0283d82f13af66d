"""Outputs of spacetime expression cloning: the fig. 11 velocity-error plot. (The glTF animation, with the
re-applied head motion, is written by :func:`rigbuild.io.gltf_anim.write_gltf_animation`.)"""

from __future__ import annotations

import os
from typing import Mapping

import numpy as np

from rigbuild.io.atomic import atomic_path

METHOD_LABELS = {
    "spacetime": "spacetime (ours)",
    "no_constraint": "No Const",
    "perframe_range": "Range PF",
    "perframe_prior": "Prior PF",
}


def plot_velocity_error(path: str | os.PathLike, curves: Mapping[str, np.ndarray], fps: float, title: str = "") -> None:
    """Fig. 11 of the paper: (a) the sum of velocity errors per method, (b) per-frame deltas of the
    velocity error from "No Const" along the time line. curves : {method: (F,) mm^2}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(curves)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 3.8), gridspec_kw={"width_ratios": [1, 2.6]})
    sums = [float(np.sum(curves[n])) for n in names]
    ax1.bar(range(len(names)), sums, color=["C0", "C7", "C1", "C2", "C3", "C4"][: len(names)])
    ax1.set_xticks(range(len(names)), [METHOD_LABELS.get(n, n) for n in names], rotation=20, fontsize=8)
    ax1.set_ylabel("sum of velocity errors (mm$^2$)")
    ax1.set_title("(a) ||D(BW)$^T$ - DS$^T$||$_F^2$", fontsize=9)
    base = curves.get("no_constraint")
    for n in names:
        if n == "no_constraint":
            continue
        c = np.asarray(curves[n])
        y = c - base if base is not None else c
        t = np.arange(c.size) / float(fps)
        ax2.plot(t, y, "-" if n == "spacetime" else ":", lw=1.2, label=METHOD_LABELS.get(n, n))
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("velocity error - No Const (mm$^2$)" if base is not None else "velocity error (mm$^2$)")
    ax2.set_title("(b) per-frame difference from No Const", fontsize=9)
    ax2.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


