"""Pins of the BLA's and the LPM's numbers, second set (issue 33's hand-written bug audit,
docs/testing.md): expected values computed here from the definitions (least squares by
hand, the F(2, 2q) tail), unequal and asymmetric inputs."""
import math

import numpy as np
import pytest

from fftune.analysis.bla import _drift_test


def _t_by_hand(row):
    p = row.size
    i = np.arange(p, dtype=float)
    X = np.column_stack([np.ones(p), i])
    coef, *_ = np.linalg.lstsq(X, row, rcond=None)
    rss = float(np.sum((row - X @ coef) ** 2))
    se = math.sqrt(rss / (p - 2) / np.sum((i - i.mean()) ** 2))
    return coef[1], coef[1] / se


def test_drift_test_slope_and_t_with_p_minus_2_degrees_of_freedom():
    dc = np.array([[0.10, 0.13, 0.11, 0.16, 0.15, 0.19],           # a trend in noise
                   [2.00, 1.97, 2.04, 1.99, 2.02, 1.98]])          # none
    slope, t = _t_by_hand(dc[0])
    assert 3.0 < t < 8.0
    m, s, tt = _drift_test(dc, t_limit=0.9 * t)
    assert m == 0 and s == pytest.approx(slope, rel=1e-12) and tt == pytest.approx(t, rel=1e-12)
    # just above the limit: no drift (with P instead of P - 2 the t would be sqrt(6 / 4) larger)
    assert _drift_test(dc, t_limit=1.05 * t) is None
    # the most significant realization is named, its sign kept
    dc2 = np.vstack([dc, -3 * dc[0][::-1] + 0.01 * np.array([1, -1, 2, 0, -2, 1])])
    slope2, t2 = _t_by_hand(dc2[2])
    m, s, tt = _drift_test(dc2, t_limit=1.0)
    assert m == (2 if abs(t2) > abs(t) else 0)
    assert _drift_test(dc[:, :3]) is None                             # P < 4: no test


def _one_pole(u, a, b):
    y = np.empty_like(u)
    acc = 0.0
    for i, x in enumerate(u):
        acc = a * acc + b * x
        y[i] = acc
    return y


