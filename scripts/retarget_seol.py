"""Snakemake entry point of rule ``retarget_seol``: spacetime expression cloning (Seol et al. 2012).

input: performance (.c3d/.npz markers), rig (character .npz), neutral (tracked ROM marker .npz files); method
seol_actor_rig also actor_rig (personalized rig.npz), marker_map (the take's marker_map.json) and actor_solve (its
solve.npz), empty for seol.
output: weights (.csv), weights_json, gltf, plot (.png), metrics (retarget_metrics.json fragment), system (.npz).
params: seol (config params.retarget.seol), method, character, performance, neutral_frames.
"""

from rigbuild.logs import run_logged
from rigbuild.retarget.stage import run_seol


def main(smk) -> None:
    o, prm = smk.output, smk.params
    neutral = smk.input.neutral if "neutral" in smk.input.keys() else None
    run_seol(smk.input.performance, smk.input.rig, neutral, prm.get("neutral_frames", None), str(prm.character),
             str(prm.performance), prm.get("seol", None), weights=o.weights, weights_json=o.weights_json,
             gltf=o.gltf, plot=o.plot, metrics=o.metrics, system=o.system, method=str(prm.get("method", "seol")),
             actor_rig=smk.input.get("actor_rig", None), marker_map=smk.input.get("marker_map", None),
             actor_solve=smk.input.get("actor_solve", None))


run_logged(snakemake, main)  # noqa: F821
