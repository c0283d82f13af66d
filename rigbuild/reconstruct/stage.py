"""Runners of the reconstruct rules (no ground truth here; see rules/eval_reconstruct.smk for that).

- ``reconstruct_frame`` (session x sequence x frame): :func:`run_reconstruct_frame` -> the frame's files
  (:mod:`rigbuild.reconstruct.sequence`) and its record ``frames/<frame>.json``.
- ``reconstruct_summary`` (session x sequence): :func:`run_reconstruct_summary` -> ``coverage.png``,
  ``renders/``, ``recon_summary.json`` and the fragment ``{"reconstruction": {"sequences": {<seq>: {...}}}}``.
- ``reconstruct_pool`` (session): :func:`run_reconstruct_pool` -> the session-level stage keys
  (``reconstruction.skipped_frames``, ``reconstruction.mean_coverage``, ``reconstruction.stereo_consistency_mm``)
  from the sequences' fragments.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.reconstruct.params import from_config

STAGE_KEY = "reconstruction"


def run_reconstruct_frame(session_dir: str | os.PathLike, sequence: str, frames: int | Sequence[int],
                          cameras_json: str | os.PathLike, params: Mapping[str, Any] | None,
                          out_dir: str | os.PathLike, threads: int | None = None,
                          log: Callable[[str], None] = print) -> list[dict]:
    """Reconstruct ``frames`` of one sequence into ``out_dir`` (``results/<s>/reconstruct/<seq>``); each
    frame's record (stats, skip reason) goes to ``out_dir/frames/<frame:06d>.json``.

    params : the raw ``config["params"]["reconstruct"]`` block; ``threads`` (the job's cores) is used
    unless the block sets ``threads``. Returns the records.
    """
    from rigbuild.io.atomic import write_json
    from rigbuild.io.cameras import read_cameras
    from rigbuild.progress import progress
    from rigbuild.reconstruct.sequence import match_cameras, process_frame
    from rigbuild.session import read_session

    values = dict(params or {})
    if threads is not None:
        values.setdefault("threads", int(threads))
    p = from_config(values)
    frames = [int(frames)] if np.isscalar(frames) else [int(f) for f in frames]
    spec = read_session(session_dir)
    seq = spec.sequence(sequence)
    cams = match_cameras(spec.cameras, spec.width, spec.height, read_cameras(cameras_json), str(cameras_json))
    bad = [f for f in frames if f not in seq.frames]
    if bad:
        raise InputError(f"frames {bad} are not in sequence {sequence} ({seq.start}..{seq.end})",
                         path=Path(session_dir) / "session.yaml")
    records = []
    for f in progress(frames, f"reconstructing {sequence}", total=len(frames), unit="frame"):
        rec = process_frame(f, [spec.rom_image(sequence, c.id, f) for c in cams], cams, p, out_dir, sequence, log)
        write_json(Path(out_dir) / "frames" / f"{f:06d}.json", rec)
        records.append(rec)
    return records


def sequence_metrics(summary: Mapping[str, Any]) -> dict[str, Any]:
    """``reconstruction.sequences.<seq>.*`` of one sequence summary (:func:`summarize_sequence`)."""
    return {"mean_coverage": summary["mean_coverage"], "stereo_consistency_mm": summary["stereo_consistency_mm"],
            "seconds_per_frame": summary["seconds_per_frame"], "frames": len(summary["frames"]),
            "skipped_frames": len(summary["skipped"])}


def run_reconstruct_summary(session_dir: str | os.PathLike, sequence: str,
                            frame_jsons: Sequence[str | os.PathLike], out_dir: str | os.PathLike,
                            fragment_path: str | os.PathLike) -> dict:
    """Frame records -> ``coverage.png``, ``renders/`` and ``recon_summary.json`` in ``out_dir``, and the fragment
    ``{"reconstruction": {"sequences": {<sequence>: sequence_metrics}}}`` at ``fragment_path``.
    Returns the summary."""
    from rigbuild.io.metrics import write_metrics_fragment
    from rigbuild.reconstruct.sequence import summarize_sequence
    from rigbuild.session import read_session

    spec = read_session(session_dir)
    records = [json.loads(Path(p).read_text()) for p in frame_jsons]
    summary = summarize_sequence(records, spec.cameras, out_dir, sequence, spec.sequence(sequence).neutral_frame)
    write_metrics_fragment(fragment_path, STAGE_KEY, {"sequences": {sequence: sequence_metrics(summary)}})
    return summary


def _number(v: Any) -> float:
    return float("nan") if v is None else float(v)


def pool_sequences(per_seq: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Session-level stage keys from the per-sequence values (in session order): total skipped frames,
    the mean of the sequences' mean coverage, and ``stereo_consistency_mm``, the worst (largest)
    sequence's (a gate: one bad sequence is not averaged away). NaN-skipping; a fragment stores NaN as null."""
    agree = [_number(v.get("stereo_consistency_mm")) for v in per_seq.values()]
    agree = [a for a in agree if np.isfinite(a)]
    return {"skipped_frames": int(sum(v.get("skipped_frames", 0) for v in per_seq.values())),
            "mean_coverage": float(np.nanmean([_number(v.get("mean_coverage")) for v in per_seq.values()])),
            "stereo_consistency_mm": float(max(agree)) if agree else float("nan")}


def run_reconstruct_pool(fragment_paths: Sequence[str | os.PathLike], out_path: str | os.PathLike) -> dict:
    """The sequences' summary fragments -> ``{"reconstruction": pool_sequences(...)}`` at ``out_path``."""
    from rigbuild.io.metrics import gather_metrics, write_metrics_fragment

    per_seq = gather_metrics(fragment_paths).get(STAGE_KEY, {}).get("sequences", {})
    return write_metrics_fragment(out_path, STAGE_KEY, pool_sequences(per_seq))[STAGE_KEY]
