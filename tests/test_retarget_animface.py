"""Real marker takes (AnimFace, Maya ASCII, 41 markers, cm, 60 Hz) retargeted onto the ICT template with the
marker map rigbuild/assets/marker_sets/animface_ict.json (Ribera et al. 2017 method and the RBF baseline)."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.io.maya_ascii import read_maya_locator_animation
from rigbuild.retarget.marker_maps import MARKER_DATA_DIR, read_marker_map
from rigbuild.retarget.ribera import RetargetParams
from rigbuild.retarget.run import make_training_set, retarget_performance

#: bound on the RMS second difference of the weight curves (per frame^2 at 60 Hz); smooth speech-rate motion
#: stays far below, frame-to-frame flicker between shapes would exceed it
JITTER_BOUND = 0.02


@pytest.fixture(scope="module")
def animface(real_data):
    folder = real_data / "animface-facial-mocap"
    if not (folder / "JawMoCap.ma").exists():
        pytest.skip(f"AnimFace takes not found in {folder}")
    return {n: read_maya_locator_animation(folder / f"{n}MoCap.ma", group="MoCapData")
            for n in ("Jaw", "Eyebrows")}


def test_reader_on_real_takes(animface):
    jaw = animface["Jaw"]
    assert jaw.markers.shape == (1590, 41, 3) and jaw.fps == pytest.approx(60.0, rel=1e-9)
    assert np.all(np.isfinite(jaw.markers))
    width = np.ptp(jaw.markers[0, :, 0])  # cm -> mm: a face is 100-200 mm wide
    assert 100.0 < width < 200.0


@pytest.mark.parametrize("method", ["ribera", "ribera_fit", "rbf", "deformation"])
def test_retarget_animface_onto_ict(animface, ict_rig, method):
    names, ids, pairs = read_marker_map(MARKER_DATA_DIR / "animface_ict.json")
    jaw, brows = animface["Jaw"], animface["Eyebrows"]
    training = make_training_set([jaw.markers, brows.markers], [jaw.names, brows.names])
    prm = RetargetParams(bounds=(0.0, 1.0), lambda_cm=0.006)
    res = retarget_performance(training, jaw.markers, jaw.names, ict_rig, names, ids, method,
                               retarget_params=prm, contact_pairs=pairs)
    w = res.weights
    assert w.shape == (1590, ict_rig.n_shapes)
    assert np.all(np.isfinite(w)) and w.min() >= 0.0 and w.max() <= 1.0
    jitter = float(np.sqrt(np.mean(np.diff(w, 2, axis=0) ** 2)))
    assert jitter < JITTER_BOUND
    # the jaw take opens the jaw: jawOpen (or its partner mouthClose) must move substantially
    k = [ict_rig.shape_names.index(n) for n in ("jawOpen", "mouthClose")]
    assert np.ptp(w[:, k].sum(1)) > 0.2
