"""Marker takes are validated on load: non-finite values and impossible jumps become gaps with a warning
naming the file, marker and frames; a truncated C3D and a take that is mostly gaps are InputErrors."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.io.markers import (MAX_MARKER_SPEED_MM_S, c3d_header_frames, read_markers, validate_take,
                                 write_markers_c3d, write_markers_npz)

NAMES = ["browInner_L", "browInner_R", "lipUpper_C", "jaw_C", "nose_C"]
FPS = 30.0


def _take(F: int = 200, seed: int = 0) -> np.ndarray:
    """(F, 5, 3) mm: a face's markers moving smoothly (speech-like, under 200 mm/s) with 0.3 mm noise."""
    rng = np.random.default_rng(seed)
    base = np.array([[-20, 40, 90], [20, 40, 90], [0, -30, 100], [0, -60, 85], [0, 0, 110]], float)
    t = np.arange(F) / FPS
    motion = 8.0 * np.sin(2 * np.pi * 1.5 * t)[:, None, None] * np.array([0, 1, 0.3])
    return base[None] + motion + rng.normal(scale=0.3, size=(F, 5, 3))


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name == "rigbuild.io.markers"]


def test_clean_take_is_unchanged_and_silent(tmp_path, caplog):
    m = _take()
    m[50:60, 2] = np.nan  # an occlusion gap (residual -1 in the C3D) is a gap, not a fault
    write_markers_c3d(tmp_path / "clean.c3d", m, NAMES, FPS)
    with caplog.at_level(logging.WARNING):
        take = read_markers(tmp_path / "clean.c3d")
    assert not _warnings(caplog)
    np.testing.assert_array_equal(np.isnan(take.markers), np.isnan(m))
    assert np.nanmax(np.abs(take.markers - m)) < 1e-4


def test_broken_c3d_values_become_gaps_with_warnings(tmp_path, caplog):
    """The issue's take: a block of 1e7 values, an all-NaN marker, an inf frame."""
    m = _take()
    m[97:112, 3] = 1e7
    m[:, 1] = np.nan
    m[150, 4, 0] = np.inf
    write_markers_c3d(tmp_path / "broken.c3d", m, NAMES, FPS)
    with caplog.at_level(logging.WARNING):
        take = read_markers(tmp_path / "broken.c3d")
    msgs = _warnings(caplog)
    jaw = [w for w in msgs if "'jaw_C'" in w]
    assert jaw and "broken.c3d" in jaw[0] and "97-111" in jaw[0] and "mm/s" in jaw[0]
    assert any("'browInner_R'" in w and "every frame" in w for w in msgs)
    assert any("'nose_C'" in w and "150" in w for w in msgs)
    assert np.isnan(take.markers[97:112, 3]).all() and np.isfinite(take.markers[:97, 3]).all()
    assert np.isfinite(take.markers[112:, 3]).all()
    assert np.isnan(take.markers[150, 4]).all() and np.isfinite(take.markers[149, 4]).all()
    assert np.isfinite(take.markers[:, [0, 2]]).all()


def test_jump_blocks_at_the_start_and_single_spikes(caplog):
    m = _take()
    m[:5, 0] += 500.0  # the take starts with a mislabelled marker
    m[120, 2] += 80.0  # one spike of 80 mm in 1/30 s (2.4 m/s)
    with caplog.at_level(logging.WARNING):
        out = validate_take(m, NAMES, FPS, "take.c3d")
    assert np.isnan(out[:5, 0]).all() and np.isfinite(out[5:, 0]).all()
    assert np.isnan(out[120, 2]).all() and np.isfinite(np.delete(out[:, 2], 120, axis=0)).all()
    assert any("take.c3d" in w and "'browInner_L'" in w and "0-4" in w for w in _warnings(caplog))


def test_speed_limit_is_per_second_at_the_takes_rate():
    """A 20 mm step is legal at 30 fps (600 mm/s) and a glitch at 240 fps (4.8 m/s)."""
    m = _take(40)
    m[20:, 2] += 20.0
    assert np.isfinite(validate_take(m, NAMES, 30.0, "slow.c3d")).all()
    out = validate_take(m, NAMES, 240.0, "fast.c3d")
    assert np.isnan(out[:, 2]).any()
    assert 20.0 * 30.0 < MAX_MARKER_SPEED_MM_S < 20.0 * 240.0


