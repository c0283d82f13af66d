"""params.track: one typed definition (rigbuild.track.params), checked whole by from_config."""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from rigbuild.errors import InputError
from rigbuild.paths import PROJECT_ROOT
from rigbuild.track.params import RegistrationParams, TrackParams, from_config


def test_defaults_and_nested_blocks():
    assert from_config(None) == TrackParams()
    assert from_config({}) == TrackParams()
    p = from_config({"registration": {"lam_schedule": [0.02, 0.5], "relabel_at": [3]},
                     "dots": {"darkness": 0.3}, "sparse": {"radius_px": [20, 10]}, "flow": {"preset": "fast"},
                     "levels": ["features", "sparse"], "template_rig": "procedural"})
    assert p.registration == RegistrationParams(lam_schedule=(0.02, 0.5), relabel_at=(3,))
    assert p.dots.darkness == 0.3 and p.sparse.radius_px == (20, 10) and p.flow.preset == "fast"
    assert p.levels == ("features", "sparse") and p.template_rig == "procedural"


def test_config_files_track_blocks_are_valid():
    for path in sorted((PROJECT_ROOT / "config").glob("*.yaml")):
        block = ((yaml.safe_load(path.read_text()) or {}).get("params") or {}).get("track")
        from_config(block)


def test_unknown_registration_key_fails_with_did_you_mean():
    with pytest.raises(InputError, match=r"params\.track\.registration\.iteratons.*did you mean 'iterations'"):
        from_config({"registration": {"iteratons": 5}})


@pytest.mark.parametrize("block, match", [
    ({"lost_residual": 1.0}, r"params\.track\.lost_residual'.*did you mean 'lost_residual_mm'"),
    ({"dots": {"darknes": 0.3}}, r"params\.track\.dots\.darknes'.*did you mean 'darkness'"),
    ({"flow": {"preset": "slow"}}, "flow preset 'slow'"),
    ({"flow": {"sources": ["previous", "neighbour"]}}, r"unknown flow sources \['neighbour'\]"),
    ({"flow": {"sources": []}}, "flow.sources is empty"),
    ({"levels": ["features", "dense"]}, "unknown tracking levels"),
    ({"registration": {"lam_schedule": [0.02]}}, "lam_schedule has 1 values"),
    ({"registration": {"coarse": "markers"}}, "unknown coarse level 'markers'"),
])
def test_bad_track_blocks_fail(block, match):
    with pytest.raises(InputError, match=match):
        from_config(block)


def test_from_config_does_not_import_opencv():
    code = ("import sys; from rigbuild.track.params import from_config; from_config({'flow': {'preset': 'fast'}}); "
            "assert 'cv2' not in sys.modules, 'cv2 imported'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=PROJECT_ROOT)
    assert r.returncode == 0, r.stderr


def test_registration_params_are_register_neutral_defaults():
    """The defaults live in RegistrationParams only: register_neutral takes them typed, no keyword copies."""
    import inspect

    from rigbuild.track.register import register_neutral

    names = set(inspect.signature(register_neutral).parameters)
    assert names == {"template", "scan_points", "scan_normals", "dots", "rays", "params", "mesh", "depth_views",
                     "dot_vertices", "landmarks"}


def test_stencil_warp_needs_a_positive_window():
    from rigbuild.errors import InputError
    from rigbuild.track.params import from_config

    with pytest.raises(InputError, match="stencil_smoothing_mm"):
        from_config({"registration": {"stencil_warp": 1.0, "stencil_smoothing_mm": 0.0}})
    assert from_config({"registration": {"stencil_warp": 0.0, "stencil_smoothing_mm": 0.0}})
