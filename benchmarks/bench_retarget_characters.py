"""Benchmark of issue 23: Ribera's retargeting onto characters the method was not built around, without tracking.

Per tier (``ict_dev``: config/ict-dev.yaml, the development actor of the ICT world; ``ict``: config/ict.yaml, its
acceptance actor; ``demo_dev`` / ``demo``: the demo world's, config/demo-dev.yaml and config/config.yaml):

- the session's actor, performance (hand-placed markers, occlusion gaps, noise, head motion) and true weights exactly
  as the session generator writes them (:func:`rigbuild.synth.session.generate_mocap_only`: no images);
- its range of motion: the tier's ROM weights (the generator's seed), head motion of the tier's range, read at the
  performance's hand-placed marker points (where rule ``take_markers`` reads the tracked ROM) with
  ``--rom-noise-mm`` of Gaussian noise standing in for the tracking (real tracking error is correlated in space and
  time and larger at the lips: this scene separates the method from the tracking, it does not replace a tier run);
- the characters of the tier's ``characters`` block (template, exaggerated, stylized, sculpted, another topology).

Methods, through the pipeline's library path (:func:`rigbuild.retarget.run.retarget_performance` with
config/config.yaml's ``params.retarget.ribera``): ``ribera_fit`` (guesses from the character), ``ribera_fit_template_rig``
(guesses from the template rig at the markers), ``deformation`` (the deformation-transfer guesses used directly) and
``ribera_fit_actor_rig`` given the actor's true rig (``true_rig``: the ceiling of the rig-guess methods, what a
perfect personalization would give). Metrics: mean per-shape correlation and weight MAE against the true weights
(:func:`rigbuild.eval.retarget.retarget_metrics`).

Run: ``.venv/bin/python benchmarks/bench_retarget_characters.py [--scenes ict_dev ict demo_dev demo]
[--rom-noise-mm 0.5]``;
writes ``benchmarks/out/retarget_characters.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from common import CACHE, cached_session, print_table, write_result  # noqa: E402

TIERS = {"ict_dev": ("config/ict-dev.yaml", "ict_dev"), "ict": ("config/ict.yaml", "ict"),
         "demo_dev": ("config/demo-dev.yaml", "demo_dev"), "demo": ("config/config.yaml", "demo")}
METHODS = ("ribera_fit", "ribera_fit_template_rig", "deformation", "true_rig")


def tier_block(name: str) -> tuple[dict, dict, str]:
    """(synthetic block, characters block, session name) of a tier config (its characters, else config.yaml's, as
    Snakemake merges a ``--configfile`` over config/config.yaml)."""
    import yaml

    cfg_file, session = TIERS[name]
    cfg = yaml.safe_load((ROOT / cfg_file).read_text())
    base = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    return copy.deepcopy(cfg["sessions"][session]["synthetic"]), cfg.get("characters") or base["characters"], session


def rom_at_take_markers(actor, p: dict, placement, noise_mm: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The tier's ROM (weights per sequence, :func:`rigbuild.synth.motion.make_rom_weights` with the generator's
    seed) read at the take's marker points ``placement``: (markers (F, M, 3) mm per sequence, weights)."""
    from rigbuild.synth.markers import performance_markers
    from rigbuild.synth.motion import make_head_motion, make_rom_weights

    seed, rom = int(p["seed"]), p["rom"]
    holds = None if rom["hold_frames"] is None else tuple(int(x) for x in rom["hold_frames"])
    seqs = make_rom_weights(actor.shape_names, int(rom["n_sequences"]), int(rom["frames_per_sequence"]), seed=seed + 2,
                            coverage=int(rom["coverage"]), peak_range=tuple(float(x) for x in rom["peak_range"]),
                            hold_frames=holds)
    markers = []
    for s, W in enumerate(seqs):
        R, t = make_head_motion(W.shape[0], seed=seed + 100 + s, max_rotation_deg=float(rom["max_rotation_deg"]),
                                max_translation_mm=float(rom["max_translation_mm"]))
        markers.append(performance_markers(actor, W, R, t, placement, None, noise_mm=noise_mm, seed=seed + 900 + s))
    return markers, seqs