def test_frame_numbers_set_the_time_steps(tmp_path):
    """Tracked ROM markers (npz with ``frames``) skip frames: a step over 10 frames may be 10 times longer."""
    m = _take(4)
    m[2:] += 150.0
    write_markers_npz(tmp_path / "rom.npz", m, NAMES, FPS, frames=np.array([0, 10, 20, 30]))
    assert np.isfinite(read_markers(tmp_path / "rom.npz").markers).all()
    write_markers_npz(tmp_path / "rom_dense.npz", m, NAMES, FPS, frames=np.arange(4))
    assert np.isnan(read_markers(tmp_path / "rom_dense.npz").markers).any()


def test_truncated_c3d_is_an_input_error_naming_the_file(tmp_path):
    write_markers_c3d(tmp_path / "full.c3d", _take(300), NAMES, FPS)
    raw = (tmp_path / "full.c3d").read_bytes()
    assert c3d_header_frames(tmp_path / "full.c3d") == 300
    (tmp_path / "half.c3d").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(InputError) as e:
        read_markers(tmp_path / "half.c3d")
    assert "half.c3d" in str(e.value) and "truncated" in str(e.value) and "300 frames" in str(e.value)


def test_mostly_gaps_is_an_input_error(tmp_path):
    m = _take()
    m[:130, :4] = np.nan
    write_markers_c3d(tmp_path / "gaps.c3d", m, NAMES, FPS)
    with pytest.raises(InputError, match="gaps.c3d.*mostly gaps"):
        read_markers(tmp_path / "gaps.c3d")
    m = _take()
    m[:90, :4] = np.nan  # 36% gaps: accepted
    write_markers_c3d(tmp_path / "some_gaps.c3d", m, NAMES, FPS)
    assert read_markers(tmp_path / "some_gaps.c3d").n_frames == 200


def test_log_lines_stay_short(caplog):
    m = _take()
    m[::2, 0] += 300.0  # every other frame off: 100 ranges
    with caplog.at_level(logging.WARNING):
        validate_take(m, NAMES, FPS, "noisy.c3d")
    msgs = _warnings(caplog)
    assert msgs and max(len(w) for w in msgs) < 400 and "more" in msgs[0]


def test_marker_sequences_round_trip_and_feed_the_retargeting(tmp_path, caplog):
    """Several ROM sequences at a take's markers in one file (rule take_markers): each comes back with its name,
    its gaps and its frame numbers, is checked like any take (a spike becomes a gap, the warning names the file
    and the sequence), and the retargeting's readers expand it into one take per sequence."""
    from rigbuild.io.markers import is_marker_sequences, read_marker_sequences, write_marker_sequences
    from rigbuild.retarget.stage import rom_takes, seol_neutral

    rng = np.random.default_rng(0)
    a = rng.normal(size=(5, 3, 3)) * 10
    b = rng.normal(size=(4, 3, 3)) * 10
    a[2, 1] = np.nan
    b[3, 0] += 500.0  # one frame 500 mm off: faster than a face moves
    path = tmp_path / "rom_markers.npz"
    write_marker_sequences(path, {"rom00": (a, np.arange(5)), "rom01": (b, np.arange(10, 14))}, ["x", "y", "z"], 60.0)
    assert is_marker_sequences(path) and not is_marker_sequences(tmp_path / "missing.npz")
    with caplog.at_level(logging.WARNING):
        seqs = read_marker_sequences(path)
    assert [s for s, _ in seqs] == ["rom00", "rom01"]
    np.testing.assert_allclose(seqs[0][1].markers, a.astype(np.float32), equal_nan=True)
    assert np.isnan(seqs[1][1].markers[3, 0]).all() and "rom01" in caplog.text
    assert seqs[0][1].names == ["x", "y", "z"] and seqs[0][1].fps == 60.0
    single = tmp_path / "single.npz"
    write_markers_npz(single, a[:, ::-1], ["z", "y", "x"], 60.0)
    takes, sources = rom_takes([path, single])
    assert len(takes) == 3 and "sequence rom01" in sources[1] and sources[2] == str(single)
    Y = seol_neutral([path], [0, 1], ["x", "y", "z"])
    assert Y.shape == (3, 3) and np.isfinite(Y).all()
    bad = tmp_path / "bad.npz"
    np.savez(bad, sequence_names=np.array(["rom00"]), marker_names=np.array(["x"]), fps=30.0)
    with pytest.raises(InputError, match="bad.npz"):
        read_marker_sequences(bad)
