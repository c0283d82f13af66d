"""A small reader for marker (locator) animation in Maya ASCII scenes (``.ma``).

Reads transforms whose ``translateX/Y/Z`` are driven by ``animCurveTL`` nodes (``setAttr ".ktv[a:b]" t0 v0
t1 v1 ...`` key lists, connected by ``connectAttr "<curve>.o" "<node>.tx"``), applies the static
translate / rotate (xyz order) / scale of their parent transforms, and converts the scene's linear unit
(``currentUnit -l``) to mm and its time unit (``currentUnit -t``) to seconds. This is what the AnimFace
motion-capture scenes contain (41 locators under a ``MoCapData`` group, cm, keys every 0.4 film frames = 60 Hz).
Only linear key values are used (no tangent evaluation): mocap keys are dense samples.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rigbuild.errors import InputError

LINEAR_TO_MM = {"mm": 1.0, "millimeter": 1.0, "cm": 10.0, "centimeter": 10.0, "m": 1000.0, "meter": 1000.0,
                "in": 25.4, "inch": 25.4, "ft": 304.8, "foot": 304.8, "yd": 914.4, "yard": 914.4}
TIME_FPS = {"game": 15.0, "film": 24.0, "pal": 25.0, "ntsc": 30.0, "show": 48.0, "palf": 50.0, "ntscf": 60.0,
            "hour": 1 / 3600.0, "min": 1 / 60.0, "sec": 1.0, "millisec": 1000.0}

_STATEMENT = re.compile(r'((?:[^;"]|"(?:\\.|[^"\\])*")*);')
_NAME = re.compile(r'-n\s+"([^"]+)"')
_PARENT = re.compile(r'-p\s+"([^"]+)"')
_KTV = re.compile(r'setAttr\s+(?:-s\s+\d+\s+)?"\.ktv\[(\d+)(?::(\d+))?\]"\s+(.*)', re.S)
_DOUBLE3 = re.compile(r'setAttr\s+"\.(t|r|s)"\s+-type\s+"double3"\s+(\S+)\s+(\S+)\s+(\S+)')
_CONNECT = re.compile(r'connectAttr\s+"([^"]+)\.o(?:utput)?"\s+"([^"]+)\.(tx|ty|tz|translateX|translateY|translateZ)"')
_UNIT_L = re.compile(r'currentUnit\b.*?-l(?:inear)?\s+(\w+)')
_UNIT_T = re.compile(r'currentUnit\b.*?-t(?:ime)?\s+(\w+)')


@dataclass
class _Transform:
    name: str
    parent: str | None
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    r: np.ndarray = field(default_factory=lambda: np.zeros(3))
    s: np.ndarray = field(default_factory=lambda: np.ones(3))

    def matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """(A, b): local -> parent space ``A x + b`` (scale, then rotate x, y, z, then translate)."""
        rx, ry, rz = np.radians(self.r)
        Rx = np.array([[1, 0, 0], [0, np.cos(rx), -np.sin(rx)], [0, np.sin(rx), np.cos(rx)]])
        Ry = np.array([[np.cos(ry), 0, np.sin(ry)], [0, 1, 0], [-np.sin(ry), 0, np.cos(ry)]])
        Rz = np.array([[np.cos(rz), -np.sin(rz), 0], [np.sin(rz), np.cos(rz), 0], [0, 0, 1]])
        return Rz @ Ry @ Rx @ np.diag(self.s), self.t.copy()


@dataclass
class LocatorTake:
    """markers (F, M, 3) mm (NaN where a locator has no key at a frame time); names (M,); fps; times (F,) s."""

    markers: np.ndarray
    names: list[str]
    fps: float
    times: np.ndarray


def read_maya_locator_animation(path: str | os.PathLike, group: str | None = None) -> LocatorTake:
    """Read the animated locators of a Maya ASCII scene.

    Parameters
    ----------
    path : the ``.ma`` file.
    group : only locators under this transform (e.g. ``"MoCapData"``); default: every transform with
        animated translateX/Y/Z.

    Returns
    -------
    :class:`LocatorTake` in mm; frame times are the union of key times; fps = 1 / median key spacing.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("Maya ASCII file not found", path=path)
    text = path.read_text(encoding="utf-8", errors="replace")
    if not text.lstrip().startswith("//Maya ASCII"):
        raise InputError("not a Maya ASCII scene (no '//Maya ASCII' header)", path=path,
                         fix="export the scene as Maya ASCII (.ma)")
    to_mm, time_fps = 10.0, 24.0  # Maya defaults: cm, film
    transforms: dict[str, _Transform] = {}
    curves: dict[str, list[np.ndarray]] = {}
    links: dict[tuple[str, int], str] = {}
    current: tuple[str, str] | None = None
    for m in _STATEMENT.finditer(text):
        st = m.group(1).strip()
        if st.startswith("//"):
            st = "\n".join(line for line in st.splitlines() if not line.lstrip().startswith("//")).strip()
        if st.startswith("currentUnit"):
            ul, ut = _UNIT_L.search(st), _UNIT_T.search(st)
            if ul:
                if ul.group(1) not in LINEAR_TO_MM:
                    raise InputError(f"unknown linear unit '{ul.group(1)}'", path=path)
                to_mm = LINEAR_TO_MM[ul.group(1)]
            if ut:
                u = ut.group(1)
                fps_m = re.fullmatch(r"(\d+(?:\.\d+)?)fps", u)
                if fps_m:
                    time_fps = float(fps_m.group(1))
                elif u in TIME_FPS:
                    time_fps = TIME_FPS[u]
                else:
                    raise InputError(f"unknown time unit '{u}'", path=path)
        elif st.startswith("createNode"):
            kind = st.split()[1]
            nm = _NAME.search(st)
            name = nm.group(1) if nm else ""
            current = (kind, name)
            if kind == "transform":
                pm = _PARENT.search(st)
                transforms[name] = _Transform(name, pm.group(1) if pm else None)
            elif kind.startswith("animCurveT"):
                curves[name] = []
        elif st.startswith("setAttr") and current is not None:
            kind, name = current
            if kind.startswith("animCurveT"):
                km = _KTV.match(st)
                if km:
                    vals = np.array(km.group(3).split(), dtype=np.float64)
                    curves[name].append(vals.reshape(-1, 2))
            elif kind == "transform":
                dm = _DOUBLE3.match(st)
                if dm:
                    setattr(transforms[name], dm.group(1), np.array([float(dm.group(i)) for i in (2, 3, 4)]))
        elif st.startswith("connectAttr"):
            cm = _CONNECT.match(st)
            if cm and cm.group(1) in curves:
                axis = {"tx": 0, "ty": 1, "tz": 2, "translateX": 0, "translateY": 1, "translateZ": 2}[cm.group(3)]
                links[(cm.group(2).split("|")[-1], axis)] = cm.group(1)

    def under_group(name: str) -> bool:
        node = transforms.get(name)
        while node is not None and node.parent is not None:
            if node.parent.split("|")[-1] == group:
                return True
            node = transforms.get(node.parent.split("|")[-1])
        return False

    names = [n for n in transforms if all((n, a) in links for a in range(3)) and (group is None or under_group(n))]
    if not names:
        raise InputError("no transforms with animated translateX/Y/Z found" + (f" under '{group}'" if group else ""),
                         path=path, fix="check the group name; markers must be keyed with animCurveTL nodes")
    keys = {(n, a): np.concatenate(curves[links[(n, a)]]) if curves[links[(n, a)]] else np.zeros((0, 2))
            for n in names for a in range(3)}
    all_t = np.unique(np.round(np.concatenate([k[:, 0] for k in keys.values()]), 6))
    F, M = all_t.size, len(names)
    local = np.full((F, M, 3), np.nan)
    for j, n in enumerate(names):
        for a in range(3):
            k = keys[(n, a)]
            pos = np.searchsorted(all_t, np.round(k[:, 0], 6))
            local[pos, j, a] = k[:, 1]
    world = local.copy()
    for j, n in enumerate(names):
        parent = transforms[n].parent
        while parent is not None:
            node = transforms.get(parent.split("|")[-1])
            if node is None:
                break
            A, b = node.matrix()
            world[:, j] = world[:, j] @ A.T + b
            parent = node.parent
    spacing = np.median(np.diff(all_t)) if F > 1 else 1.0
    return LocatorTake(world * to_mm, names, float(time_fps / spacing), all_t / time_fps)