def scene(name: str, rom_noise_mm: float) -> dict:
    """The tier's mocap-only session (cached) with its ROM at the take's markers and the template rig there."""
    from rigbuild.io.markers import read_markers
    from rigbuild.io.rigs import read_rig_npz
    from rigbuild.retarget.actor_rig import MarkerMap, sample_rig_at_markers
    from rigbuild.retarget.ribera import RigAtMarkers
    from rigbuild.synth.dots import place_painted_dots
    from rigbuild.synth.session import generate_mocap_only, synth_params

    syn, characters, session = tier_block(name)
    folder = cached_session(CACHE / f"mocap_{name}", syn, lambda out: generate_mocap_only(out, session, syn))
    p = synth_params(syn)
    gt = folder / "ground_truth"
    actor, template = read_rig_npz(gt / "actor_rig.npz"), read_rig_npz(gt / "template_rig.npz")
    take = read_markers(folder / "performances" / "perf00.c3d")
    with np.load(gt / "performances" / "perf00.npz") as z:
        weights, truth_names = z["weights"].astype(np.float64), [str(n) for n in z["shape_names"]]
    # the take's marker points: the generator's hand placement of perf00 (rigbuild.synth.session._hand_placed_markers)
    placement = place_painted_dots(actor, actor.marker_vertices, sigma_mm=float(p["performance"]["marker_placement_sd_mm"]),
                                   missing_fraction=0.0, seed=int(p["seed"]) + 800)
    rom, rom_weights = rom_at_take_markers(actor, p, placement, rom_noise_mm)
    mmap = MarkerMap(list(actor.marker_names), placement.triangles, placement.bary, np.zeros(len(placement.triangles)))
    rigs = {}
    for label, rig in (("template_rig", template), ("true_rig", actor)):
        b0, D = sample_rig_at_markers(rig.neutral, rig.deltas, rig.faces, mmap)
        rigs[label] = RigAtMarkers(b0, D, list(actor.marker_names), list(rig.shape_names))
    return {"actor": actor, "take": take, "weights": weights, "truth_names": truth_names, "rom": rom,
            "rom_weights": rom_weights, "rigs": rigs, "characters": characters}


def make_characters(block: dict) -> dict:
    """The tier's characters as rule ``character_rig`` builds them (mm)."""
    from rigbuild.io.rigs import load_rig
    from rigbuild.paths import ict_dir
    from rigbuild.synth.characters import make_character

    out = {}
    for name, c in block.items():
        ch = make_character(load_rig(c["rig"]), c.get("kind", "template"), seed=0,
                            identity_folder=ict_dir() if c["rig"] == "ict" else None)
        out[name] = ch if ch.units == "mm" else ch.to_units("mm")
    return out


def measure(sc: dict) -> list[dict]:
    import yaml

    from rigbuild.eval.retarget import retarget_metrics
    from rigbuild.retarget.methods import RIBERA_ACTOR_RIG_METHOD
    from rigbuild.retarget.params import ribera_from_config
    from rigbuild.retarget.run import make_training_set, retarget_performance

    p = ribera_from_config(yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["params"]["retarget"]["ribera"])
    names = list(sc["actor"].marker_names)
    ts = make_training_set(sc["rom"], [names] * len(sc["rom"]), [0] * len(sc["rom"]))
    take = sc["take"]
    actor_sparse = sc["actor"].deltas[:, sc["actor"].marker_vertices]
    rows = []
    for cname, ch in make_characters(sc["characters"]).items():
        for label in METHODS:
            method = RIBERA_ACTOR_RIG_METHOD if label == "true_rig" else label
            rig = sc["rigs"].get("true_rig" if label == "true_rig" else "template_rig") \
                if method in ("ribera_fit_template_rig", RIBERA_ACTOR_RIG_METHOD) else None
            t0 = time.perf_counter()
            res = retarget_performance(ts, take.markers, take.names, ch, ch.marker_names, ch.marker_vertices, method,
                                       p.transfer_params(method), p.retarget_params(method), workers=1,
                                       marker_lowpass_hz=p.marker_lowpass_hz, fps=take.fps, actor_rig=rig)
            met = retarget_metrics(res.weights, res.shape_names, sc["weights"], sc["truth_names"], actor_sparse)
            rows.append({"character": cname, "method": label, "mean_correlation": met["mean_correlation"],
                         "weight_mae": met["weight_mae"], "seconds": time.perf_counter() - t0})
            print(f"  {cname} {label}: correlation {met['mean_correlation']:.3f} MAE {met['weight_mae']:.3f}",
                  flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(TIERS), choices=list(TIERS))
    ap.add_argument("--rom-noise-mm", type=float, default=0.5)
    ap.add_argument("--out", default="retarget_characters")
    args = ap.parse_args()
    from rigbuild.paths import ict_dir

    if not (ict_dir() / "generic_neutral_mesh.obj").exists():
        sys.exit(f"bench_retarget_characters: ICT-FaceKit not found at {ict_dir()} (set RIGBUILD_DATA)")
    results = {"rom_noise_mm": args.rom_noise_mm, "methods": list(METHODS), "scenes": {}}
    for name in args.scenes:
        print(f"== {name}", flush=True)
        results["scenes"][name] = measure(scene(name, args.rom_noise_mm))
    write_result(args.out, results)
    rows = [{"scene": s, **r} for s, rs in results["scenes"].items() for r in rs]
    print_table(rows, ["scene", "character", "method", "mean_correlation", "weight_mae", "seconds"])


if __name__ == "__main__":
    main()
