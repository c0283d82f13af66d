"""Snakemake entry point of rule ``retarget_ribera``: one performance onto one character with one Ribera method.

input: performance (.c3d/.npz markers), training (tracked ROM marker .npz files), rig (character .npz);
the methods of RIBERA_RIG_METHODS also guess_rig (their rig's files), marker_map (the take's marker_map.json on
it) and actor_solve (its solve.npz), empty for the other methods.
output: weights (.csv), weights_json, gltf, preview (.png), metrics (retarget_metrics.json fragment).
params: ribera (config params.retarget.ribera), guess_rig (the rig's spec or ""), method, character, performance,
neutral_frames.
"""

from rigbuild.logs import run_logged
from rigbuild.retarget.stage import run_ribera


def main(smk) -> None:
    o, prm = smk.output, smk.params
    run_ribera(smk.input.performance, list(smk.input.training), smk.input.rig, str(prm.method), str(prm.character),
               str(prm.performance), prm.get("ribera", None), prm.get("neutral_frames", None),
               weights=o.weights, weights_json=o.weights_json, gltf=o.gltf, preview=o.preview, metrics=o.metrics,
               workers=int(smk.threads), actor_rig=prm.get("guess_rig", None) or None,
               marker_map=smk.input.get("marker_map", None), actor_solve=smk.input.get("actor_solve", None))


run_logged(snakemake, main)  # noqa: F821
