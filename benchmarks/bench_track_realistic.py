"""Benchmark of issue 20: tracking on the realistic capture world, per level and per option, against ground truth.

Scenes: the first two ROM sequences (rom00, rom01; 15 frames each; ``--sequences`` picks others, for example
the mouth-opening ones) of a realistic ICT tier exactly as the tier has them (``ict_dev``: config/ict-dev.yaml,
seed 21, the development actor; ``ict``: config/ict.yaml, seed 11, never tuned on; the tier's ``synthetic:`` block
with ``rom.render_sequences`` set: hand-painted dots 2 mm off their stencil sites, realistic skin, studio lights,
Bayer, JPEG, motion blur, depth of field), generated once and cached in benchmarks/out/cache. Every frame is
reconstructed once with the ground-truth cameras and the tiers' ``params.reconstruct`` (cached beside the scene),
so calibration error is left out and every variant tracks the same depth maps. As in the pipeline, the template
is registered on the first rendered sequence's neutral frame, which is every sequence's anchor, and each sequence
is tracked from its own neutral frame.

A variant is a ``params.track`` block merged over the tier config's; always measured:

- ``config``: the tier's own tracking (landmark registration, dots + SIFT + dense flow);
- ``dots``: the dot level alone (``levels: [features]``); ``dots+sift``: ``[features, sparse]``;
- ``unpainted``: the unpainted-face path on the same images (landmarks, SIFT and flow; the dots ignored).

Metrics (rigbuild.eval.tracking.ground_truth_tracking_metrics, the pipeline's evaluation of the whole face mask):
``neutral_error_mm`` (the registration), ``mean_error_mm``, ``p95_error_mm``, ``end_drift_mm``, their ``visible_``
forms, ``corr_mean_error_mm`` (tracking with the registration's tangential error taken out), lips and eyelids,
per-frame means; seconds of the registration and per tracked frame (2 worker threads, in this process).

The dot-placement sweep (``--dot-sweep [SD_MM ...]``, default 0 1 2 4): the tier's own tracking on the same
session (same seed, actor, ROM and images but the dots) with the painted dots placed off their stencil sites by
each standard deviation; the generated sessions are cached beside the tier's.

Run: ``.venv/bin/python benchmarks/bench_track_realistic.py [--scenes ict_dev ict] [--variant NAME=JSON ...]
[--only NAME ...] [--dot-sweep [SD_MM ...]] [--sequences I ...] [--out NAME]``; writes
``benchmarks/out/track_realistic.json`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from bench_reconstruct_realistic import TIERS  # noqa: E402
from common import CACHE, _git, cached_session, print_table, write_result  # noqa: E402

from rigbuild.synth.session import _merge as merge  # noqa: E402  (the config blocks' deep merge)
RENDERED = [0, 1]
BUILTIN = {"config": {}, "dots": {"levels": ["features"]}, "dots+sift": {"levels": ["features", "sparse"]},
           "unpainted": "unpainted"}
DOT_SWEEP_MM = (0.0, 1.0, 2.0, 4.0)
KEYS = ("neutral_error_mm", "mean_error_mm", "p95_error_mm", "end_drift_mm", "visible_mean_error_mm",
        "corr_mean_error_mm", "lips_mean_error_mm", "eyelids_mean_error_mm")


def tier_scene(name: str, dot_sd: float | None = None) -> Path:
    """The tier's ROM sequences :data:`RENDERED`, as the tier has them (generated once, cached; a folder per
    sequence set); ``dot_sd``: the same session with the painted dots placed off their stencil sites by this
    standard deviation (mm) instead."""
    import yaml

    from rigbuild.synth.session import generate_session

    cfg_file, session = TIERS[name]
    syn = copy.deepcopy(yaml.safe_load((ROOT / cfg_file).read_text())["sessions"][session]["synthetic"])
    syn["calib_poses"] = 2
    syn["rom"]["render_sequences"] = RENDERED
    syn["performance"]["duration_s"] = 1.0
    folder = CACHE / (f"track_{name}" + ("" if RENDERED == [0, 1] else "_rom" + "_".join(map(str, RENDERED))))
    if dot_sd is not None and dot_sd != syn.get("dot_placement_sd_mm"):
        syn["dot_placement_sd_mm"] = float(dot_sd)
        folder = folder.with_name(f"{folder.name}_dots{dot_sd:g}")
    return cached_session(folder, syn, lambda out: generate_session(out, name, syn, progress=print))


def tier_params(name: str) -> dict:
    """The tier's merged ``params`` block (config/config.yaml, then the tier's file)."""
    import yaml

    base = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["params"]
    return merge(base, yaml.safe_load((ROOT / TIERS[name][0]).read_text()).get("params", {}))


def depth_folders(name: str, reconstruct: dict, dot_sd: float | None = None) -> dict[str, Path]:
    """Depth maps of every frame of the scene's sequences (name -> folder), reconstructed with the ground-truth
    cameras and ``reconstruct`` (cached beside the scene, keyed by the block and the git tree of
    rigbuild/reconstruct)."""
    from rigbuild.io.cameras import read_cameras
    from rigbuild.reconstruct.params import from_config
    from rigbuild.reconstruct.sequence import process_frame
    from rigbuild.session import read_session

    sess = tier_scene(name, dot_sd)
    out = sess / "bench_depth"
    key = json.dumps({"reconstruct": reconstruct, "source": _git("rev-parse", "HEAD:rigbuild/reconstruct")},
                     sort_keys=True)
    stamp = out / "key.json"
    spec = read_session(sess)
    folders = {seq.name: out / seq.name / "depth" for seq in spec.rom}
    if stamp.exists() and stamp.read_text() == key:
        return folders
    cams = read_cameras(sess / "ground_truth" / "cameras.json")
    params = from_config({**reconstruct, "threads": 2})
    for seq in spec.rom:
        for f in seq.frames:
            process_frame(f, [spec.rom_image(seq.name, c.id, f) for c in cams], cams, params, out / seq.name,
                          name=f"{name} {seq.name}")
    stamp.write_text(key)
    return folders


def measure(name: str, block, base: dict, dot_sd: float | None = None) -> dict:
    """Register and track the scene's sequences (``dot_sd``: :func:`tier_scene`'s) with the tier's
    ``params.track`` merged with ``block`` ("unpainted": the unpainted path); the pipeline's ground-truth metrics
    and timings."""
    from rigbuild.dots import painted_dot_vertices
    from rigbuild.eval.tracking import contour_regions, ground_truth_tracking_metrics
    from rigbuild.io.cameras import read_cameras
    from rigbuild.io.rigs import load_rig
    from rigbuild.session import read_session
    from rigbuild.track.params import from_config, unpainted
    from rigbuild.track.stage import load_views, track_neutral_frame, track_rom_sequence

    sess = tier_scene(name, dot_sd)
    depth = depth_folders(name, base.get("reconstruct", {}), dot_sd)
    spec = read_session(sess)
    cams_path = sess / "ground_truth" / "cameras.json"
    cams = read_cameras(cams_path)
    tp = from_config(merge(base.get("track", {}), {} if block == "unpainted" else block))
    if block == "unpainted":
        tp = unpainted(tp)
    tp.workers = 2
    template = load_rig(tp.template_for(spec))
    dot_vertices = painted_dot_vertices(template, spec.dot_stencil_mm)
    cells: dict = {}
    first = spec.rom[0]
    anchor = load_views(spec, cams, first.name, first.neutral_frame, depth[first.name], cells)
    t0 = time.perf_counter()
    reg, _ = track_neutral_frame(template, anchor, tp, dot_vertices=dot_vertices)
    t_reg = time.perf_counter() - t0
    dot_surface = None if reg.dot_surface is None else (reg.dot_surface[0], reg.dot_surface[1])
    tracked, lost, t_track, n_frames = {}, 0, 0.0, 0
    for seq in spec.rom:
        ids = [f for f in seq.frames if f >= seq.neutral_frame]
        views = [load_views(spec, cams, seq.name, f, depth[seq.name], cells) for f in ids]
        t0 = time.perf_counter()
        V, _, _, stats = track_rom_sequence(template, reg.vertices, anchor, views, ids, seq.name, tp,
                                            dot_vertices=dot_vertices, dot_surface=dot_surface)
        t_track += time.perf_counter() - t0
        n_frames += len(ids)
        lost += int(sum(s.lost for s in stats))
        tracked[seq.name] = (V.astype(np.float64), np.asarray(ids))
    regions = contour_regions(template.neutral, template.landmarks, template.face_vertices)
    values, per = ground_truth_tracking_metrics(sess / "ground_truth", cams_path, template.faces,
                                                template.face_vertices, reg.vertices,
                                                (first.name, first.neutral_frame), tracked, regions=regions)
    out = {k: float(values[k]) for k in KEYS if k in values}
    out["per_frame_mean_mm"] = {k: [round(float(x), 4) for x in d["per_frame_mean_mm"]] for k, d in per.items()}
    out["per_frame_corr_mean_mm"] = {k: [round(float(x), 4) for x in d["corr_per_frame_mean_mm"]]
                                     for k, d in per.items()}
    out.update(registration_seconds=t_reg, seconds_per_frame=t_track / n_frames, lost_frames=lost, params=block)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(TIERS), choices=list(TIERS))
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=JSON",
                    help="a params.track block merged over the tier's (repeatable)")
    ap.add_argument("--only", nargs="*", help="measure only these variants (none: only the dot sweep)")
    ap.add_argument("--dot-sweep", nargs="*", type=float, metavar="SD_MM",
                    help="also the dot-placement sweep: the tier's tracking on the same session with the dots "
                         f"placed off their stencil sites by these standard deviations (default {DOT_SWEEP_MM})")
    ap.add_argument("--sequences", nargs="+", type=int, default=RENDERED, metavar="I",
                    help=f"the tier's ROM sequences to render and track (default {RENDERED}; the first one's neutral "
                         "is the registration's)")
    ap.add_argument("--out", default="track_realistic")
    a = ap.parse_args()
    RENDERED[:] = a.sequences
    variants: dict = dict(BUILTIN)
    for v in a.variant:
        k, _, js = v.partition("=")
        variants[k] = json.loads(js)
    if a.only is not None:
        variants = {k: variants[k] for k in a.only}
    result: dict = {"rendered_sequences": RENDERED, "scenes": {}}
    rows = []
    for name in a.scenes:
        base = tier_params(name)
        result["scenes"][name] = {"config": TIERS[name][0], "variants": {}}
        for vname, block in variants.items():
            r = measure(name, block, base)
            result["scenes"][name]["variants"][vname] = r
            rows.append({"scene": name, "variant": vname, **{k: r.get(k) for k in (*KEYS, "seconds_per_frame")}})
            print_table(rows[-1:], list(rows[-1]))
    if a.dot_sweep is not None:
        result["dot_sweep"] = {}
        for name in a.scenes:
            base = tier_params(name)
            result["dot_sweep"][name] = {}
            for sd in a.dot_sweep or DOT_SWEEP_MM:
                r = measure(name, {}, base, dot_sd=sd)
                result["dot_sweep"][name][f"{sd:g}"] = r
                rows.append({"scene": name, "variant": f"dots sd {sd:g} mm",
                             **{k: r.get(k) for k in (*KEYS, "seconds_per_frame")}})
                print_table(rows[-1:], list(rows[-1]))
    print_table(rows, ["scene", "variant", *KEYS, "seconds_per_frame"])
    write_result(a.out, result)


if __name__ == "__main__":
    main()
