"""Per-stage parameters: one typed definition per stage, used both at DAG start and by the stage's runner.

Each stage package has a ``params.py`` with dataclasses (defaults in the field definitions, nowhere else)
and a ``from_config(values)`` that builds them from ``config["params"][<stage>]``, raising
:class:`~rigbuild.errors.InputError` with the key, the allowed keys and a "did you mean" on a typo.
``rules/common.smk`` calls :func:`validate_params` on the whole ``params`` block before any job runs, so a
typo in ``params.track`` fails in seconds, not after hours of reconstruction.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import typing
from typing import Any, Iterable, Mapping

from rigbuild.errors import InputError

#: stage -> "module:function" building its typed parameters from the config block (imported lazily)
STAGE_PARAMS: dict[str, str] = {
    "calibrate": "rigbuild.calibrate.params:from_config",
    "reconstruct": "rigbuild.reconstruct.params:from_config",
    "track": "rigbuild.track.params:from_config",
    "personalize": "rigbuild.personalize.params:from_config",
    "retarget": "rigbuild.retarget.params:from_config",
    "report": "rigbuild.report.params:from_config",
}


def did_you_mean(key: str, allowed: Iterable[str]) -> str:
    """``" (did you mean 'x'?)"`` for the closest allowed key, or ``""``."""
    close = difflib.get_close_matches(str(key), [str(a) for a in allowed], n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def check_keys(values: Mapping[str, Any] | None, allowed: Iterable[str], where: str) -> None:
    """Raise InputError naming the first unknown key of ``values`` under ``where`` (``params.track``)."""
    allowed = sorted(str(a) for a in allowed)
    unknown = [str(k) for k in (values or {}) if str(k) not in allowed]
    if unknown:
        k = unknown[0]
        raise InputError(f"unknown key '{where}.{k}'{did_you_mean(k, allowed)}", path="config",
                         fix=f"keys of {where}: {', '.join(allowed)}")


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    """Lists from YAML become tuples where the field is a tuple; nested dataclasses are built."""
    origin = typing.get_origin(annotation)
    if dataclasses.is_dataclass(annotation) and isinstance(annotation, type):
        if not isinstance(value, Mapping):
            raise InputError(f"'{where}' must be a mapping of keys, got {value!r}", path="config")
        return from_mapping(annotation, value, where)
    if (annotation is tuple or origin is tuple) and isinstance(value, list):
        return tuple(value)
    if origin is typing.Union:  # Optional[...]: coerce against the non-None member
        members = [a for a in typing.get_args(annotation) if a is not type(None)]
        if value is not None and len(members) == 1:
            return _coerce(value, members[0], where)
    return value


def from_mapping(cls: type, values: Mapping[str, Any] | None, where: str) -> Any:
    """Build dataclass ``cls`` from a config mapping: unknown keys fail with "did you mean"; fields not given
    keep their defaults; nested dataclass fields take nested mappings."""
    values = dict(values or {})
    names = [f.name for f in dataclasses.fields(cls)]
    check_keys(values, names, where)
    hints = typing.get_type_hints(cls)
    return cls(**{k: _coerce(v, hints.get(k), f"{where}.{k}") for k, v in values.items()})


def load_from_config(stage: str):
    """The ``from_config`` function of a stage (see :data:`STAGE_PARAMS`)."""
    module, func = STAGE_PARAMS[stage].split(":")
    return getattr(importlib.import_module(module), func)


def validate_params(params: Mapping[str, Any] | None) -> dict[str, Any]:
    """Validate every ``config["params"]`` block at DAG start; returns stage -> typed parameters."""
    params = dict(params or {})
    check_keys(params, STAGE_PARAMS, "params")
    return {stage: load_from_config(stage)(params.get(stage) or {}) for stage in STAGE_PARAMS}


def as_dict(obj: Any) -> Any:
    """A parameters dataclass as plain JSON-able values (for the outputs that record what ran)."""
    return dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj
