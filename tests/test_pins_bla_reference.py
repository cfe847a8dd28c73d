"""The BLA's reference variances pinned (issue 33): var_total, var_noise and the float32
rounding reference of the full-grid F test (every line of the band excited: nonlinear
distortion judged at the excited lines, var_total against var_noise + the rounding
variance), on unequal, asymmetric spectra, against a loop over realizations and periods
written here from the definitions (Pintelon & Schoukens, the robust method) and the
rounding law checked by Monte Carlo.

A rounding reference 4x too small (a uniform error's variance taken as r^2/12 instead of
r^2/3 for an error within +-r) moves the excited lines' median excess by about 6 dB where
the rounding dominates: it fails here.
"""
import math

import numpy as np
import pytest

from fftune.analysis.bla import robust_bla, robust_bla_spectra

N = 96                                 # samples per period
M, P = 5, 3                            # realizations, periods
BINS = np.arange(4, 17)                # the band, every line excited (full grid)


def _spectra(seed, noise_std, real_std):
    """U, Y (M, P, L): unequal amplitudes and a plant G unequal per line; Y has noise that
    changes from period to period (noise_std) and from realization to realization
    (real_std: what the rounding of a record does, the same in every period)."""
    rng = np.random.default_rng(seed)
    L = BINS.size
    amp = (N / 2) * (1.0 + 0.6 * np.arange(L) / L)
    phi = rng.uniform(0, 2 * np.pi, (M, L))
    U = np.broadcast_to((amp * np.exp(1j * phi))[:, None, :], (M, P, L)).copy()
    G = (0.8 - 0.35j) * (1.0 + 0.15 * np.arange(L)) * np.exp(-0.2j * np.arange(L))
    def c(std, shape):
        return std * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / math.sqrt(2)
    Y = G * U + c(real_std, (M, 1, L)) + c(noise_std, (M, P, L))
    return U, Y, G


def _reference(U, Y, y_r, u_r):
    """var_total, var_noise of G and the rounding variance, by loops (the definitions)."""
    L = U.shape[2]
    var_total, var_noise, round_var = np.zeros(L), np.zeros(L), np.zeros(L)
    for l in range(L):
        G_m = []
        ss = 0.0
        u_lev = 0.0
        for m in range(M):
            g_p = [Y[m, p, l] / U[m, p, l] for p in range(P)]
            g = sum(g_p) / P
            G_m.append(g)
            ss += sum(abs(x - g) ** 2 for x in g_p)
            u_lev += abs(sum(U[m, p, l] for p in range(P)) / P) ** 2 / M
        G = sum(G_m) / M
        var_total[l] = sum(abs(g - G) ** 2 for g in G_m) / (M * (M - 1))   # of the mean over m
        var_noise[l] = ss / (P * (P - 1)) / M ** 2                        # of the mean over m, p
        # rounding within +-r per sample, uniform: variance r^2 / 3; a line sums N samples:
        # N r^2 / 3 on Y (|G|^2 times that of U), re |U|^2, of the mean over M realizations
        round_var[l] = N * (y_r ** 2 + abs(G) ** 2 * u_r ** 2) / 3 / u_lev / M
    return var_total, var_noise, round_var


def _median_db(ratio):
    return float(np.median(10 * np.log10(ratio)))


def test_rounding_law_by_monte_carlo():
    """The reference's law: N samples each off by a uniform error in +-r give a DFT line
    of variance N r^2 / 3 (not N r^2 / 12: that is a step of r, an error within +-r/2)."""
    rng = np.random.default_rng(7)
    r = 0.37
    e = rng.uniform(-r, r, (20000, N))
    line = np.fft.rfft(e, axis=1)[:, 5]
    assert np.mean(np.abs(line) ** 2) == pytest.approx(N * r ** 2 / 3, rel=0.03)


