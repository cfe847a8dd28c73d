"""Robust BLA: the magnitude of the nonlinear variance var_nl (issue 16).

The other BLA tests only check var_nl ~ 0 on a linear system, so var_nl = M (s2_BLA -
s2_BLA,n) without its factor M went unnoticed. Here var_nl is compared with the nonlinear
variance of ONE experiment known by construction (analytic) and with the Monte Carlo spread
of single-experiment estimates of a Wiener system (measured over many realizations).
"""
import numpy as np
import pytest

from fftune.analysis.bla import robust_bla
from fftune.analysis.multisine import multisine_realizations


def _multisine_table(m, n, k_max, seed, first_realization=0):
    designs = multisine_realizations(m + first_realization, 1.0, n, k_min=1, k_max=k_max,
                                     seed=seed, group=5)[first_realization:]
    return designs[0].excited, np.stack([d.period for d in designs])        # (M, N)


@pytest.mark.parametrize("known_reference", [False, True], ids=["known-input", "known-reference"])
def test_var_nl_equals_known_stochastic_distortion_variance(known_reference):
    """Y_m = G0 U_m + D_m + noise, D_m a periodic zero-mean random spectrum, new per realization.

    Then G_m = G0 + D_m / U_m + noise, so the nonlinear variance of one experiment is
    s2_S = E|D|^2 / |U|^2 exactly (|U| is the same at every excited line of the multisine).
    """
    m, p, n, sigma_noise = 8, 4, 256, 0.01
    excited, one = _multisine_table(m, n, 100, seed=5)
    u = np.repeat(one[:, None, :], p, axis=1)                          # (M, P, N)
    u_dft = np.abs(np.fft.rfft(one[0]))[excited]                       # |U|, DFT units
    assert np.ptp(u_dft) < 1e-9 * u_dft.max()
    g0 = 0.5 - 0.2j
    d_rms = 0.3 * u_dft[0]                                             # E|D|^2 = d_rms^2
    s2_s = d_rms ** 2 / u_dft[0] ** 2
    ratios, noise_ratios = [], []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        spec = np.zeros((m, n // 2 + 1), complex)
        spec[:, excited] = g0 * np.fft.rfft(one, axis=-1)[:, excited]
        spec[:, excited] += d_rms * (rng.standard_normal((m, excited.size))
                                     + 1j * rng.standard_normal((m, excited.size))) / np.sqrt(2)
        y_one = np.fft.irfft(spec, n=n, axis=-1)
        y = np.repeat(y_one[:, None, :], p, axis=1) + sigma_noise * rng.standard_normal(u.shape)
        res = robust_bla(u, y, u if known_reference else None, excited_bins=excited)
        ratios.append(np.mean(res.var_nl) / s2_s)
        # the noise part of the total variance is removed, not left in var_nl
        noise_ratios.append(np.mean(res.var_noise) * m / s2_s)
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.05)
    assert np.mean(noise_ratios) < 0.05


def test_var_nl_matches_monte_carlo_spread_of_wiener_system():
    """Wiener system (low-pass, then v + 0.4 v^3): var_nl of M realizations against the
    spread of the single-realization estimate G_m over 180 realizations."""
    n, k_max, m = 512, 120, 6
    excited, one = _multisine_table(180, n, k_max, seed=17)
    h = np.zeros(n // 2 + 1, complex)
    k = np.arange(n // 2 + 1)
    h[:] = 1.0 / (1.0 + 1j * k / 60.0)                                # first-order low-pass
    x = np.fft.irfft(np.fft.rfft(one, axis=-1) * h, n=n, axis=-1)
    x *= 1.5 / np.std(x)
    y = x + 0.4 * x ** 3
    g_single = (np.fft.rfft(y, axis=-1)[:, excited]
                / np.fft.rfft(one, axis=-1)[:, excited])                          # (180, E)
    spread = np.mean(np.abs(g_single - g_single.mean(axis=0)) ** 2, axis=0)        # s2_S per line
    ratios = []
    for start in range(0, 180, m):
        sl = slice(start, start + m)
        u = np.repeat(one[sl][:, None, :], 2, axis=1)
        yy = np.repeat(y[sl][:, None, :], 2, axis=1)
        yy = yy + 1e-6 * np.random.default_rng(start).standard_normal(yy.shape)
        res = robust_bla(u, yy, excited_bins=excited)
        ratios.append(np.mean(res.var_nl) / np.mean(spread))
    # 30 independent estimates of the mean nonlinear variance: their mean is within 10 %
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.1)
    # and the distortion is far above the measurement noise (a meaningful check)
    assert np.mean(spread) > 1e4 * np.mean(res.var_noise) * m


# --- input checks and helpers that mutation testing found untested (docs/testing.md) -----

import warnings  # noqa: E402

from fftune.analysis.bla import to_db  # noqa: E402
from fftune.analysis.errors import InputError  # noqa: E402


def test_to_db_values_and_no_warning_for_zero_or_negative():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = to_db([100.0, 0.0, -1.0, 1e-3])
    np.testing.assert_allclose(out[[0, 3]], [20.0, -30.0], rtol=1e-12)
    assert np.isnan(out[1]) and np.isnan(out[2])
    assert to_db(None) is None


def test_excited_bins_and_period_length_are_checked():
    n = 64
    excited, one = _multisine_table(2, n, 20, seed=1)
    u = np.repeat(one[:, None, :], 2, axis=1)
    robust_bla(u, u, excited_bins=[1, n // 2 - 1])                   # the extreme valid bins
    for bad in ([0, 5], [5, n // 2], [0, n // 2]):                   # DC, Nyquist, both
        with pytest.raises(InputError, match="bins must lie in 1 .. 31"):
            robust_bla(u, u, excited_bins=bad)
    three = np.ones((2, 2, 3))
    with pytest.raises(InputError, match="N = 3 is too small"):
        robust_bla(three, three)


# --- second round (docs/testing.md): known-reference variances, the spectra entry point,
# --- the transient check, the detection statistics, each against an independent value ------

from scipy import signal  # noqa: E402
from scipy.stats import binom  # noqa: E402

from fftune.analysis import bla as bla_mod  # noqa: E402
from fftune.analysis.bla import (TransientWarning, detect_excited_lines,  # noqa: E402
                                 estimate_quantisation_step, robust_bla_spectra)

_B, _A = signal.butter(2, 0.12)


def _periodic_filter(x):
    n = x.shape[-1]
    _, h = signal.freqz(_B, _A, worN=np.arange(n // 2 + 1) * 2 * np.pi / n)
    return np.fft.irfft(np.fft.rfft(x, axis=-1) * h, n=n, axis=-1)


def test_known_reference_noise_and_total_variance_unbiased():
    """Open loop with r = u: the known-reference variances equal the analytic noise variance
    4 sigma^2 / (N |U|^2 M P) of G (|U| the line amplitude), as the known-input ones do."""
    m, p, n, sigma = 6, 3, 256, 0.02
    excited, one = _multisine_table(m, n, 100, seed=2)
    u = np.repeat(one[:, None, :], p, axis=1)
    y0 = np.repeat(_periodic_filter(one)[:, None, :], p, axis=1)
    amp = np.abs(np.fft.rfft(one[0]))[excited] * 2 / n
    truth = 4 * sigma ** 2 / n / amp ** 2 / (m * p)
    rn, rt = [], []
    for seed in range(6):
        y = y0 + sigma * np.random.default_rng(seed).standard_normal(u.shape)
        res = robust_bla(u, y, u, excited_bins=excited)
        rn.append(np.mean(res.var_noise / truth))
        rt.append(np.mean(res.var_total / truth))
    assert np.mean(rn) == pytest.approx(1.0, abs=0.06)
    assert np.mean(rt) == pytest.approx(1.0, abs=0.12)


def test_known_reference_input_noise_through_a_linear_system_leaves_no_variance():
    """u = r + input noise, y = H u exactly per period: Y and U vary together (their
    covariance cancels the variance, first-order propagation), G = H exactly; M = P = 2."""
    m, p, n = 2, 2, 128
    excited, one = _multisine_table(m, n, 40, seed=4)
    r = np.repeat(one[:, None, :], p, axis=1)
    u = r + 0.05 * np.random.default_rng(1).standard_normal(r.shape)
    y = _periodic_filter(u)
    res = robust_bla(u, y, r, excited_bins=excited)
    _, h = signal.freqz(_B, _A, worN=2 * np.pi * excited / n)
    np.testing.assert_allclose(res.G, h, rtol=1e-9)
    assert res.var_total is not None and res.var_noise is not None
    assert np.all(np.abs(res.var_total) < 1e-12 * np.abs(h) ** 2)
    assert np.all(np.abs(res.var_noise) < 1e-12 * np.abs(h) ** 2)


def test_spectra_entry_point_equals_time_domain_one_and_checks_shapes():
    m, p, n = 3, 3, 256
    excited, one = _multisine_table(m, n, 90, seed=6)
    u = np.repeat(one[:, None, :], p, axis=1)
    y = u + 0.3 * u ** 3 + 1e-3 * np.random.default_rng(2).standard_normal(u.shape)
    ref = robust_bla(u, y, excited_bins=excited, fs=10.0)
    bins = np.arange(excited[0], excited[-1] + 1)
    U, Y = np.fft.rfft(u, axis=-1)[..., bins], np.fft.rfft(y, axis=-1)[..., bins]
    res = robust_bla_spectra(U, Y, bins=bins, n_period=n, fs=10.0, excited_bins=excited)
    for name in ("G", "var_total", "var_noise", "var_nl", "odd_db", "even_db"):
        np.testing.assert_allclose(getattr(res, name), getattr(ref, name), rtol=1e-9, atol=0)
    assert res.summary["odd_detected"] == ref.summary["odd_detected"] is True
    for U_bad, Y_bad in ((U[0], Y[0]), (U, Y[..., :-1]), (U, Y[:, :2])):
        with pytest.raises(InputError, match="spectra"):
            robust_bla_spectra(U_bad, Y_bad, bins=bins, n_period=n, excited_bins=excited)


@pytest.mark.parametrize("p", [6, 3])
def test_transient_reference_is_the_median_of_the_later_kept_periods(p):
    """expected_db: the median level of the kept periods after the first (documented), and
    the message quotes it."""
    n, settle = 256, 0
    excited, one = _multisine_table(2, n, 60, seed=2)
    u = np.repeat(one[:, None, :], p + settle, axis=1)
    b, a = signal.butter(2, 0.01)
    y = signal.lfilter(b, a, u.reshape(2, -1), axis=-1).reshape(u.shape)
    y = y + 1e-6 * np.random.default_rng(3).standard_normal(y.shape)
    res = robust_bla(u, y, settle_periods=settle, excited_bins=excited, warn_transient=False)
    tr = res.transient
    level = np.nan_to_num(10 ** (tr.level_db / 10))          # NaN dB: no power (to_db)
    noise = np.median(level[settle + 1:])
    np.testing.assert_allclose(tr.expected_db, 10 * np.log10(noise), rtol=1e-12)
    assert p < 6 or (tr.suspect and f"{10 * np.log10(noise):.1f} dB: transient" in tr.message
                     and f"by {10 * np.log10(level[settle]):.1f} dB re the output" in tr.message)
    # the steady state is the mean of the last half of the kept periods: the level of a
    # period is the mean over lines of |Y - centre|^2 re the mean of |centre|^2
    Y = np.fft.rfft(y, axis=-1)[..., excited]
    centre = Y[:, -(p // 2):, :].mean(axis=1, keepdims=True)
    d = np.mean(np.abs(Y - centre) ** 2, axis=(0, 2))
    np.testing.assert_allclose(level, d / np.mean(np.abs(centre) ** 2), rtol=1e-9)


def test_otsu_threshold_and_false_alarm_count_against_definitions():
    thr, sep = bla_mod._otsu(np.array([0.0, 0.1, 0.2, 0.3, 10.0, 10.2, 10.4]))
    assert thr == pytest.approx((0.3 + 10.0) / 2) and sep == pytest.approx(10.2 - 0.15)
    for n_lines, p in ((40, 0.02), (400, 0.0183), (7, 0.3)):
        k = bla_mod._false_alarm_count(n_lines, p, 1e-3)
        assert binom.sf(k - 1, n_lines, p) <= 1e-3 and (k == 1 or binom.sf(k - 2, n_lines, p) > 1e-3)
    assert bla_mod._false_alarm_count(0, 0.1) is None


def test_class_stats_against_their_definitions():
    rng = np.random.default_rng(0)
    ref = rng.uniform(1.0, 2.0, 50)
    level = ref * np.concatenate([np.full(45, 0.5), [8.0, 9.0, 10.0, 5.0, 3.5]])
    nu = 6
    out = bla_mod._class_stats(level, ref, nu, "x_")
    ratio = level / ref
    assert out["x_line_median_re_noise_db"] == pytest.approx(np.median(10 * np.log10(ratio)))
    assert out["x_lines_over_noise_6db"] == int(np.sum(ratio > 4.0)) == 4
    p_line = (1 + 4.0 / nu) ** -nu
    assert out["x_lines_by_noise"] == pytest.approx(50 * p_line)
    need = out["x_lines_needed"]
    assert binom.sf(need - 1, 50, p_line) <= 1e-3 < binom.sf(need - 2, 50, p_line)
    strongest = 50 * (1 + 10.0 / nu) ** -nu <= 1e-3
    assert out["x_detected"] == (4 >= need or strongest)
    # one line far above the noise alone is a detection (Bonferroni)
    one = bla_mod._class_stats(np.append(np.full(20, 1.0), 1e4), np.ones(21), 8, "y_")
    assert one["y_lines_over_noise_6db"] == 1 and one["y_detected"] is True
    assert bla_mod._class_stats(level, None, nu, "z_")["z_detected"] is None


def test_plant_state_unsure_between_noise_and_detection():
    base = {"plant_odd_detected": False, "plant_odd_lines_by_noise": 0.3,
            "plant_odd_lines_needed": 5}
    state = lambda over: bla_mod._plant_state(dict(base, plant_odd_lines_over_noise_6db=over), "odd")  # noqa: E731
    assert state(0) == "no" and state(1) == "no" and state(2) == "unsure"
    assert bla_mod._plant_state(dict(base, plant_odd_detected=True,
                                     plant_odd_lines_over_noise_6db=6), "odd") == "yes"
    assert bla_mod._plant_state({"plant_odd_detected": None}, "odd") is None


def test_interp_frf_exact_for_power_laws():
    """log-log interpolation is exact for a power law (double integrator), with 4 lines
    (linear) and with more (Lagrange), and its leave-one-out error is then 0."""
    for e in (4, 5, 9):
        f = np.geomspace(1.0, 50.0, e)
        g = 1.0 / (1j * 2 * np.pi * f) ** 2 * np.exp(-0.0j)
        f_at = np.sqrt(f[:-1] * f[1:])
        g_at, loo = bla_mod._interp_frf(f, g, f_at)
        np.testing.assert_allclose(g_at, 1.0 / (1j * 2 * np.pi * f_at) ** 2, rtol=1e-9)
        if e >= 5:
            assert np.max(loo) < 1e-9
    f = np.geomspace(1.0, 50.0, 4)
    g = 1.0 / (1j * 2 * np.pi * f)
    g_at, _ = bla_mod._interp_frf(f, g, np.sqrt(f[:-1] * f[1:]))
    np.testing.assert_allclose(g_at, 1.0 / (1j * 2 * np.pi * np.sqrt(f[:-1] * f[1:])), rtol=1e-9)


def test_summary_line_figures_against_the_arrays():
    """line_fraction_nl_over_noise_6db and odd_re_even_db (the one odd-re-even figure: a
    power ratio, issue 23) from the result's own per-line arrays (Figure 3)."""
    m, p, n = 6, 4, 1024
    excited, one = _multisine_table(m, n, 200, seed=3)
    x = _periodic_filter(one)
    y = np.repeat((x + 0.3 * x ** 3 + 0.1 * x ** 2)[:, None, :], p, axis=1)
    u = np.repeat(one[:, None, :], p, axis=1)
    res = robust_bla(u, y + 1e-3 * np.random.default_rng(0).standard_normal(y.shape),
                     excited_bins=excited)
    s = res.summary
    nu = m * (p - 1)                       # complex degrees of freedom of the noise estimate
    assert s["odd_lines_by_noise"] == pytest.approx(res.odd_bins.size * (1 + 4 / nu) ** -nu)
    assert s["plant_above_noise_lines"] == int(np.sum(res.plant_db > res.plant_expected_db
                                                      + 10 * np.log10(4.0)))
    nl = np.where(np.isnan(res.nl_db), -np.inf, res.nl_db)
    assert s["line_fraction_nl_over_noise_6db"] == pytest.approx(
        np.mean(nl > res.noise_db + 10 * np.log10(4.0)))
    assert 0.0 < s["line_fraction_nl_over_noise_6db"] <= 1.0
    assert "line_median_odd_re_even_db" not in s
    assert s["odd_re_even_db"] == pytest.approx(
        10 * np.log10(np.mean(10 ** (res.odd_db / 10)) / np.mean(10 ** (res.even_db / 10))))


def test_sample_rate_must_be_positive_and_finite():
    excited, one = _multisine_table(2, 64, 20, seed=1)
    u = np.repeat(one[:, None, :], 2, axis=1)
    for fs in (0.0, -1.0, np.inf, np.nan):
        with pytest.raises(InputError, match="fs must be"):
            robust_bla(u, u, fs=fs, excited_bins=excited)



def test_levels_are_line_amplitudes_in_db():
    """output_db of a linear system: 20 log10 of the output line amplitude |H| a (a the
    multisine's line amplitude, |DFT| 2 / N)."""
    m, p, n = 2, 2, 256
    excited, one = _multisine_table(m, n, 60, seed=8)
    u = np.repeat(one[:, None, :], p, axis=1)
    res = robust_bla(u, _periodic_filter(u), excited_bins=excited)
    amp = np.abs(np.fft.rfft(one[0]))[excited] * 2 / n
    _, h = signal.freqz(_B, _A, worN=2 * np.pi * excited / n)
    np.testing.assert_allclose(res.output_db, 20 * np.log10(np.abs(h) * amp), atol=1e-9)


def test_known_reference_with_one_realization_or_one_period():
    excited, one = _multisine_table(1, 128, 40, seed=3)
    u = np.repeat(one[:, None, :], 3, axis=1)
    y = _periodic_filter(u) + 1e-3 * np.random.default_rng(0).standard_normal(u.shape)
    res = robust_bla(u, y, u, excited_bins=excited)
    assert res.var_total is None and res.var_nl is None and res.var_noise is not None
    excited, one = _multisine_table(3, 128, 40, seed=3)
    u = one[:, None, :]
    res = robust_bla(u, _periodic_filter(u), u, excited_bins=excited)
    assert res.var_noise is None and res.var_nl is None and res.var_total is not None


@pytest.mark.parametrize("ringing", [-1, 0], ids=["top", "bottom"])
def test_transient_check_covers_the_top_of_a_wide_band(ringing):
    """More than 256 excited lines: the check samples lines over the whole band, the first
    and the last one included (a lightly damped mode at an end of the band still rings)."""
    m, periods, lines = 2, 6, 400
    bins = np.arange(10, 10 + 2 * lines, 2)                  # every other line excited
    band = np.arange(bins[0], bins[-1] + 1)
    rng = np.random.default_rng(0)
    U = np.zeros((m, periods, band.size), complex)
    U[..., ::2] = np.exp(2j * np.pi * rng.random((m, 1, lines)))
    Y = 0.5 * U + 1e-9 * (rng.standard_normal(U.shape) + 1j * rng.standard_normal(U.shape))
    Y[:, :, ringing] += 30.0 * np.exp(-1.5 * np.arange(periods))[None, :]   # one end decays
    res = robust_bla_spectra(U, Y, bins=band, n_period=4096, excited_bins=bins,
                             warn_transient=False)
    assert res.transient.suspect


def test_transient_settle_periods_and_short_records():
    """settle_differs compares the LAST settle period; with P < 3 kept periods there is no
    noise reference (expected_db None)."""
    n = 128
    excited, one = _multisine_table(2, n, 30, seed=5)
    u = np.repeat(one[:, None, :], 6, axis=1)
    y = np.repeat(_periodic_filter(one)[:, None, :], 6, axis=1)
    y = y + 1e-6 * np.random.default_rng(0).standard_normal(y.shape)
    y[:, 0] += 5.0 * np.random.default_rng(1).standard_normal((2, n))   # only period 0 is off
    res = robust_bla(u, y, settle_periods=2, excited_bins=excited, warn_transient=False)
    assert res.transient.settle_differs is False and not res.transient.suspect
    res = robust_bla(u, y, settle_periods=1, excited_bins=excited, warn_transient=False)
    assert res.transient.settle_differs is True
    res = robust_bla(u[:, :4], y[:, :4], settle_periods=2, excited_bins=excited)
    assert res.transient.expected_db is None and res.transient.settle_differs is None


def test_interp_frf_uses_the_neighbouring_lines_at_the_band_edges():
    """A first-order low-pass (not a power law): 4-point interpolation from the nearest
    lines is accurate at the lowest and highest gaps too."""
    f = np.geomspace(1.0, 100.0, 12)
    lowpass = lambda ff: 1.0 / (1.0 + 1j * ff / 10.0)  # noqa: E731
    f_at = np.array([np.sqrt(f[0] * f[1]), np.sqrt(f[-2] * f[-1])])
    g_at, _ = bla_mod._interp_frf(f, lowpass(f), f_at)
    np.testing.assert_allclose(g_at, lowpass(f_at), rtol=4e-4)   # wrapped points: 8e-4


def test_spectra_must_hold_every_line_of_the_band():
    n = 64
    excited = np.array([5, 7, 9, 11])
    bins = np.array([5, 6, 7, 9, 10, 11])                      # 8 missing
    U = np.ones((2, 2, bins.size), complex)
    with pytest.raises(InputError, match=r"every line 5 \.\. 11"):
        robust_bla_spectra(U, U, bins=bins, n_period=n, excited_bins=excited)


def test_zero_power_message_lists_five_lines_then_dots():
    excited, one = _multisine_table(2, 128, 40, seed=1)
    u = np.repeat(one[:, None, :], 2, axis=1)
    bad = np.append(excited, [42, 44, 46, 48, 50, 52])
    with pytest.raises(InputError, match=r"zero power at 6 excited line\(s\) 42 Hz, 44 Hz, 46 Hz, "
                                         r"48 Hz, 50 Hz \.\.\. "):
        robust_bla(u, u, fs=128.0, excited_bins=bad)


def test_float32_record_rounding_floor_at_the_nonexcited_lines():
    """An exactly periodic float32 record: no spread over the periods, so the noise at the
    non-excited lines is the rounding floor 4 (q^2 / 12) / N with q = 2 max|y| 2^-24."""
    n, p = 256, 3
    excited, one = _multisine_table(2, n, 100, seed=7)
    u = np.repeat(one[:, None, :], p, axis=1)
    y = (u + 0.2 * u ** 3).astype(np.float32)
    res = robust_bla(u, y, excited_bins=excited)
    q = 2 * float(np.max(np.abs(y))) * 2.0 ** -24
    np.testing.assert_allclose(res.nonexcited_noise_db, 10 * np.log10(4 * q ** 2 / 12 / n), atol=1e-6)


def test_summary_noise_re_output_median_against_the_arrays():
    excited, one = _multisine_table(3, 256, 80, seed=2)
    u = np.repeat(one[:, None, :], 3, axis=1)
    y = u + 0.1 * u ** 3 + 1e-2 * np.random.default_rng(5).standard_normal(u.shape)
    s = robust_bla(u, y, excited_bins=excited)
    assert s.summary["line_median_noise_re_output_db"] == pytest.approx(
        np.median(s.noise_db - s.output_db))
    assert s.summary["line_median_noise_re_output_db"] < -20


_LINEAR = {"odd_detected": False, "even_detected": False, "nl_detected": False,
           "parity_classifiable": True, "plant_odd_detected": False, "plant_even_detected": False,
           "plant_odd_lines_over_noise_6db": 0, "plant_odd_lines": 20, "plant_odd_lines_needed": 5,
           "plant_odd_lines_by_noise": 0.4, "plant_even_lines_over_noise_6db": 1,
           "plant_even_lines": 80, "plant_even_lines_needed": 9, "plant_even_lines_by_noise": 1.6,
           "quantisation_floor_db": None}


def test_level_verdict_every_cause_and_its_text():
    v = bla_mod.level_verdict({"odd_detected": None, "even_detected": None, "nl_detected": None,
                               "periods": 1, "realizations": 4, "nonexcited_lines": 30})
    assert v == {"causes": ["cannot tell"], "text": "cannot tell: no noise estimate (P = 1 period)"}
    v = bla_mod.level_verdict({"odd_detected": None, "even_detected": None, "nl_detected": None,
                               "periods": 5, "realizations": 1, "nonexcited_lines": 0})
    assert v["text"] == ("cannot tell: no nonlinear variance (M = 1 realization) and no "
                         "non-excited line in the band")
    v = bla_mod.level_verdict(_LINEAR, None, "1 V rms")
    assert v == {"causes": ["linear"],
                 "text": "linear at 1 V rms: no nonlinear distortion above the noise"}
    v = bla_mod.level_verdict(_LINEAR, 0.02)
    assert v["causes"] == ["linear"] and v["text"].endswith("(though 2 % of the samples at u_max)")
    # a plant odd nonlinearity: named, with its counts and median
    odd = dict(_LINEAR, odd_detected=True, nl_detected=True, plant_odd_detected=True,
               plant_odd_lines_over_noise_6db=12, plant_odd_line_median_re_noise_db=9.25)
    v = bla_mod.level_verdict(odd, 0.0, "3 V rms")
    assert v["causes"] == ["plant odd nonlinearity"]
    assert v["text"] == ("plant odd nonlinearity (12 of 20 odd lines 6 dB over what noise, BLA "
                         "interpolation and quantisation explain, median +9.2 dB)")
    v = bla_mod.level_verdict(dict(odd, plant_odd_line_median_re_noise_db=None), 0.01)
    assert v["causes"] == ["plant odd nonlinearity", "drive output saturation"]
    assert "explain); also drive output saturation (1 % of the samples at u_max)" in v["text"]
    # the loop is nonlinear, the plant-referred lines are not: named by what is known
    loop = dict(_LINEAR, odd_detected=True, nl_detected=True)
    v = bla_mod.level_verdict(loop, 0.004, "3 V rms")
    assert v["causes"] == ["drive output saturation"]
    assert v["text"].startswith("odd lines: drive output saturation at 3 V rms (0.4 % of the "
                                "samples at u_max); the distortion enters at the plant input")
    v = bla_mod.level_verdict(dict(_LINEAR, nl_detected=True), 0.0)
    assert v["causes"] == ["loop nonlinearity outside the plant"]
    assert v["text"].startswith("non-excited lines: distortion in the loop")
    v = bla_mod.level_verdict(dict(loop, quantisation_floor_db=-85.0), 0.0)
    assert v["causes"] == ["quantisation floor"] and "(-85.0 dB per line)" in v["text"]
    # no parity with this grid: the whole non-excited class
    full = {"odd_detected": None, "even_detected": None, "nl_detected": True,
            "parity_classifiable": False, "grid": "full with removed lines",
            "plant_nonexcited_detected": True, "plant_nonexcited_lines_over_noise_6db": 7,
            "plant_nonexcited_lines": 30, "plant_nonexcited_lines_needed": 3,
            "plant_nonexcited_line_median_re_noise_db": -1.0, "quantisation_floor_db": None}
    v = bla_mod.level_verdict(full)
    assert v["causes"] == ["plant nonlinearity (parity not classifiable with this grid)"]
    assert v["text"] == ("plant nonlinearity, (parity not classifiable with this grid) (7 of 30 "
                         "lines 6 dB over what noise, BLA interpolation and quantisation explain, "
                         "median -1.0 dB); no odd/even claim: full with removed lines grid")
    # some lines over the noise, too few to tell
    v = bla_mod.level_verdict(dict(loop, plant_odd_lines_over_noise_6db=3), 0.0)
    assert v["causes"] == ["cannot tell"]
    assert v["text"] == ("cannot tell whether the plant is nonlinear at the odd lines: 3 of 20 "
                         "over the noise, 5 needed (more detection lines: a longer period or a "
                         "wider band)")
    # by_noise above 0.5 widens "no": 3 over with 1.6 expected from noise
    assert bla_mod._plant_state(dict(_LINEAR, plant_even_lines_over_noise_6db=3), "even") == "no"


def test_tiny_signals_and_bad_settle_and_bins_messages():
    """Detection is scale invariant (a 1e-6 multisine is not "zero power"); settle periods
    must be >= 0; the bin range error quotes the range given."""
    designs = multisine_realizations(2, 1.0, 256, k_min=1, k_max=60, seed=4, rms=1e-6)
    u = np.repeat(np.stack([d.period for d in designs])[:, None, :], 2, axis=1)
    np.testing.assert_array_equal(detect_excited_lines(u), designs[0].excited)
    with pytest.raises(InputError, match=r"settle periods T = -1 must be in 0 \.\. 1 "):
        robust_bla(u, u, settle_periods=-1)
    with pytest.raises(InputError, match=r"got 0 \.\. 5"):
        robust_bla(u, u, excited_bins=[0, 3, 5])


def test_odd_grid_without_odd_detection_lines_has_no_odd_re_even_median():
    """Every odd bin excited: no non-excited odd line, so no odd/even median (None)."""
    n = 128
    excited = np.arange(1, 40, 2)
    rng = np.random.default_rng(0)
    spec = np.zeros(n // 2 + 1, complex)
    spec[excited] = np.exp(2j * np.pi * rng.random(excited.size))
    one = np.fft.irfft(spec, n=n)
    u = np.tile(one, (2, 2, 1))
    res = robust_bla(u, u + 0.1 * u ** 2 + 1e-6 * rng.standard_normal(u.shape), excited_bins=excited)
    assert res.odd_bins.size == 0 and res.even_bins.size > 0
    assert res.summary["odd_re_even_db"] is None


def test_spectra_transient_warning_points_at_the_caller():
    m, periods = 2, 6
    bins = np.arange(10, 40)
    excited = bins[::2]
    U = np.zeros((m, periods, bins.size), complex)
    U[..., ::2] = 1.0
    Y = 0.5 * U
    Y[:, 0, ::2] += 5.0
    with pytest.warns(TransientWarning) as rec:
        robust_bla_spectra(U, Y, bins=bins, n_period=256, excited_bins=excited)
    assert rec[0].filename == __file__


def test_line_detection_gap_and_empty_lines_and_few_levels():
    """separation_db is the largest gap between the sorted line levels (dB); an empty line
    list is refused; two distinct values are too few to call a signal quantised."""
    excited, one = _multisine_table(2, 256, 60, seed=9)
    x = np.repeat(one[:, None, :], 2, axis=1) + 1e-5 * np.random.default_rng(0).standard_normal((2, 2, 256))
    found, info = detect_excited_lines(x, return_info=True)
    np.testing.assert_array_equal(found, excited)
    spec = np.fft.rfft(x.sum(axis=1), axis=-1)
    level = np.sort(10 * np.log10(np.mean(np.abs(spec) ** 2, axis=0)[1:128]))
    assert info["separation_db"] == pytest.approx(np.max(np.diff(level)), rel=1e-9)
    with pytest.raises(InputError, match="none given"):
        robust_bla(x, x, excited_bins=[])
    assert estimate_quantisation_step(np.array([0.0, 0.5, 0.5, 0.0])) is None
    steps = np.arange(5) * 0.25
    assert estimate_quantisation_step(steps) == pytest.approx(0.25)
    assert estimate_quantisation_step(steps, max_levels=4) is None


def test_otsu_maximises_the_between_class_variance():
    v = np.sort(np.random.default_rng(3).uniform(0.0, 1.0, 60) ** 2)
    scores = [k * (v.size - k) * (v[k:].mean() - v[:k].mean()) ** 2 for k in range(1, v.size)]
    k = 1 + int(np.argmax(scores))
    thr, _ = bla_mod._otsu(v)
    assert thr == pytest.approx((v[k - 1] + v[k]) / 2)


def test_notes_reference_checks_and_level_lists():
    excited, one = _multisine_table(2, 128, 40, seed=1)
    u = np.repeat(one[:, None, :], 2, axis=1)
    res = robust_bla(u, u, fs=128.0)
    assert f"{excited.size} lines {excited[0]:g} .. {excited[-1]:g} Hz" in res.notes[0]
    assert res.var_total is not None                     # known input, M = 2
    # the reference's zero power is checked per line; a weak line (1e-5) is not zero
    r = u.copy()
    spec = np.fft.rfft(r, axis=-1)
    spec[..., excited[3]] *= 1e-5
    r_weak = np.fft.irfft(spec, n=128, axis=-1)
    assert robust_bla(u, u, r_weak, excited_bins=excited).known_reference
    spec[..., excited[3]] = 0
    with pytest.raises(InputError, match=r"reference r: zero power at 1 excited line"):
        robust_bla(u, u, np.fft.irfft(spec, n=128, axis=-1), excited_bins=excited)
    # the quantisation model: the error of quantising the predicted periodic output
    # (issue 23: not the white floor 4 (q^2 / 12) / N); a step far above the signal gives
    # an error -u itself, at the lines where the output is
    res = robust_bla(u, u, excited_bins=excited, y_quantisation_step=0.01)
    assert res.summary["quantisation_model"].startswith("periodic")
    assert res.quantisation_db.shape == res.nonexcited_bins.shape
    with pytest.raises(InputError, match="same number of levels"):
        bla_mod.bla_levels([u, u], [u])


def test_one_excited_odd_line_is_an_odd_grid_not_odd_odd():
    from fftune.analysis.bla import classify_grid
    assert classify_grid([5], 64)["grid"] == "odd"
    assert classify_grid([5, 9, 13], 64)["grid"] == "odd-odd"


def test_small_helpers_by_definition():
    from fftune.analysis.bla import classify_grid
    assert classify_grid([2, 4, 8], 64)["grid"] == "even"
    assert bla_mod._median_db([np.nan, 1.0, 2.0]) == 1.0          # NaN counts as -inf
    # a line with no power at all is no detection
    out = bla_mod._class_stats(np.append(np.ones(30), 0.0), np.ones(31), 6, "z_")
    assert out["z_detected"] is False
    # 4 lines over with 1.6 expected from noise: more than 2 x 1.6, fewer than needed
    s = {"plant_odd_detected": False, "plant_odd_lines_by_noise": 1.6,
         "plant_odd_lines_needed": 9, "plant_odd_lines_over_noise_6db": 4}
    assert bla_mod._plant_state(s, "odd") == "unsure"


def test_spectra_default_rate_and_a_reference_line_120_db_down_is_zero():
    excited, one = _multisine_table(2, 128, 40, seed=1)
    u = np.repeat(one[:, None, :], 2, axis=1)
    bins = np.arange(excited[0], excited[-1] + 1)
    U = np.fft.rfft(u, axis=-1)[..., bins]
    res = robust_bla_spectra(U, U, bins=bins, n_period=128, excited_bins=excited)
    np.testing.assert_allclose(res.freq, excited / 128)               # fs = 1 by default
    spec = np.fft.rfft(u, axis=-1)
    spec[..., excited[3]] *= 1e-7
    with pytest.raises(InputError, match=r"reference r: zero power at 1 excited line"):
        robust_bla(u, u, np.fft.irfft(spec, n=128, axis=-1), excited_bins=excited)


# --- round 3 (issue 16): survivors of the complete run after the line-moments refactor -----
from fftune.analysis.bla import _class_stats, _local_floor, _transient, classify_grid  # noqa: E402


def test_local_floor_is_the_tenth_percentile_of_plus_minus_24_lines():
    level = np.random.default_rng(3).normal(size=300).cumsum()
    padded = np.pad(level, 24, mode="reflect")
    brute = [np.quantile(padded[i:i + 49], 0.1) for i in range(level.size)]
    np.testing.assert_allclose(_local_floor(level), brute, rtol=0, atol=1e-12)


def _lines_excitation(n, excited, gap_db, m=2, p=2, seed=0):
    """Periodic excitation: the excited bins at 0 dB, every other bin gap_db below."""
    rng = np.random.default_rng(seed)
    spec = np.zeros((m, n // 2 + 1), complex)
    amp = np.full(n // 2 + 1, 10 ** (-gap_db / 20))
    amp[excited] = 1.0
    amp[0] = 0.0
    if n % 2 == 0:
        amp[n // 2] = 0.0
    spec[:] = amp * np.exp(2j * np.pi * rng.random((m, n // 2 + 1)))
    one = np.fft.irfft(spec, n=n, axis=-1)
    return np.repeat(one[:, None, :], p, axis=1)


def test_line_detection_default_gap_is_10_db_and_reaches_the_top_bin():
    n = 64                                              # 31 usable lines: no local threshold
    excited = np.array([3, 7, 11, 19, 23, 31])          # 31 = the top usable bin
    np.testing.assert_array_equal(detect_excited_lines(_lines_excitation(n, excited, 10.5)), excited)
    with pytest.raises(InputError, match="cannot tell"):
        detect_excited_lines(_lines_excitation(n, excited, 9.5))
    np.testing.assert_array_equal(
        detect_excited_lines(_lines_excitation(n, excited, 9.5), min_gap_db=9.0), excited)
    odd = np.array([3, 7, 11, 32])                      # N = 65: the top bin is 32
    np.testing.assert_array_equal(detect_excited_lines(_lines_excitation(65, odd, 30.0)), odd)


def test_transient_check_with_one_kept_period_compares_the_settle_period_with_it():
    """T = 1, P = 1: the steady state is the one kept period; the settle period's level
    is its difference from it (finite), the kept one's 0."""
    y = np.ones((2, 2, 3), complex)
    y[:, 0] *= 1.1
    check = _transient(y, 1, 1)
    assert check.level_db[0] == pytest.approx(10 * np.log10(0.01)) and not check.suspect


@pytest.mark.parametrize("factor, suspect", [(10.5, True), (9.5, False)])
def test_transient_flags_a_first_period_10_times_the_later_ones(factor, suspect):
    """T = 1 settle period and P = 5: the first kept period's level re the steady state
    (the mean of the last 2) against 10 times the median of the later kept ones (and the
    settle period's too)."""
    base, d = np.ones(4, complex), 1e-3 * np.exp(0.7j)
    periods = np.stack([base + np.sqrt(factor) * d, base + np.sqrt(factor) * d,
                        base + d, base - d, base + d, base - d])
    check = _transient(periods[None], 1, 5)
    np.testing.assert_allclose(10 ** (check.level_db / 10), [factor * 1e-6, factor * 1e-6] + [1e-6] * 4,
                               rtol=1e-6)
    assert check.suspect is suspect and check.settle_differs is suspect


def test_odd_odd_grid_starting_below_4():
    assert classify_grid(np.array([3, 7, 11, 15]), 64)["grid"] == "odd-odd"
    assert classify_grid(np.array([1, 5, 9, 13]), 64)["grid"] == "odd-odd"


def test_one_line_far_above_its_noise_is_detected_alone():
    """A single line 20 times its noise with nu = 12: one line is too few for the count
    rule (2 needed), but (1 + 20/12)^-12 = 8e-6 <= alpha alone (Bonferroni)."""
    out = _class_stats(np.array([20.0]), np.array([1.0]), 12, "x_")
    assert out["x_lines_over_noise_6db"] == 1 and out["x_lines_needed"] == 2
    assert out["x_detected"] is True
    assert _class_stats(np.array([5.0]), np.array([1.0]), 12, "x_")["x_detected"] is False


def test_lines_over_noise_exactly_as_many_as_needed_is_detected():
    nu, n = 12, 50
    p_line = (1 + 4.0 / nu) ** (-nu)
    need = int(binom.isf(1e-3, n, p_line)) + 1
    level = np.ones(n)
    level[:need] = 4.5                                  # 6 dB over, not enough alone
    out = _class_stats(level, np.ones(n), nu, "x_")
    assert out["x_lines_over_noise_6db"] == out["x_lines_needed"] == need
    assert out["x_detected"] is True


def _distorted_excitation(n=512, m=2, p=2, floor_db=-40.0, seed=5, k_max=201, offset=20.0):
    """Excited lines falling by 44 dB over the band and a broadband distortion floor_db
    under them everywhere: the sorted levels have no clean gap."""
    from fftune.analysis.multisine import drive_lines
    excited = drive_lines(n, 3, k_max, 4, seed).excited
    k = np.arange(n // 2 + 1)
    level_db = -40 * np.log10(k + offset)
    amp = 10 ** ((level_db + floor_db) / 20)
    amp[excited] = 10 ** (level_db[excited] / 20)
    amp[0] = amp[n // 2] = 0.0
    rng = np.random.default_rng(seed)
    spec = amp * np.exp(2j * np.pi * rng.random((m, k.size)))
    one = np.fft.irfft(spec, n=n, axis=-1)
    return excited, np.repeat(one[:, None, :], p, axis=1)


def test_distorted_excitation_found_by_the_local_threshold_and_the_note_says_how_sure():
    excited, x = _distorted_excitation()
    found, info = detect_excited_lines(x, return_info=True)
    np.testing.assert_array_equal(found, excited)
    assert info["method"] == "local threshold" and info["separation_db"] >= 20.0
    # the note's share of lines within 3 dB of the threshold, by its definition
    n = x.shape[2]
    power = np.mean(np.abs(np.fft.rfft(x.sum(axis=1), axis=-1)) ** 2, axis=0)[1:(n + 1) // 2]
    level = 10 * np.log10(np.maximum(power, power.max() * 1e-12))
    rel = level - _local_floor(level)
    thr, _ = bla_mod._otsu(rel)
    share = np.mean(np.abs(rel - thr) < 3.0)
    assert share <= 0.05
    assert f"{100 * share:.1f} % of the lines lie within 3 dB" in info["note"]
    # robust_bla puts the line note right after the "found from the spectrum" note
    res = robust_bla(x, 0.5 * x, warn_transient=False)
    assert res.notes[0].startswith("excited lines found from the spectrum of u")
    assert res.notes[1] == info["note"]
    # the local floor needs 64 lines or more (N = 130); with 63 (N = 128) no threshold
    small = dict(k_max=50, offset=10.0, floor_db=-30.0)
    excited, x = _distorted_excitation(n=130, **small)
    np.testing.assert_array_equal(detect_excited_lines(x), excited)
    with pytest.raises(InputError, match="cannot tell"):
        detect_excited_lines(_distorted_excitation(n=128, **small)[1])


def test_line_detection_zero_input_says_so():
    with pytest.raises(InputError, match="zero power"):
        detect_excited_lines(np.zeros((1, 2, 64)))


def test_top_bin_of_an_odd_period_is_a_valid_excited_line():
    n = 65
    excited = np.array([3, 7, 11, 19, 23, 32])
    x = _lines_excitation(n, excited, 40.0, m=2, p=2)
    res = robust_bla(x, 2.0 * x, excited_bins=excited, warn_transient=False)
    np.testing.assert_array_equal(res.bins, excited)
    np.testing.assert_allclose(res.G, 2.0, rtol=1e-9)
    assert res.fs == 1.0 and res.freq[-1] == pytest.approx(32 / 65)        # default fs 1 Hz


def test_five_excited_lines_are_enough_for_the_plant_referred_figures():
    n = 64
    excited = np.array([3, 7, 11, 19, 23])
    x = _lines_excitation(n, excited, 200.0, m=2, p=3)
    rng = np.random.default_rng(0)
    res = robust_bla(x, 2.0 * x + 1e-6 * rng.standard_normal(x.shape), excited_bins=excited,
                     warn_transient=False)
    assert res.plant_db is not None and res.plant_db.size == res.nonexcited_bins.size


def test_line_moments_need_one_period_and_have_no_settle_periods():
    from fftune.analysis.bla import LineMoments, robust_bla_moments
    e = np.array([3, 5, 7, 9, 11])
    band = np.arange(3, 12)
    rng = np.random.default_rng(1)
    U = np.exp(2j * np.pi * rng.random((2, band.size)))
    z = np.zeros((2, band.size))
    mom = LineMoments(bins=band, n_periods=2, U=U, Y=2 * U, ss_u=z + 1e-6, ss_y=z + 4e-6,
                      s_yu=z + 2e-6 + 0j, R=U, ss_r=z)
    res = robust_bla_moments(mom, n_period=64, excited_bins=e)
    np.testing.assert_allclose(res.G, 2.0, rtol=1e-12)
    assert res.settle_periods == 0 and res.n_periods == 2 and res.fs == 1.0
    with pytest.raises(InputError, match="P = 0 periods"):
        robust_bla_moments(LineMoments(**{**mom.__dict__, "n_periods": 0}), n_period=64,
                           excited_bins=e)


def test_negative_nonlinear_variance_is_noted_only_where_it_occurs():
    n, m, p = 256, 4, 4
    excited, table = _multisine_table(m, n, 60, seed=2)
    u = np.repeat(table[:, None, :], p, axis=1)
    rng = np.random.default_rng(4)
    noisy = robust_bla(u, u + 0.05 * rng.standard_normal(u.shape), excited_bins=excited)
    assert noisy.var_nl_negative.any()
    assert any(note.startswith(f"var_nl < 0 at {int(noisy.var_nl_negative.sum())} of")
               for note in noisy.notes)
    distorted = robust_bla(u, u + 0.3 * u ** 3 + 1e-6 * rng.standard_normal(u.shape),
                           excited_bins=excited)
    assert not distorted.var_nl_negative.any()
    assert not any(note.startswith("var_nl < 0") for note in distorted.notes)


def test_quantisation_step_of_a_float32_record_far_from_zero():
    """Multiples of q = 1 mrad stored as float32, some at 5000 rad: their float32 rounding
    (up to 0.24 q there) is allowed, the step is still found."""
    k = np.r_[np.arange(60), 5_000_000, 5_000_003]
    v = (k * 1e-3).astype(np.float32)
    assert bla_mod.estimate_quantisation_step(v) == pytest.approx(1e-3, rel=1e-6)
    assert bla_mod.estimate_quantisation_step(np.r_[np.arange(60), 60.3] * 1e-3) is None


def test_plant_lines_above_noise_count_by_definition():
    """plant_above_noise_lines counts the plant-referred lines more than 4 times (6 dB)
    over what is expected there without plant distortion."""
    n, m, p = 512, 4, 4
    excited, table = _multisine_table(m, n, 200, seed=9)
    u = np.repeat(table[:, None, :], p, axis=1)
    y = 0.5 * u + 1e-3 * np.random.default_rng(1).standard_normal(u.shape)
    res = robust_bla(u, y, excited_bins=excited)
    ratio = 10 ** ((res.plant_db - res.plant_expected_db) / 10)
    assert np.any((ratio > 3.0) & (ratio <= 4.0))                 # lines just under 6 dB
    assert res.summary["plant_above_noise_lines"] == int(np.sum(ratio > 4.0)) == 1


def test_interp_frf_uses_the_documented_four_point_windows():
    """At a frequency: Lagrange through the 4 excited lines around it (2 below, 2 above,
    shifted inside the band at its edges); leave-one-out at line i: the 4 nearest other
    lines, 2 on each side where there are. Checked with cubic fits through those points."""
    freq = np.array([3, 5, 9, 11, 13, 17, 21, 23, 29, 31, 33], float)
    G = 1 / (1 + 1j * freq / 7) / (1 + 0.3j * freq / 19) * np.exp(-0.05j * freq)
    x, logmag, phase = np.log(freq), np.log(np.abs(G)), np.unwrap(np.angle(G))

    def cubic(idx, xa):
        c_m, c_p = np.polyfit(x[idx], logmag[idx], 3), np.polyfit(x[idx], phase[idx], 3)
        return np.exp(np.polyval(c_m, xa) + 1j * np.polyval(c_p, xa))

    f_at = np.array([4.0, 7.0, 10.0, 15.0, 19.0, 26.0, 32.0])
    g_at, loo = bla_mod._interp_frf(freq, G, f_at)
    e = freq.size
    for f, g in zip(f_at, g_at):
        start = min(max(np.searchsorted(freq, f) - 2, 0), e - 4)
        assert g == pytest.approx(cubic(np.arange(start, start + 4), np.log(f)), rel=1e-8), f
    for i in range(e):
        others = np.delete(np.arange(e), i)
        start = min(max(i - 2, 0), e - 5)
        pred = cubic(others[start:start + 4], x[i])
        assert loo[i] == pytest.approx(abs(pred - G[i]) / abs(G[i]), rel=1e-6), i


def test_a_single_near_zero_line_is_no_lower_cluster():
    """Below a split there must be at least 2 lines: one line 120 dB down under a flat
    full grid (31 lines, too few for the local threshold) leaves no way to tell."""
    n = 64
    amp = np.ones(n // 2 + 1)
    amp[[0, n // 2, 10]] = 0.0
    one = np.fft.irfft(amp * np.exp(2j * np.pi * np.random.default_rng(2).random(n // 2 + 1)), n=n)
    with pytest.raises(InputError, match="cannot tell"):
        detect_excited_lines(np.tile(one, (1, 2, 1)))


def test_excited_line_range_message_and_the_smallest_period():
    with pytest.raises(InputError, match=r"bins must lie in 1 \.\. 31 for N = 64 samples"):
        robust_bla(np.ones((1, 2, 64)), np.ones((1, 2, 64)), excited_bins=[3, 32])
    x = _lines_excitation(4, np.array([1]), 200.0, m=2, p=2)            # N = 4: one line
    res = robust_bla(x, 3.0 * x, excited_bins=[1], warn_transient=False)
    np.testing.assert_allclose(res.G, 3.0, rtol=1e-9)


def test_float64_record_rounding_floor_at_the_nonexcited_lines():
    """Identical periods of a float64 record (no noise): the noise of the non-excited
    lines is the record's rounding floor, 4 (2 max|y| 2^-53)^2 / 12 / N."""
    n, m, p = 256, 2, 3
    excited, table = _multisine_table(m, n, 60, seed=3)
    u = np.repeat(table[:, None, :], p, axis=1)
    y = 0.7 * u + 0.01 * u ** 2
    assert not np.array_equal(y, y.astype(np.float32))
    res = robust_bla(u, y, excited_bins=excited)
    floor = 4.0 * (2.0 * np.max(np.abs(y)) * 2.0 ** -53) ** 2 / 12.0 / n
    np.testing.assert_allclose(res.nonexcited_noise_db, 10 * np.log10(floor), atol=0.01)
