"""Snakemake entry point: score retargeted weight curves against a synthetic session's ground truth.

input: weights (.csv from scripts/retarget.py), truth (ground_truth/performances/<perf>.npz: weights,
shape_names), actor_rig (ground_truth/actor_rig.npz with the marker map).
output: metrics (.json). params: method, character, metrics_path, ribera (params.retarget.ribera: primary).
"""


import numpy as np

from rigbuild.eval.retarget import PRIMARY_RIBERA_METHOD, metric_prefixes, retarget_metrics
from rigbuild.io.atomic import write_json
from rigbuild.io.metrics import merge_metrics
from rigbuild.io.rigs import read_rig_npz
from rigbuild.logs import run_logged
from rigbuild.retarget.common import read_weight_curves_csv


def main(snakemake) -> None:
    w, names, _ = read_weight_curves_csv(snakemake.input.weights)
    with np.load(snakemake.input.truth, allow_pickle=False) as z:
        tw = z["weights"].astype(np.float64)
        tn = [str(s) for s in z["shape_names"]]
    actor = read_rig_npz(snakemake.input.actor_rig).subset(tn)
    m = retarget_metrics(w, names, tw, tn, actor.deltas[:, actor.marker_vertices])
    write_json(snakemake.output.metrics, m)
    primary = (snakemake.params.get("ribera", None) or {}).get("primary", PRIMARY_RIBERA_METHOD)
    char = snakemake.params.character
    merge_metrics(snakemake.params.metrics_path, "retarget",
                  {f"{prefix}.{char}.{k}": m[k] for prefix in metric_prefixes(snakemake.params.method, primary)
                   for k in ("weight_mae", "mean_correlation", "unobservable_mae")})


run_logged(snakemake, main)  # noqa: F821
