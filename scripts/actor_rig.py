"""Snakemake entry point of rule ``actor_rig_weights``: a take's markers on the personalized rig, actor weights.

input: performance (.c3d/.npz markers), rig (personalize/rig.npz, or the template rig's files). output: marker_map (.json), weights (.csv),
weights_json, solve (.npz), metrics (actor_rig_metrics.json fragment). params: actor_rig
(params.retarget.actor_rig), performance, rig (the rig spec), source (actor_rig | template_rig).
"""

from rigbuild.logs import run_logged
from rigbuild.retarget.stage import run_actor_rig


def main(smk) -> None:
    o = smk.output
    run_actor_rig(smk.input.performance, str(smk.params.rig), smk.params.get("actor_rig", None),
                  str(smk.params.performance), source=str(smk.params.source), marker_map=o.marker_map, weights=o.weights, weights_json=o.weights_json, solve=o.solve,
                  metrics=o.metrics)


run_logged(snakemake, main)  # noqa: F821
