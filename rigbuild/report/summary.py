"""The report's decision summary: one row per stage (pass / warn / fail, the number that matters, its limit).

Every stage has **gates**: metrics a stage computes without ground truth, so that a real capture is judged
(calibration's held-out reprojection, tracking's residual to the scan and lost frames, the rig's fit residual,
...). The other headline keys of a stage (:mod:`rigbuild.report.thresholds`) compare with ``ground_truth/`` and
exist for synthetic sessions only. A stage's status is the worst status over all its measured headline keys;
the session's verdict is the worst stage status. Nothing unmeasured counts as pass or fail: it is listed.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from rigbuild.report.thresholds import Rule, is_number, rule_for, split_headline, status

RANK = {"pass": 0, "warn": 1, "fail": 2}


@dataclass(frozen=True)
class Stage:
    """id: the report section; prefix: the metrics.json key; gates: metric keys (one ``*`` may stand for a
    sequence or character) judged without ground truth, the first measured one is the stage's number."""

    id: str
    title: str
    prefix: str
    gates: tuple[str, ...]


STAGES = (
    Stage("calibration", "Calibration", "calibration",
          ("calibration.heldout_reprojection_rms_px", "calibration.rms_px", "calibration.n_gate_failures",
           "calibration.n_plausibility_flags")),
    Stage("reconstruction", "Reconstruction", "reconstruction", ("reconstruction.stereo_consistency_mm",)),
    Stage("tracking", "Tracking", "tracking", ("tracking.sequences.*.median_residual_mm", "tracking.lost_frames")),
    Stage("personalization", "Personalization", "personalization",
          ("personalization.heldout_residual_final_mm", "personalization.residual_final_mm",
           "personalization.residual_reduction", "personalization.heldout_residual_reduction")),
    # retargeting's stage writes neither gate yet: the marker residual of the solve and the plausibility
    # numbers of rigbuild.retarget.plausible (antagonist pairs active together)
    Stage("retargeting", "Retargeting", "retarget",
          ("retarget.ribera.*.marker_residual_mm", "retarget.seol.*.marker_residual_mm",
           "retarget.ribera.*.antagonist_fraction", "retarget.seol.*.antagonist_fraction",
           "retarget.actor_rig_weights.marker_residual_mm")),
)


@dataclass
class Judged:
    """A measured metric with its status ("" when it has no limit) and limit."""

    key: str
    value: Any
    status: str
    rule: Rule | None


@dataclass
class StageSummary:
    """status: worst over gates and truth ("" when nothing with a limit was measured); number: the stage's
    number (first measured gate, else the worst ground-truth key); gates / truth: the measured keys of each
    kind (worst first within one gate pattern); missing_gates: gate patterns without a number."""

    stage: Stage
    status: str = ""
    number: Judged | None = None
    gates: list[Judged] = field(default_factory=list)
    truth: list[Judged] = field(default_factory=list)
    missing_gates: list[str] = field(default_factory=list)


def worst(statuses: Sequence[str]) -> str:
    """The worst of pass / warn / fail; "" for none."""
    marked = [s for s in statuses if s in RANK]
    return max(marked, key=RANK.__getitem__) if marked else ""


def beyond(j: Judged) -> float:
    """How far a value is past its pass limit, relative (> 1: beyond it): value / limit for ``max`` rules,
    limit / value for ``min`` rules (comparable across metrics of one status); 0 without a rule."""
    if j.rule is None or not is_number(j.value):
        return 0.0
    direction, ok, _ = j.rule
    v, ok = abs(float(j.value)), abs(float(ok))
    tiny = 1e-12
    return v / max(ok, tiny) if direction == "max" else ok / max(v, tiny)


def _badness(j: Judged) -> tuple:
    """Sort key: worse status first, then further beyond its pass limit."""
    return (-RANK.get(j.status, -1), -beyond(j))


def judge(flat: Mapping[str, Any], pattern: str, thresholds: Mapping | None = None) -> list[Judged]:
    """The keys of ``flat`` matching ``pattern`` with a number, judged, worst first."""
    keys = [pattern] if "*" not in pattern else sorted(k for k in flat if fnmatch.fnmatchcase(k, pattern))
    out = [Judged(k, flat[k], status(k, flat[k], thresholds), rule_for(k, thresholds))
           for k in keys if is_number(flat.get(k))]
    return sorted(out, key=_badness)


def is_gate(key: str, stage: Stage) -> bool:
    return any(fnmatch.fnmatchcase(key, g) for g in stage.gates)


def summarize_stage(flat: Mapping[str, Any], stage: Stage, thresholds: Mapping | None = None) -> StageSummary:
    """One stage's summary row from flat metrics."""
    s = StageSummary(stage)
    for g in stage.gates:
        got = judge(flat, g, thresholds)
        s.gates += got
        if not got:
            s.missing_gates.append(g)
    own = {k: v for k, v in flat.items() if k.startswith(stage.prefix + ".") and not is_gate(k, stage)}
    head, _ = split_headline(own, thresholds)
    s.truth = sorted((j for k in head for j in judge(flat, k, thresholds)), key=_badness)
    s.status = worst([j.status for j in s.gates + s.truth])
    s.number = s.gates[0] if s.gates else (s.truth[0] if s.truth else None)
    return s


def summarize(flat: Mapping[str, Any], thresholds: Mapping | None = None,
              stages: Sequence[Stage] = STAGES) -> tuple[list[StageSummary], str]:
    """(one :class:`StageSummary` per stage, the session verdict: worst stage status, "" if none measured)."""
    rows = [summarize_stage(flat, st, thresholds) for st in stages]
    return rows, worst([r.status for r in rows])


def counts(judged: Sequence[Judged]) -> dict[str, int]:
    """pass / warn / fail counts of judged keys."""
    return {s: sum(1 for j in judged if j.status == s) for s in RANK}