def test_lpm_with_an_exactly_periodic_input_from_rest():
    # a generator's input (every period the same) into y[n] = 0.93 y[n-1] + 0.21 u[n] from
    # rest: the period-mean input lines are one period's DFT, G the filter's response
    from fftune.analysis.lpm import lpm_moments
    n, p = 128, 8
    rng = np.random.default_rng(4)
    bins = np.arange(3, 40, 2)
    X = np.zeros(n // 2 + 1, complex)
    X[bins] = np.exp(2j * np.pi * rng.random(bins.size))
    one = np.fft.irfft(X, n)
    u = np.tile(one, (2, p))                                   # M = 2 realizations
    u[1] *= 0.7
    y = np.vstack([_one_pole(row, 0.93, 0.21) for row in u]) + 1e-6 * rng.standard_normal(u.shape)
    band = np.arange(bins[0], bins[-1] + 1)
    mom, G_per, info = lpm_moments(u.reshape(2, p, n), y.reshape(2, p, n), band=band, excited=bins)
    assert mom.U[0] == pytest.approx(np.fft.rfft(one)[band], rel=1e-9, abs=1e-12)
    assert mom.U[1] == pytest.approx(0.7 * np.fft.rfft(one)[band], rel=1e-9, abs=1e-12)
    G_true = 0.21 / (1 - 0.93 * np.exp(-2j * np.pi * bins / n))
    assert G_per[0][0] == pytest.approx(G_true, rel=1e-3)
    assert G_per[0][1] == pytest.approx(G_true, rel=1e-3)
    # the periodic output at the excited lines: G times the input (transient removed)
    pos = np.searchsorted(band, bins)
    assert mom.Y[0][pos] == pytest.approx(G_true * np.fft.rfft(one)[bins], rel=1e-3)


def test_lpm_input_noise_through_the_plant_leaves_no_variance_of_g():
    # the measured input's own noise drives the plant: y = filter(u) exactly, so G = Y / U
    # has (almost) no variance; its propagation subtracts 2 Re(conj(G) cov_yu), the sum
    # |G|^2 var_u + var_y of the parts alone would be about 2 |G|^2 var_u
    from fftune.analysis.lpm import lpm_moments
    n, p = 128, 8
    rng = np.random.default_rng(8)
    bins = np.arange(3, 40, 2)
    X = np.zeros(n // 2 + 1, complex)
    X[bins] = np.exp(2j * np.pi * rng.random(bins.size))
    one = np.fft.irfft(X, n)
    u = np.tile(one, (2, p)) + 0.02 * rng.standard_normal((2, p * n))
    y = np.vstack([_one_pole(row, 0.93, 0.21) for row in u])
    band = np.arange(bins[0], bins[-1] + 1)
    mom, G_per, _ = lpm_moments(u.reshape(2, p, n), y.reshape(2, p, n), band=band, excited=bins)
    pos = np.searchsorted(band, bins)
    G = G_per[0]
    parts = (np.abs(G) ** 2 * mom.ss_u[:, pos] + mom.ss_y[:, pos]) / np.abs(mom.U[:, pos]) ** 2
    assert np.all(parts > 0)
    assert np.median(G_per[1] / parts) < 0.05


# ---- second round: the helpers behind the detection's figures ------------------------------------

def test_g_extrapolated_is_a_falling_power_law_of_the_top_tenth():
    from fftune.analysis.bla import _g_extrapolated2
    f = np.linspace(1.0, 40.0, 40)
    G = 5.0 * f ** -1.5 * np.exp(1j * f)
    f_at = np.array([44.0, 80.0])
    assert _g_extrapolated2(f, G, f_at) == pytest.approx((5.0 * f_at ** -1.5) ** 2, rel=1e-9)
    # a rising top is capped flat: the geometric mean of the top four |G|, squared
    G_up = 0.3 * f ** 0.7
    top = np.abs(G_up[-4:])
    assert _g_extrapolated2(f, G_up, f_at) == pytest.approx(np.exp(2 * np.mean(np.log(top))) * np.ones(2), rel=1e-9)


def test_mean_quantisation_error_against_the_gaussian_level_probabilities():
    from scipy.special import ndtr
    from fftune.analysis.bla import _mean_quantisation_error
    q, sigma = 0.01, 0.003
    s = np.linspace(-0.023, 0.031, 37)
    k = np.arange(-10, 11)[:, None]
    lo, hi = ((k - 0.5) * q - s) / sigma, ((k + 0.5) * q - s) / sigma
    expected = np.sum(k * q * (ndtr(hi) - ndtr(lo)), axis=0) - s
    assert _mean_quantisation_error(s, q, sigma) == pytest.approx(expected, abs=1e-7 * q)
    # without noise: the plain rounding error
    assert _mean_quantisation_error(s, q, 0.0) == pytest.approx(q * np.round(s / q) - s, abs=1e-15)


def test_class_stats_noise_tail_and_false_alarm_count():
    from scipy.special import bdtrc, fdtrc
    from fftune.analysis.bla import _class_stats, _false_alarm_count
    nu = 7
    level = np.array([1.0, 5.0, 2.0, 0.3, 4.5, 0.9, 1.2, 3.9, 0.8, 6.0, 1.1])
    ref = np.ones_like(level)
    st = _class_stats(level, ref, nu, "x_")
    p4 = float(fdtrc(2, 2 * nu, 4.0))                     # a noise-only line 6 dB over
    assert st["x_lines_by_noise"] == pytest.approx(level.size * p4, rel=1e-9)
    assert st["x_lines_over_noise_6db"] == 3
    for n, p in ((11, p4), (200, 0.013), (3000, 0.002), (40, 0.3)):
        need = next(k for k in range(1, n + 2) if k == n + 1 or bdtrc(k - 1, n, p) <= 1e-3)
        assert _false_alarm_count(n, p) == need, (n, p)
    assert st["x_lines_needed"] == _false_alarm_count(level.size, p4)


def test_float32_rounding_above_the_band_is_no_distortion():
    # a linear plant's output on a large offset (an encoder's absolute angle) recorded as
    # float32, exactly periodic (no noise): the lines above the band hold its rounding
    # only (-75 dB re the lines: not the 100 dB under them that is ignored outright), under
    # the floor 4 (2 r)^2 / 12 / N, r = 2^-24 max|y| (uniform within +-r): nothing detected
    from fftune.analysis.bla import robust_bla
    n, p, m = 1024, 4, 3
    rng = np.random.default_rng(17)
    bins = np.arange(1, 101)
    G = 2.0 / (1 + 1j * bins / 30.0) ** 2
    u_list, y_list = [], []
    for _ in range(m):
        X = np.zeros(n // 2 + 1, complex)
        X[bins] = np.exp(2j * np.pi * rng.random(bins.size))
        u1 = np.fft.irfft(X, n)
        Yf = np.zeros_like(X)
        Yf[bins] = G * X[bins]
        y1 = np.fft.irfft(Yf, n)
        u_list.append(np.tile(u1, p))
        y_list.append(np.tile((y1 + 1.0e4).astype(np.float32), p))
    u = np.array(u_list).reshape(m, p, n)
    y = np.array(y_list).reshape(m, p, n)
    res = robust_bla(u, y, fs=1.0, excited_bins=bins)
    s = res.summary
    assert s["above_band_lines"] > 150
    assert s["above_band_line_median_re_noise_db"] is not None      # the lines were tested
    assert s["above_band_detected"] is False, s["above_band_lines_over_noise_6db"]


def test_lpm_offsets_by_hand():
    from fftune.analysis.lpm import lpm_offsets
    # P = 4, lines at multiples of 4: the nearest non-multiples, n on each side
    assert list(lpm_offsets(8, 4, 3, 1000)) == [-3, -2, -1, 1, 2, 3]
    assert list(lpm_offsets(12, 4, 4, 1000)) == [-5, -3, -2, -1, 1, 2, 3, 5]
    # near DC only 3 below (bins 3, 2, 1): the rest above
    assert list(lpm_offsets(4, 4, 4, 1000)) == [-3, -2, -1, 1, 2, 3, 5, 6]
    # near the top (n_full 15: bins up to 14): the rest below
    assert list(lpm_offsets(12, 4, 3, 15)) == [-5, -3, -2, -1, 1, 2]


def test_lpm_reference_moments_are_its_period_mean():
    from fftune.analysis.lpm import lpm_moments
    n, p = 64, 5
    t = np.arange(n)
    r1 = np.sin(2 * np.pi * 3 * t / n) + 0.4 * np.sin(2 * np.pi * 7 * t / n + 1.0)
    r = np.tile(r1, (1, p)).reshape(1, p, n)
    u = r + 0.01 * np.random.default_rng(1).standard_normal(r.shape)
    y = 0.5 * u
    band = np.arange(3, 8)
    mom, _, _ = lpm_moments(u, y, r, band=band, excited=np.array([3, 7]))
    assert mom.R[0] == pytest.approx(np.fft.rfft(r1)[band], abs=1e-9)
    assert np.all(mom.ss_r == 0)