@pytest.mark.parametrize("seed, noise_std, real_std, y_r, u_r", [
    (11, 0.02, 0.9, 0.11, 0.0),        # the output's rounding dominates the reference
    (12, 0.02, 0.9, 0.0, 0.08),        # the input's (times |G|^2)
    (13, 0.3, 0.5, 0.05, 0.03),        # both, beside a noise of the same order
])
def test_full_grid_reference_is_noise_plus_the_rounding_variance(seed, noise_std, real_std, y_r, u_r):
    U, Y, G = _spectra(seed, noise_std, real_std)
    res = robust_bla_spectra(U, Y, bins=BINS, n_period=N, excited_bins=BINS, y_rounding=y_r,
                             _u_rounding=u_r, warn_transient=False)
    var_total, var_noise, round_var = _reference(U, Y, y_r, u_r)
    assert res.var_total == pytest.approx(var_total, rel=1e-9)
    assert res.var_noise == pytest.approx(var_noise, rel=1e-9)
    assert res.var_nl == pytest.approx(M * (var_total - var_noise), rel=1e-9, abs=1e-12 * np.max(var_total))
    want = _median_db(var_total / (var_noise + round_var))
    got = res.summary["excited_line_median_re_noise_db"]
    assert got == pytest.approx(want, abs=1e-6)
    # the rounding part matters in these data: without it, or 4x smaller, the excess moves
    assert abs(_median_db(var_total / (var_noise + round_var / 4)) - want) > 1.0
    assert res.summary["excited_lines"] == BINS.size and res.G == pytest.approx(np.mean(Y / U, axis=(0, 1)), rel=1e-9)


def test_full_grid_without_rounding_is_the_noise_alone():
    U, Y, _ = _spectra(21, 0.05, 0.4)
    res = robust_bla_spectra(U, Y, bins=BINS, n_period=N, excited_bins=BINS, warn_transient=False)
    var_total, var_noise, _ = _reference(U, Y, 0.0, 0.0)
    assert res.summary["excited_line_median_re_noise_db"] == pytest.approx(_median_db(var_total / var_noise), abs=1e-6)
    # a realization spread 8x the period noise's is distortion at the excited lines
    assert res.summary["excited_line_median_re_noise_db"] > 10 and res.summary["excited_detected"]


def test_float32_records_take_their_rounding_as_2_to_the_minus_24_of_the_largest_output():
    """robust_bla on float32 output records (a linear plant, no noise: the realizations
    differ only by the rounding of their records) uses r = 2^-24 max|y| (a float32 value x
    is within 2^-24 |x| of the number it stores), not half or twice that: its excited
    lines' excess is the spectra's with that r, and rounding alone is not distortion."""
    rng = np.random.default_rng(5)
    n, Mr, Pr = 256, 6, 2
    k = np.arange(3, 40)
    t = np.arange(n)
    u = np.zeros((Mr, Pr, n))
    for m in range(Mr):
        ph = rng.uniform(0, 2 * np.pi, k.size)
        one = np.sum(np.cos(2 * np.pi * np.outer(k, t) / n + ph[:, None]) * (1 + 0.02 * k)[:, None], axis=0)
        u[m] = one                                     # float64, not float32-exact
    # a linear plant applied per line (periodic steady state), unequal gain and phase
    U = np.fft.rfft(u, axis=2)
    H = np.zeros(n // 2 + 1, complex)
    H[k] = (1.7 - 0.4j) / (1 + 1j * k / 12.0)
    y64 = np.fft.irfft(U * H, n=n, axis=2) * 37.0          # |y| of a few tens: ulp 2^-19 or so
    y32 = y64.astype(np.float32)
    res = robust_bla(u, y32, excited_bins=k, warn_transient=False)
    r = 2.0 ** -24 * float(np.max(np.abs(y32)))
    Y = np.fft.rfft(y32, axis=2).astype(np.complex128)       # (as robust_bla: in float32 precision)
    band = np.arange(k[0], k[-1] + 1)
    ref = robust_bla_spectra(U[:, :, band], Y[:, :, band], bins=band, n_period=n, excited_bins=k,
                             y_rounding=r, warn_transient=False)
    got = res.summary["excited_line_median_re_noise_db"]
    assert got == pytest.approx(ref.summary["excited_line_median_re_noise_db"], abs=1e-6)
    for wrong in (r / 2, 2 * r):
        other = robust_bla_spectra(U[:, :, band], Y[:, :, band], bins=band, n_period=n, excited_bins=k,
                                   y_rounding=wrong, warn_transient=False)
        assert abs(other.summary["excited_line_median_re_noise_db"] - got) > 3.0
    # the periods are identical (var_noise = 0): the rounding is the whole reference, and
    # the bound (each value's own error is at most r) keeps the excess under 0 dB
    assert np.all(res.var_noise == 0) and got < 0 and not res.summary["excited_detected"]
