"""Spacetime editing (Seol et al. 2012, sec. 6): exact pins, untouched frames outside the range,
smooth propagation inside; the `rigbuild edit` command; bad-input messages."""

from __future__ import annotations


import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.io.curves import read_weight_curves_csv, write_weight_curves_csv
from rigbuild.retarget.editing import edit_spacetime
from rigbuild.retarget.seol import SeolSystem, build_pca_prior

NAMES = ["jawOpen", "eyeBlink_L", "mouthSmile_L", "browInnerUp"]


def _system(F=120, M=12, seed=0, alpha=0.01):
    """A retargeting system whose source is a smooth blendshape animation of B."""
    rng = np.random.default_rng(seed)
    K = len(NAMES)
    B = rng.normal(size=(3 * M, K)) * 5
    t = np.arange(F) / 30.0
    W_true = 0.5 - 0.5 * np.cos(2 * np.pi * np.outer(t, [0.5, 0.8, 0.3, 0.6]))
    S = W_true @ B.T
    prior = build_pca_prior(np.vstack([np.zeros(3 * M), B.T]))
    P, p = prior.quadratic(B)
    return SeolSystem(B, S, P, p, alpha=alpha, shape_names=NAMES)


def _check_edit(W, W_new, frame, a, b, pinned):
    assert np.array_equal(W_new[:a], W[:a]) and np.array_equal(W_new[b + 1:], W[b + 1:])
    assert np.array_equal(W_new[[a, b]], W[[a, b]])
    for k, v in pinned.items():
        assert W_new[frame, NAMES.index(k)] == v  # exact
    corr = W_new - W
    d2 = np.diff(corr[a:b + 1], 2, axis=0)  # second differences of the correction
    inner = np.delete(np.arange(d2.shape[0]), frame - a - 1)  # all but the kink at the pinned frame
    step = np.abs(corr[frame]).max() / min(frame - a, b - frame)
    return d2, inner, step


def test_edit_with_system_is_exact_local_and_smooth():
    system = _system()
    W = system.solve_spacetime()
    frame, a, b = 60, 48, 75
    pinned = {"jawOpen": 0.95, "eyeBlink_L": 0.1}
    W_new = edit_spacetime(W, frame, pinned, (a, b), system=system)
    d2, inner, step = _check_edit(W, W_new, frame, a, b, pinned)
    # smooth propagation: away from the pinned frame the correction's curvature is a small fraction
    # of the edit's slope (a Poisson correction is near-linear in time), and it has no sign flips
    assert np.abs(d2[:, [0, 1]][inner]).max() < 0.1 * step
    corr = (W_new - W)[a:b + 1, 0]
    assert np.all(np.diff(corr[: frame - a + 1]) > 0) and np.all(np.diff(corr[frame - a:]) < 0)
    # unpinned shapes at the edited frame were re-solved, not frozen
    assert not np.array_equal(W_new[a + 1:b, 2:], W[a + 1:b, 2:]) or np.allclose(W_new, W)


def test_edit_without_system_is_a_linear_correction():
    W = _system().solve_spacetime()
    frame, a, b = 30, 20, 50
    W_new = edit_spacetime(W, frame, {"mouthSmile_L": 1.2}, (a, b), shape_names=NAMES)
    d2, inner, step = _check_edit(W, W_new, frame, a, b, {"mouthSmile_L": 1.2})
    k = NAMES.index("mouthSmile_L")
    corr = (W_new - W)[:, k]
    expect = np.interp(np.arange(W.shape[0]), [a, frame, b], [0.0, 1.2 - W[frame, k], 0.0])
    assert np.abs(corr - expect).max() < 1e-7
    assert np.abs(d2[inner]).max() < 1e-7
    others = [i for i in range(len(NAMES)) if i != k]
    assert np.abs(W_new[:, others] - W[:, others]).max() < 1e-7


