"""Snakemake entry point of rule ``retarget_semantic``: the actor weights carried to a character by shape name.

input: weights (actor_rig weights.csv), solve (actor_rig solve.npz), actor_rig (personalize/rig.npz), rig
(character .npz). output: weights (.csv), weights_json, gltf, preview (.png), metrics (retarget_metrics.json).
params: character, performance.
"""

from rigbuild.logs import run_logged
from rigbuild.retarget.stage import run_semantic


def main(smk) -> None:
    i, o = smk.input, smk.output
    run_semantic(i.weights, i.solve, i.rig, i.actor_rig, str(smk.params.character), str(smk.params.performance),
                 weights=o.weights, weights_json=o.weights_json, gltf=o.gltf, preview=o.preview, metrics=o.metrics)


run_logged(snakemake, main)  # noqa: F821
