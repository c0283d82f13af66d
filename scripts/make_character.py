"""Snakemake entry point: build one character rig (rigbuild.synth.characters.make_character)."""

from rigbuild.io.rigs import load_rig, write_rig_npz
from rigbuild.logs import run_logged
from rigbuild.paths import ict_dir
from rigbuild.synth.characters import make_character


def main(snakemake):
    cfg = snakemake.params.character
    rig = load_rig(cfg["rig"])
    if cfg.get("markers"):
        import json

        from rigbuild.errors import InputError

        with open(cfg["markers"]) as fh:
            markers = json.load(fh)
        markers = markers.get("markers", markers)
        bad = [n for n, v in markers.items() if not 0 <= int(v) < rig.n_vertices]
        if bad:
            raise InputError(f"markers {bad} index vertices outside the rig", path=cfg["markers"])
        rig = rig.with_markers(list(markers), list(markers.values()))
    identity_folder = ict_dir() if cfg["rig"] == "ict" else None
    character = make_character(rig, cfg.get("kind", "template"), seed=0, identity_folder=identity_folder)
    character.name = snakemake.wildcards.character
    write_rig_npz(snakemake.output.rig, character)
    print(f"character {character.name}: {character.n_vertices} vertices, {character.n_shapes} shapes, "
          f"{len(character.marker_names)} markers")


run_logged(snakemake, main)  # noqa: F821
