"""The environment files agree, exactly one OpenCV distribution is installed, the stack imports."""

from __future__ import annotations

import re
import tomllib
from importlib import metadata

import yaml

from rigbuild.paths import PROJECT_ROOT


def _pins_pyproject() -> dict[str, str]:
    data = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())
    reqs = data["project"]["dependencies"] + data["project"]["optional-dependencies"]["test"]
    return dict(r.split("==") for r in reqs)


def _pins_environment() -> dict[str, str]:
    env = yaml.safe_load((PROJECT_ROOT / "environment.yml").read_text())
    pip = next(d["pip"] for d in env["dependencies"] if isinstance(d, dict) and "pip" in d)
    return dict(r.split("==") for r in pip)


def test_environment_yml_matches_pyproject():
    assert _pins_pyproject() == _pins_environment()


def test_installed_versions_match_pins():
    for name, version in _pins_pyproject().items():
        assert metadata.version(name) == version, name


def test_exactly_one_opencv_distribution():
    dists = {d.metadata["Name"].lower() for d in metadata.distributions()}
    cv = sorted(d for d in dists if re.match(r"opencv(-contrib)?-python(-headless)?$", d))
    assert cv == ["opencv-contrib-python-headless"]
    assert not ({"open3d", "open3d-cpu"} <= dists)