def test_full_pose_edit_and_edit_at_range_end():
    system = _system()
    W = system.solve_spacetime()
    pose = np.array([0.3, 0.9, 0.1, 0.0])
    W_new = edit_spacetime(W, 40, pose, (35, 52), system=system)
    assert np.array_equal(W_new[40], pose)
    # the edited frame may be a range end: its pinned values replace the old boundary there
    W_end = edit_spacetime(W, 35, {"browInnerUp": 0.7}, (35, 52), system=system)
    assert W_end[35, 3] == 0.7 and np.array_equal(W_end[:35], W[:35]) and np.array_equal(W_end[52:], W[52:])


def test_edit_bad_input():
    system = _system()
    W = system.solve_spacetime()
    with pytest.raises(InputError, match=r"range \[10, 20\] does not contain the edited frame 30"):
        edit_spacetime(W, 30, {"jawOpen": 1.0}, (10, 20), system=system)
    with pytest.raises(InputError, match="range end frame 500 is outside the sequence"):
        edit_spacetime(W, 30, {"jawOpen": 1.0}, (10, 500), system=system)
    with pytest.raises(InputError, match="edited frame -3 is outside"):
        edit_spacetime(W, -3, {"jawOpen": 1.0}, (0, 20), system=system)
    with pytest.raises(InputError, match="weight name 'jawOpenn' is not a shape"):
        edit_spacetime(W, 15, {"jawOpenn": 1.0}, (10, 20), system=system)
    with pytest.raises(InputError, match="empty or reversed"):
        edit_spacetime(W, 15, {"jawOpen": 1.0}, (20, 15), system=system)
    with pytest.raises(InputError, match="frames x"):
        edit_spacetime(W[:50], 15, {"jawOpen": 1.0}, (10, 20), system=system)


def test_rigbuild_edit_command(tmp_path, capsys):
    from rigbuild.cli import main

    system = _system()
    W = system.solve_spacetime()
    src = tmp_path / "weights.csv"
    write_weight_curves_csv(src, W, NAMES, 30.0)
    system.save(tmp_path / "system.npz")
    out = tmp_path / "new.csv"
    rc = main(["edit", str(src), "--frame", "60", "--set", "jawOpen=0.95", "--set", "eyeBlink_L=0.1",
               "--range", "48", "75", "--out", str(out), "--system", str(tmp_path / "system.npz")])
    assert rc == 0
    W_file, names, _ = read_weight_curves_csv(src)
    W_new, names_new, times = read_weight_curves_csv(out)
    assert names_new == NAMES and np.allclose(np.diff(times), 1 / 30.0, atol=1e-6)
    assert W_new[60, 0] == pytest.approx(0.95, abs=1e-6) and W_new[60, 1] == pytest.approx(0.1, abs=1e-6)
    assert np.array_equal(W_new[:48], W_file[:48]) and np.array_equal(W_new[76:], W_file[76:])
    ref = edit_spacetime(W_file, 60, {"jawOpen": 0.95, "eyeBlink_L": 0.1}, (48, 75), system=SeolSystem.load(tmp_path / "system.npz"))
    assert np.abs(W_new - ref).max() < 2e-6
    # --from-csv with a single pose row, no system (curve-movement edit)
    pose = tmp_path / "pose.csv"
    pose.write_text("mouthSmile_L,browInnerUp\n0.8,0.2\n")
    out2 = tmp_path / "new2.csv"
    assert main(["edit", str(src), "--frame", "20", "--from-csv", str(pose), "--range", "10", "30", "--out", str(out2)]) == 0
    W2, _, _ = read_weight_curves_csv(out2)
    assert W2[20, 2] == pytest.approx(0.8, abs=1e-6) and W2[20, 3] == pytest.approx(0.2, abs=1e-6)
    # bad input: clear message, exit code 2
    capsys.readouterr()
    rc = main(["edit", str(src), "--frame", "20", "--set", "nope=1", "--range", "10", "30", "--out", str(out2)])
    assert rc == 2 and "weight name 'nope' is not a shape" in capsys.readouterr().err
    rc = main(["edit", str(src), "--frame", "40", "--set", "jawOpen=1", "--range", "10", "30", "--out", str(out2)])
    assert rc == 2 and "does not contain the edited frame 40" in capsys.readouterr().err
