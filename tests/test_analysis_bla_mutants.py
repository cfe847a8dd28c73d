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
