"""``config["params"]["report"]``: the report's parameters (pass / warn / fail limits over the defaults).

Limits come in three layers, later ones winning key by key: the defaults
(:data:`rigbuild.report.thresholds.DEFAULT_THRESHOLDS`), ``thresholds`` (the config's: a tier's config file
sets its tier's limits) and ``sessions.<session>.thresholds`` (one session's). A layer may tighten or loosen a
limit; the page shows every limit it applied beside its value.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from rigbuild.errors import InputError
from rigbuild.params import check_keys, from_mapping


@dataclass
class ReportParams:
    """thresholds : metric key (one ``*`` may stand for a sequence or character) -> [direction, pass, warn],
    where direction is ``max`` (a value <= pass passes) or ``min``; overrides
    :data:`rigbuild.report.thresholds.DEFAULT_THRESHOLDS`.
    sessions : session name -> ``{thresholds: {...}}``, that session's limits over ``thresholds``.
    image_width : width in px of the pictures embedded as JPEG (downscaled, never upscaled).
    jpeg_quality : their JPEG quality (1-100).
    inline_limit_mb : above this page size the 3D view's data and three.js go to ``report_files/`` beside it."""

    thresholds: dict[str, Any] = field(default_factory=dict)
    sessions: dict[str, Any] = field(default_factory=dict)
    image_width: int = 560
    jpeg_quality: int = 80
    inline_limit_mb: float = 5.0

    def for_session(self, session: str) -> dict[str, tuple]:
        """The overrides for ``session``: the config's thresholds with the session's own over them."""
        return {**self.thresholds, **self.sessions.get(session, {}).get("thresholds", {})}


def _checked(rules: Any, where: str) -> dict[str, tuple]:
    if not isinstance(rules, Mapping):
        raise InputError(f"{where} must be a mapping metric key -> [max|min, pass, warn], got {rules!r}", path="config")
    for key, rule in rules.items():
        ok = (isinstance(rule, (list, tuple)) and len(rule) == 3 and rule[0] in ("max", "min")
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in rule[1:]))
        if not ok:
            raise InputError(f"{where}.{key} is {rule!r}", path="config",
                             fix="give [max|min, pass_value, warn_value], e.g. [max, 0.2, 0.5]")
    return {k: tuple(v) for k, v in rules.items()}


def from_config(values: Mapping[str, Any] | None) -> ReportParams:
    p = from_mapping(ReportParams, values, "params.report")
    p.thresholds = _checked(p.thresholds, "params.report.thresholds")
    if not isinstance(p.sessions, Mapping):
        raise InputError(f"params.report.sessions must be a mapping session -> {{thresholds: ...}}, got "
                         f"{p.sessions!r}", path="config")
    sessions = {}
    for name, entry in p.sessions.items():
        where = f"params.report.sessions.{name}"
        if not isinstance(entry, Mapping):
            raise InputError(f"{where} must be a mapping {{thresholds: ...}}, got {entry!r}", path="config")
        check_keys(entry, ["thresholds"], where)
        sessions[str(name)] = {"thresholds": _checked(entry.get("thresholds", {}), f"{where}.thresholds")}
    p.sessions = sessions
    if not (isinstance(p.image_width, int) and p.image_width >= 64):
        raise InputError(f"params.report.image_width is {p.image_width!r}", path="config", fix="give a width >= 64 px")
    if not (isinstance(p.jpeg_quality, int) and 1 <= p.jpeg_quality <= 100):
        raise InputError(f"params.report.jpeg_quality is {p.jpeg_quality!r}", path="config", fix="give 1-100")
    if not (isinstance(p.inline_limit_mb, (int, float)) and p.inline_limit_mb > 0):
        raise InputError(f"params.report.inline_limit_mb is {p.inline_limit_mb!r}", path="config",
                         fix="give a size in MB > 0")
    return p
