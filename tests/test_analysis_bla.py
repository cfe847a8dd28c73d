"""Robust BLA: linear system with noise, Wiener odd/even detection, closed loop, real data."""
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from fftune.analysis.bla import TransientWarning, bla_levels, detect_excited_lines, robust_bla
from fftune.analysis.errors import InputError
from fftune.analysis.multisine import multisine_realizations

# KU Leuven motor bench (MIT, provenance in tests/data/kul_motorbench_twomass.md)
DATA = Path(__file__).resolve().parent / "data" / "kul_motorbench_twomass.npz"
B, A = signal.butter(2, 0.12)          # the "plant": a discrete 2nd-order low-pass


def periodic_filter(x, b=B, a=A):
    """Steady-state response of b/a to a periodic x (last axis = one period), exactly."""
    n = x.shape[-1]
    _, h = signal.freqz(b, a, worN=np.arange(n // 2 + 1) * 2 * np.pi / n)
    return np.fft.irfft(np.fft.rfft(x, axis=-1) * h, n=n, axis=-1)


def multisine_table(m, n, periods, k_max, seed=1, rms=1.0, group=5):
    designs = multisine_realizations(m, 1.0, n, k_min=1, k_max=k_max, seed=seed, rms=rms,
                                     group=group)
    one = np.stack([d.period for d in designs])                       # (M, N)
    return designs, one, np.repeat(one[:, None, :], periods, axis=1)  # (M, P, N)


def test_linear_system_with_noise_bounds_and_unbiased_noise_variance():
    m, p, n, sigma = 8, 4, 256, 0.02
    designs, one, u = multisine_table(m, n, p, 100)
    y0 = np.repeat(periodic_filter(one)[:, None, :], p, axis=1)
    exc = designs[0].excited
    _, g_true = signal.freqz(B, A, worN=2 * np.pi * exc / n)
    u_amp = designs[0].amplitudes                     # |U| of every realization (scaled 2/N)
    var_truth = 4 * sigma ** 2 / n / u_amp ** 2 / (m * p)
    inside, ratio_noise, ratio_total, nl_rel = [], [], [], []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        res = robust_bla(u, y0 + sigma * rng.standard_normal(u.shape), fs=1.0)
        np.testing.assert_array_equal(res.bins, exc)
        inside.append(np.abs(res.G - g_true) ** 2 <= 9 * res.var_total)
        ratio_noise.append(np.mean(res.var_noise / var_truth))
        ratio_total.append(np.mean(res.var_total / var_truth))
        nl_rel.append(np.mean(res.var_nl) / np.mean(m * res.var_noise))
        assert np.array_equal(res.var_nl_negative, res.var_nl < 0)
    assert np.mean(inside) >= 0.99
    assert np.mean(ratio_noise) == pytest.approx(1.0, abs=0.03)     # unbiased noise variance
    assert np.mean(ratio_total) == pytest.approx(1.0, abs=0.06)
    assert abs(np.mean(nl_rel)) < 0.05                               # no nonlinear variance
    assert np.std(nl_rel) < 0.3


@pytest.mark.parametrize("kind", ["odd", "even"])
def test_wiener_system_odd_and_even_detection(kind):
    m, p, n = 6, 4, 1024
    designs, one, u = multisine_table(m, n, p, 200, seed=3)
    x = periodic_filter(one)
    static = (lambda v: v + 0.3 * v ** 3) if kind == "odd" else (lambda v: v + 0.3 * v ** 2)
    y = np.repeat(static(x)[:, None, :], p, axis=1)
    y = y + 1e-4 * np.random.default_rng(0).standard_normal(y.shape)
    res = robust_bla(u, y, fs=1000.0)
    s = res.summary
    assert res.odd_bins.size > 10 and res.even_bins.size > 50
    if kind == "odd":
        assert s["odd_detected"] and not s["even_detected"]
        assert s["odd_re_noise_db"] > 30 and abs(s["even_re_noise_db"]) < 2
        assert s["odd_re_even_db"] > 30
        assert s["nl_re_output_db"] is not None and s["nl_re_output_db"] > -40
        assert s["noise_re_nl_db"] < -20
    else:
        assert s["even_detected"] and not s["odd_detected"]
        assert s["even_re_noise_db"] > 30 and abs(s["odd_re_noise_db"]) < 2
        assert s["odd_re_even_db"] < -30
    # the Figure-3 arrays line up with the lines
    assert res.output_db.shape == res.bins.shape and res.odd_db.shape == res.odd_bins.shape


def closed_loop_records(m, p=6, n=512, kp=4.0):
    """(u, y, r, den) of the plant G = B/A under C = kp (static) with output noise v inside
    the loop: y = T r + S v, u = C S (r - v), S = A / den, T = kp B / den."""
    _, _, r = multisine_table(m, n, p, 120, seed=9)
    rng = np.random.default_rng(4)
    v = 0.05 * rng.standard_normal(r.shape)
    den = A + kp * np.concatenate([B, np.zeros(A.size - B.size)])
    y = periodic_filter(r, kp * B, den) + periodic_filter(v, A, den)
    u = periodic_filter(r - v, kp * A, den)
    return u, y, r, den


def test_closed_loop_known_reference_gives_plant_not_closed_loop():
    m, n, kp = 8, 512, 4.0
    u, y, r, den = closed_loop_records(m, n=n, kp=kp)
    res = robust_bla(u, y, r, fs=1.0)
    _, g_plant = signal.freqz(B, A, worN=2 * np.pi * res.bins / n)
    _, g_closed = signal.freqz(kp * B, den, worN=2 * np.pi * res.bins / n)
    assert res.known_reference
    err_plant = np.abs(res.G - g_plant)
    assert np.mean(err_plant ** 2 <= 9 * res.var_total) >= 0.97
    assert np.median(err_plant / np.abs(g_plant)) < 0.02
    assert np.median(np.abs(res.G - g_closed) / np.abs(g_closed)) > 0.2
    assert res.summary["odd_detected"] is False


def test_single_realization_and_single_period():
    designs, one, u = multisine_table(1, 128, 3, 40)
    y = periodic_filter(u) + 1e-3 * np.random.default_rng(0).standard_normal(u.shape)
    res = robust_bla(u, y)
    assert res.var_total is None and res.var_nl is None and res.var_noise is not None
    assert any("M = 1" in note for note in res.notes)
    designs, one, u = multisine_table(3, 128, 1, 40)
    res = robust_bla(u, periodic_filter(u))
    assert res.var_noise is None and res.var_nl is None and res.var_total is not None
    assert res.odd_noise_db is None and any("P = 1" in note for note in res.notes)


def test_transient_in_kept_periods_warns():
    n, p = 256, 6
    designs, one, u = multisine_table(2, n, p, 60, seed=2)
    b, a = signal.butter(2, 0.01)           # slow plant started from rest: long transient
    y = signal.lfilter(b, a, u.reshape(2, -1), axis=-1).reshape(u.shape)
    with pytest.warns(TransientWarning, match="transient"):
        res = robust_bla(u, y, settle_periods=0)
    assert res.transient.suspect and res.transient.settle_differs is None
    skipped = robust_bla(u, y, settle_periods=2, warn_transient=False)
    assert skipped.transient.settle_differs is True
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        y_steady = np.repeat(periodic_filter(one, b, a)[:, None, :], p, axis=1)
        ok = robust_bla(u, y_steady + 1e-6 * np.random.default_rng(1).standard_normal(u.shape),
                        settle_periods=1)
    assert not ok.transient.suspect and ok.transient.level_db.shape == (p,)
    assert ok.transient.settle_differs is False


def test_detect_excited_lines_on_odd_odd_grid_and_bad_input():
    n = 512
    t = np.arange(n)
    lines = np.arange(5, 200, 4)
    x = sum(np.sin(2 * np.pi * k * t / n + k) for k in lines)
    x = np.tile(x, (2, 3, 1)) + 1e-4 * np.random.default_rng(0).standard_normal((2, 3, n))
    np.testing.assert_array_equal(detect_excited_lines(x), lines)
    with pytest.raises(InputError, match="--lines"):
        detect_excited_lines(np.random.default_rng(0).standard_normal((2, 3, n)))


def test_bad_input_is_rejected():
    designs, one, u = multisine_table(2, 128, 2, 40)
    y = periodic_filter(u)
    with pytest.raises(InputError, match="shape"):
        robust_bla(u, y[:, :1])
    with pytest.raises(InputError, match="realizations M"):
        robust_bla(u[0], y[0])
    bad = y.copy()
    bad[1, 1, 7] = np.nan
    with pytest.raises(InputError, match="NaN"):
        robust_bla(u, bad)
    with pytest.raises(InputError, match="zero power"):
        robust_bla(u, y, excited_bins=[2, 4, 6])
    with pytest.raises(InputError, match=r"zero power at 1 excited line\(s\) 4 Hz"):
        robust_bla(u, y, fs=128.0, excited_bins=np.append(designs[0].excited, 4))
    with pytest.raises(InputError, match="settle"):
        robust_bla(u, y, settle_periods=2)


def test_bla_over_levels_sees_saturation():
    n, p = 512, 2
    us, ys = [], []
    for rms in (0.1, 0.5, 2.0):
        designs, one, u = multisine_table(4, n, p, 100, rms=rms, seed=11)
        us.append(u)
        ys.append(np.clip(periodic_filter(u), -1.0, 1.0))
    lev = bla_levels(us, ys, fs=1.0)
    assert lev.G.shape == (3, lev.freq.size)
    np.testing.assert_allclose(lev.rms, [0.1, 0.5, 2.0], rtol=1e-9)
    gain = np.mean(np.abs(lev.G[:, :10]), axis=1)
    _, h = signal.freqz(B, A, worN=2 * np.pi * lev.freq[:10])
    assert gain[0] == pytest.approx(np.mean(np.abs(h)), rel=0.01)     # linear at low level
    assert gain[2] < 0.8 * gain[0]                                     # saturated at high level


@pytest.fixture(scope="module")
def motorbench():
    return np.load(DATA)      # part of the repository: a missing file is a failure


def test_real_motorbench_odd_odd_record(motorbench):
    u = motorbench["B_iq"][None].astype(float)            # (M=1, 20, 2500)
    y = motorbench["B_theta_motor"][None].astype(float)
    fs = float(motorbench["fs"])
    res = robust_bla(u, y, fs=fs, settle_periods=1)
    np.testing.assert_array_equal(res.bins, motorbench["B_excited_lines"])
    assert np.all(res.bins % 4 == 1)
    np.testing.assert_array_equal(res.odd_bins, np.arange(15, 249, 4))   # 4k+3 lines
    np.testing.assert_array_equal(res.even_bins, np.arange(14, 249, 2))
    s = res.summary
    assert res.var_nl is None and res.var_total is None       # one realization
    assert s["odd_re_even_db"] == pytest.approx(3.3, abs=1.0)  # odd distortion above even
    assert s["odd_re_noise_db"] == pytest.approx(21.3, abs=1.5)
    assert s["even_re_noise_db"] == pytest.approx(14.8, abs=1.5)
    assert s["noise_re_output_db"] == pytest.approx(-56.2, abs=1.0)
    assert s["odd_re_output_db"] == pytest.approx(-40.7, abs=1.0)
    # BLA: a double-integrator-like mechanics at low frequency, with its noise level
    g_db = 20 * np.log10(np.abs(res.G))
    assert g_db[0] == pytest.approx(PINNED_G13_DB, abs=0.5)
    assert np.all(np.diff(g_db[:8]) < 0)                      # falling with frequency
    rel_noise_db = 10 * np.log10(np.median(res.var_noise / np.abs(res.G) ** 2))
    assert rel_noise_db == pytest.approx(PINNED_REL_NOISE_DB, abs=2.0)
    assert not res.transient.suspect


PINNED_G13_DB = -36.0        # |G_BLA| at 13 Hz, rad/A, measured here
PINNED_REL_NOISE_DB = -48.3  # median var_noise / |G|^2, measured here


def test_known_reference_variances_match_monte_carlo_spread():
    """var_total and var_noise of the closed-loop estimator equal the spread of G over seeds."""
    m, p, n, kp = 6, 4, 256, 4.0
    designs, one, r = multisine_table(m, n, p, 60, seed=9)
    den = A + kp * np.concatenate([B, np.zeros(A.size - B.size)])
    y_r, u_r = periodic_filter(r, kp * B, den), periodic_filter(r, kp * A, den)
    estimates, var_total, var_noise = [], [], []
    for seed in range(150):
        v = 0.05 * np.random.default_rng(seed).standard_normal(r.shape)
        res = robust_bla(u_r - periodic_filter(v, kp * A, den), y_r + periodic_filter(v, A, den),
                         r, excited_bins=designs[0].excited)
        estimates.append(res.G)
        var_total.append(res.var_total)
        var_noise.append(res.var_noise)
    estimates = np.array(estimates)
    spread = np.mean(np.abs(estimates - estimates.mean(axis=0)) ** 2, axis=0)
    assert np.mean(spread / np.mean(var_total, axis=0)) == pytest.approx(1.0, abs=0.1)
    assert np.mean(spread / np.mean(var_noise, axis=0)) == pytest.approx(1.0, abs=0.1)


def test_real_motorbench_full_grid_record_lines_found(motorbench):
    """Record A (Schroeder, full grid 11..250): the lines are found, no detection lines."""
    u = motorbench["A_iq"][None].astype(float)
    np.testing.assert_array_equal(detect_excited_lines(u, settle_periods=1),
                                  motorbench["A_excited_lines"])
    res = robust_bla(u, motorbench["A_theta_motor"][None].astype(float), fs=2500.0,
                     settle_periods=1)
    assert res.odd_bins.size == 0 and res.even_bins.size == 0
    assert res.summary["odd_re_even_db"] is None
    assert res.summary["noise_re_output_db"] == pytest.approx(-52.8, abs=1.0)
