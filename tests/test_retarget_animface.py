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


# ------------------------------------------------------------- plausibility on all four takes (issue 23)
TAKES = ("Jaw", "Eyebrows", "Cheeks", "Nose")


@pytest.fixture(scope="module")
def four_takes(real_data):
    folder = real_data / "animface-facial-mocap"
    if not all((folder / f"{n}MoCap.ma").exists() for n in TAKES):
        pytest.skip(f"AnimFace takes not found in {folder}")
    return {n: read_maya_locator_animation(folder / f"{n}MoCap.ma", group="MoCapData") for n in TAKES}


def test_plausible_weights_on_all_four_takes(four_takes, ict_rig):
    """The pipeline's ribera_fit settings (config/config.yaml) with and without the plausibility options
    (log sparsity, antagonist exclusion): antagonist pairs both above 0.3 in <= 2 % of frames, <= 6 shapes
    above 0.1 per frame on average, eye and brow shapes above 0.2 in <= 5 % of the Jaw take's frames, and
    weight curves no rougher (RMS second difference) than the papers' terms alone give."""
    from dataclasses import replace

    import yaml

    from rigbuild.paths import PROJECT_ROOT
    from rigbuild.retarget.params import PLAUSIBLE, ribera_from_config
    from rigbuild.retarget.plausible import plausibility_metrics
    from rigbuild.retarget.run import apply_model, prepare_model

    cfg = yaml.safe_load((PROJECT_ROOT / "config" / "config.yaml").read_text())
    p = ribera_from_config(cfg["params"]["retarget"]["ribera"])
    names, ids, pairs = read_marker_map(MARKER_DATA_DIR / "animface_ict.json")
    training = make_training_set([t.markers for t in four_takes.values()], [t.names for t in four_takes.values()])
    model = prepare_model(training, ict_rig, names, ids, "ribera_fit", p.transfer_params("ribera_fit"),
                          p.retarget_params("ribera_fit"), pairs)
    out = {}
    for label, params in (("plain", p), ("plausible", replace(p, **PLAUSIBLE))):
        model.params = params.retarget_params("ribera_fit")
        W = {n: apply_model(model, training, t.markers, t.names, marker_lowpass_hz=params.marker_lowpass_hz,
                            fps=t.fps).weights for n, t in four_takes.items()}
        pooled = plausibility_metrics(np.concatenate(list(W.values())), model.shape_names)
        jaw = plausibility_metrics(W["Jaw"], model.shape_names, still_regions=("eyes", "brows"))
        rough = float(np.sqrt(np.mean([plausibility_metrics(w, model.shape_names)["second_difference_rms"] ** 2
                                       for w in W.values()])))
        out[label] = (pooled, jaw, rough)
        assert all(np.all(np.isfinite(w)) and w.min() >= 0.0 and w.max() <= 1.0 for w in W.values())
    (pooled, jaw, rough), (_, _, rough_plain) = out["plausible"], out["plain"]
    assert pooled["antagonist_fraction"] <= 0.02
    assert pooled["mean_active"] <= 6.0
    assert jaw["still_fraction"] <= 0.05
    assert rough <= rough_plain
    # the papers' terms alone do not give this (the numbers issue 23 measured)
    assert out["plain"][0]["antagonist_fraction"] > 0.2 and out["plain"][0]["mean_active"] > 10


def test_plausible_ribera_on_a_take_with_occlusion_gaps(animface, ict_rig):
    """Occlusion gaps (NaN) as the validating reader writes them: 3 % of the marker samples in runs, a
    whole-face dropout and a frame with two markers: finite weights in bounds, the gaps' frames close to
    the complete take's, the plausibility options still holding."""
    from dataclasses import replace

    from rigbuild.retarget.params import PLAUSIBLE, RiberaParams
    from rigbuild.retarget.plausible import antagonist_frames
    from rigbuild.retarget.run import apply_model, prepare_model

    names, ids, pairs = read_marker_map(MARKER_DATA_DIR / "animface_ict.json")
    jaw, brows = animface["Jaw"], animface["Eyebrows"]
    training = make_training_set([jaw.markers, brows.markers], [jaw.names, brows.names])
    p = replace(RiberaParams(lambda_cm=0.006, marker_lowpass_hz=5.0), **PLAUSIBLE)
    model = prepare_model(training, ict_rig, names, ids, "ribera_fit", p.transfer_params("ribera_fit"),
                          p.retarget_params("ribera_fit"), pairs)
    rng = np.random.default_rng(0)
    X = jaw.markers.copy()
    for _ in range(60):  # runs of 1-20 frames on single markers
        f, m = rng.integers(0, X.shape[0] - 20), rng.integers(0, X.shape[1])
        X[f:f + rng.integers(1, 21), m] = np.nan
    X[700:705] = np.nan
    X[900, 2:] = np.nan
    full = apply_model(model, training, jaw.markers, jaw.names, marker_lowpass_hz=5.0, fps=jaw.fps).weights
    res = apply_model(model, training, X, jaw.names, marker_lowpass_hz=5.0, fps=jaw.fps)
    w = res.weights
    assert np.all(np.isfinite(w)) and w.min() >= 0.0 and w.max() <= 1.0
    assert set(range(700, 705)) | {900} <= set(res.empty_frames.tolist())
    assert np.abs(w - full).mean() < 0.02
    assert not antagonist_frames(w, model.shape_names, level=0.3).any()
