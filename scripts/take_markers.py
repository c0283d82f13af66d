"""Snakemake entry point of rule ``take_markers``: a take's markers on the tracked neutral, the ROM read there.

input: performance (.c3d/.npz markers), session_yaml, neutral (track/neutral.npz), vertices (each ROM sequence's
track/<seq>/vertices.npz). output: marker_map (.json), rom_markers (.npz), metrics (fragment). params:
session_dir, track (params.track), take_markers (params.retarget.take_markers).
"""

from rigbuild.logs import run_logged
from rigbuild.retarget.stage import run_take_markers


def main(smk) -> None:
    i, o, prm = smk.input, smk.output, smk.params
    run_take_markers(i.performance, str(prm.session_dir), i.neutral, list(i.vertices), prm.get("track", None),
                     prm.get("take_markers", None), marker_map=o.marker_map, rom_markers=o.rom_markers,
                     metrics=o.metrics)


run_logged(snakemake, main)  # noqa: F821
