"""Snakemake entry point of rule ``actor_rig_weights``: a take's markers on the personalized rig, actor weights.

input: performance (.c3d/.npz markers), rig (personalize/rig.npz). output: marker_map (.json), weights (.csv),
weights_json, solve (.npz), metrics (actor_rig_metrics.json fragment). params: actor_rig
(params.retarget.actor_rig), performance.
"""

from rigbuild.logs import run_logged
from rigbuild.retarget.stage import run_actor_rig


def main(smk) -> None:
    o = smk.output
    run_actor_rig(smk.input.performance, smk.input.rig, smk.params.get("actor_rig", None), str(smk.params.performance),
                  marker_map=o.marker_map, weights=o.weights, weights_json=o.weights_json, solve=o.solve,
                  metrics=o.metrics)


run_logged(snakemake, main)  # noqa: F821
