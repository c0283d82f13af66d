"""Shared marker-trajectory helpers of the retargeting stages (rigbuild.retarget.common)."""

from __future__ import annotations

import numpy as np
import pytest

from rigbuild.errors import InputError
from rigbuild.retarget.common import lowpass_markers, lowpass_sigma_frames


def test_lowpass_is_minus_3db_at_the_cutoff_and_passes_slow_motion():
    fps, fc = 60.0, 5.0
    t = np.arange(2400) / fps
    X = np.zeros((t.size, 2, 3))
    X[:, 0, 0] = np.sin(2 * np.pi * fc * t)        # at the cutoff
    X[:, 1, 1] = np.sin(2 * np.pi * 0.5 * t)       # slow facial motion
    Y = lowpass_markers(X, fps, fc)
    inner = slice(200, -200)

    def gain(y, f):  # amplitude of the output sinusoid (least squares on sin and cos)
        A = np.stack([np.sin(2 * np.pi * f * t[inner]), np.cos(2 * np.pi * f * t[inner])], 1)
        return float(np.hypot(*np.linalg.lstsq(A, y[inner], rcond=None)[0]))

    gain_fc, gain_slow = gain(Y[:, 0, 0], fc), gain(Y[:, 1, 1], 0.5)
    assert gain_fc == pytest.approx(1 / np.sqrt(2), rel=2e-3)
    expected_slow = np.exp(-2 * np.pi**2 * (lowpass_sigma_frames(fps, fc) / fps) ** 2 * 0.5**2)
    assert gain_slow == pytest.approx(expected_slow, rel=1e-3)
    assert gain_slow > 0.99


def test_lowpass_keeps_gaps_and_does_not_leak_them():
    X = np.full((50, 3, 3), 7.0)
    X[:, 1] += np.arange(50)[:, None] * 0.5  # linear motion is kept (symmetric kernel) away from the ends
    X[20:25, 0] = np.nan
    X[30, 2, :] = np.nan
    Y = lowpass_markers(X, 30.0, 4.0)
    assert np.isnan(Y[20:25, 0]).all() and np.isnan(Y[30, 2]).all()
    seen = np.isfinite(X)
    np.testing.assert_allclose(Y[seen.all(2)[:, 0], 0], 7.0, atol=1e-12)  # constant stays constant beside a gap
    np.testing.assert_allclose(Y[10:40, 1], X[10:40, 1], atol=1e-9)
    assert np.isfinite(Y[seen]).all()


def test_lowpass_cutoff_must_be_below_nyquist():
    X = np.zeros((10, 2, 3))
    for bad in (0.0, -1.0, 15.0, 40.0):
        with pytest.raises(InputError, match="Nyquist"):
            lowpass_markers(X, 30.0, bad)
