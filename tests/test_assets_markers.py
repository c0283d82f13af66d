"""Tests of the marker sets (rigbuild.assets.markers): the recipe, the shipped JSON files and their packaging."""

from __future__ import annotations

import fnmatch
import tomllib

import numpy as np
import pytest

from rigbuild.assets.markers import (
    MARKER_DIR,
    MULTIPIE_MIRROR,
    load_marker_set,
    marker_names,
    marker_set_path,
    marker_targets,
    mirror_name,
    snap_to_surface,
)
from rigbuild.errors import InputError
from rigbuild.paths import PROJECT_ROOT

MIRROR = np.array([-1.0, 1.0, 1.0])


def test_marker_recipe_names_and_targets():
    names = marker_names()
    assert len(names) == len(set(names))
    assert np.array_equal(MULTIPIE_MIRROR[MULTIPIE_MIRROR], np.arange(68))
    assert mirror_name("browInner_L") == "browInner_R" and mirror_name("jaw_R3") == "jaw_L3"
    assert mirror_name("chin_C") == "chin_C"
    lm = np.arange(68 * 3, dtype=float).reshape(68, 3)
    n, t = marker_targets(lm)
    d = dict(zip(n, t))
    assert np.array_equal(d["browInner_L"], lm[22]) and np.array_equal(d["browInner_R"], lm[21])
    assert np.allclose(d["eyeOuter_L"], lm[45] + [4, 0, 0]) and np.allclose(d["eyeOuter_R"], lm[36] + [-4, 0, 0])
    assert np.allclose(d["lidUpper_R"], 0.5 * (lm[38] + lm[37]) + [0, 3, 0])
    with pytest.raises(InputError):
        marker_targets(np.zeros((5, 3)))


def test_snap_to_surface_picks_front_facing_nearest():
    # two parallel squares facing +z (z = 0) and -z (z = -1): the back one is never chosen
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, -1], [1, 0, -1], [1, 1, -1], [0, 1, -1]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]])
    idx = snap_to_surface(v, f, np.array([[0.9, 0.1, -1.0], [0.1, 0.8, 5.0]]))
    assert idx.tolist() == [1, 3]


def test_ict_marker_json_loads():
    names, idx = load_marker_set("ict")
    assert 60 <= len(names) <= 100 and len(set(names)) == len(names)
    assert idx.dtype == np.int64 and idx.min() >= 0 and idx.max() <= 9408
    assert np.unique(idx).size == idx.size
    assert set(names) == set(marker_names())  # same names as the procedural head
    with pytest.raises(InputError):
        load_marker_set("no_such_rig")


def test_ict_markers_on_ict_face(ict_rig):
    names, idx = load_marker_set("ict")
    v = ict_rig.neutral
    pos = dict(zip(names, v[idx]))
    for n in names:
        assert np.linalg.norm(pos[mirror_name(n)] * MIRROR - pos[n]) < 3.0, n
    # the markers sit near their recipe targets on the ICT face
    _, targets = marker_targets(v[ict_rig.landmarks])
    assert np.median(np.linalg.norm(targets - v[idx], axis=1)) < 8.0
    assert v[idx, 2].min() > 20.0  # on the front of the face


def test_marker_sets_are_package_data():
    """Every shipped marker set lies in the package and matches pyproject.toml's package-data patterns, so a
    (non-editable) ``pip install`` carries it."""
    package = PROJECT_ROOT / "rigbuild"
    shipped = sorted(MARKER_DIR.glob("*.json"))
    assert {p.stem for p in shipped} >= {"ict", "animface_ict"}
    assert MARKER_DIR.is_relative_to(package)
    patterns = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    for p in shipped:
        rel = p.relative_to(package).as_posix()
        assert any(fnmatch.fnmatch(rel, pat) for pat in patterns["rigbuild"]), rel
    assert marker_set_path("ict") == MARKER_DIR / "ict.json"
