"""Zero-phase Butterworth low-pass and the rigidity test."""
import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt, sosfreqz

from reconstruct.filtering import butterworth_lowpass, contiguous_runs
from reconstruct.rigidity import rigidity_flags

RATE = 120.0
CUTOFF = 6.0
GAIN_REL = 1e-6         # steady-state amplitude vs |H|^2 of the forward-backward filter
                        # (measured to ~5e-16 at 1, 6 and 15 Hz)
PHASE_TOL_S = 1e-3      # zero phase: peak-time shift


def _amplitude(f_hz, n=2400):
    t = np.arange(n) / RATE
    x = np.sin(2 * np.pi * f_hz * t)
    y = butterworth_lowpass(x[:, None, None] * np.ones((1, 1, 3)), RATE, CUTOFF)[:, 0, 0]
    mid = slice(n // 4, 3 * n // 4)
    return np.sqrt(2 * np.mean(y[mid] ** 2)), x, y, t


@pytest.mark.parametrize("f_hz", [1.0, 6.0, 15.0])
def test_gain_is_squared_butterworth_response(f_hz):
    amp, *_ = _amplitude(f_hz)
    sos = butter(2, CUTOFF, fs=RATE, output="sos")
    _, h = sosfreqz(sos, worN=[f_hz], fs=RATE)
    assert amp == pytest.approx(abs(h[0]) ** 2, rel=GAIN_REL)
    if f_hz == 6.0:
        assert amp == pytest.approx(0.5, rel=GAIN_REL)   # -6 dB at the cutoff


def test_zero_phase():
    _, x, y, t = _amplitude(2.0)
    mid = slice(600, 1800)
    lag = np.argmax(np.correlate(y[mid], x[mid], "full")) - (1200 - 1)
    assert abs(lag) / RATE <= PHASE_TOL_S


def test_runs_filtered_separately_gaps_kept():
    g = np.random.default_rng(0)
    x = np.cumsum(g.normal(size=(300, 2, 3)), axis=0)
    x[100:110, 0] = np.nan
    x[200:202, 1] = np.nan
    x[50, 1] = np.nan
    y = butterworth_lowpass(x, RATE, CUTOFF)
    assert np.array_equal(np.isnan(y), np.isnan(x))
    sos = butter(2, CUTOFF, fs=RATE, output="sos")
    for a, b in contiguous_runs(np.isfinite(x[:, 0, 0])):
        ref = sosfiltfilt(sos, x[a:b, 0], axis=0, padlen=min(9, b - a - 1))
        assert np.abs(y[a:b, 0] - ref).max() < 1e-12


def test_filter_validation():
    with pytest.raises(ValueError, match="cutoff_hz"):
        butterworth_lowpass(np.zeros((10, 1, 3)), RATE, 70.0)
    with pytest.raises(ValueError, match="rate_hz"):
        butterworth_lowpass(np.zeros((10, 1, 3)), 0.0, 5.0)


def test_rigidity_flags_the_marker_that_moved():
    g = np.random.default_rng(1)
    T = 100
    base = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.15, 0], [0.1, 0.1, 0.1]], float)
    P = base[None] + np.linspace(0, 1, T)[:, None, None] + g.normal(0, 0.0005, (T, 4, 3))
    away = base[2] - np.delete(base, 2, axis=0).mean(axis=0)
    shift = 0.05 * away / np.linalg.norm(away)        # marker 2 slides 5 cm outwards
    moved = base.copy()
    moved[2] += shift
    change = np.abs(np.linalg.norm(moved[2] - base, axis=1) - np.linalg.norm(base[2] - base,
                                                                             axis=1))
    assert np.all(np.delete(change, 2) > 0.02)        # precondition: every pair of 2 fails
    P[30:35, 2] += shift
    P[60, 1] = np.nan
    flags = rigidity_flags(P, [[0, 1, 2, 3]], threshold_m=0.01)
    expected = np.zeros((T, 4), bool)
    expected[30:35, 2] = True
    assert np.array_equal(flags, expected)
    # a two-marker group flags both
    f2 = rigidity_flags(P, [[1, 2]], threshold_m=0.01)
    assert f2[30:35, [1, 2]].all() and f2.sum() == 10
    with pytest.raises(ValueError, match="threshold_m"):
        rigidity_flags(P, [[0, 1]], threshold_m=0)
