"""The robust MIMO BLA's variances against their analytic values.

A linear 2 x 2 system with white output noise of known standard deviation: per block b and
line k, G_bp = Y_bp U_b^-1 with the same U_b in every period, so the noise of one period's
entry (o, i) has the variance N sigma^2 sum_j |(U_b^-1)_ji|^2 (rfft scaling: the DFT of
white noise has variance N sigma^2 per line). Averaged over P periods and B blocks:
var_noise = 1 / B^2 sum_b N sigma^2 sum_j |(U_b^-1)_ji|^2 / P. Without distortion,
var_total estimates the same variance (var_nl ~ 0); a static nonlinearity makes it larger.
"""
import numpy as np
import pytest

from fftune.analysis import robust_bla_mimo
from fftune.analysis.errors import InputError
from fftune.analysis.multisine import multisine_realizations

N, P, FS = 512, 4, 512.0


def _experiment(n_blocks, sigma, seed, cubic=0.0, p=P):
    d = multisine_realizations(2 * n_blocks, FS, N, k_min=1, k_max=150, seed=seed, rms=0.5, kind="odd")
    per = np.stack([x.period for x in d]).reshape(2 * n_blocks, 1, N)
    # input 2 of each realization: the same design, an independent phase (its own seed)
    d2 = multisine_realizations(2 * n_blocks, FS, N, k_min=1, k_max=150, seed=seed + 99, rms=0.5, kind="odd")
    per2 = np.stack([x.period for x in d2]).reshape(2 * n_blocks, 1, N)
    u = np.repeat(np.concatenate([per, per2], axis=1)[:, None, :, :].swapaxes(2, 3), p, axis=1)
    # (M, P, N, 2): y1 = 0.8 u1 + 0.3 u2 delayed, y2 = -0.5 u1 + u2 (exact, periodic)
    y = np.empty_like(u)
    y[..., 0] = 0.8 * u[..., 0] + 0.3 * np.roll(u[..., 1], 3, axis=2) + cubic * u[..., 0] ** 3
    y[..., 1] = -0.5 * u[..., 0] + u[..., 1]
    rng = np.random.default_rng(seed)
    y = y + sigma * rng.standard_normal(y.shape)
    return u, y, d[0].excited


def _analytic_var_noise(u, excited, n_blocks, sigma, p):
    U = np.fft.rfft(u[:, 0], axis=1)[:, excited, :]                  # (M, E, n_u)
    Ub = U.reshape(n_blocks, 2, excited.size, 2).transpose(0, 2, 3, 1)  # (B, E, ch, exp)
    inv = np.linalg.inv(np.swapaxes(Ub, -1, -2))     # (U^T)^-1 = (U^-1)^T: [j, i] of U^-1 at [i, j]
    col2 = np.sum(np.abs(inv) ** 2, axis=-1)          # (B, E, i): sum_j |(U^-1)_ji|^2
    per_block = N * sigma ** 2 * col2 / p
    return per_block.sum(axis=0) / n_blocks ** 2      # (E, i), the same for every output


@pytest.mark.parametrize("n_blocks, sigma", [(4, 1e-2), (6, 3e-3)])
def test_noise_and_total_variance_equal_the_analytic_noise_variance(n_blocks, sigma):
    u, y, excited = _experiment(n_blocks, sigma, seed=3)
    res = robust_bla_mimo(u, y, fs=FS, excited_bins=excited)
    want = _analytic_var_noise(u, excited, n_blocks, sigma, P)
    assert res.var_noise.shape == (excited.size, 2, 2)
    for o in range(2):
        for i in range(2):
            # per line estimate / truth, averaged over ~75 lines (per line: B (P - 1)
            # complex dof for the noise, +-4 % (1 sd) in the mean; B - 1 for the total,
            # +-7 %): the truth is heavy-tailed over the lines (nearly singular input
            # matrices), so the ratio is taken line by line
            ratio = np.mean(res.var_noise[:, o, i] / want[:, i])
            assert ratio == pytest.approx(1.0, abs=0.15), (o, i, ratio)
            ratio_t = np.mean(res.var_total[:, o, i] / want[:, i])
            assert ratio_t == pytest.approx(1.0, abs=0.25), (o, i, ratio_t)
    # the estimate itself within 5 of its standard deviations of the truth at every line
    w = np.exp(-2j * np.pi * excited / N)
    truth = np.array([[0.8 + 0 * w, 0.3 * w ** 3], [-0.5 + 0 * w, 1.0 + 0 * w]]).transpose(2, 0, 1)
    z = np.abs(res.G - truth) / np.sqrt(res.var_noise)
    assert np.max(z) < 5.0
    assert not res.detected.any()
    assert res.n_blocks == n_blocks and res.n_periods == P


def test_a_cubic_in_one_path_is_detected_there_only():
    u, y, excited = _experiment(4, 1e-3, seed=5, cubic=0.5)
    res = robust_bla_mimo(u, y, fs=FS, excited_bins=excited)
    assert res.detected[0].all() and not res.detected[1].any()
    # var_nl = B (var_total - var_noise), far above the noise on output 1 only
    np.testing.assert_allclose(res.var_nl, 4 * (res.var_total - res.var_noise), rtol=1e-12)
    assert np.nanmin(res.nl_re_output_db[0]) > -40.0 > np.nanmax(res.nl_re_output_db[1])


def test_one_block_or_one_period_says_what_is_missing():
    u, y, excited = _experiment(1, 1e-3, seed=6)
    res = robust_bla_mimo(u, y, fs=FS, excited_bins=excited)
    assert res.var_total is None and res.var_nl is None and res.var_noise is not None
    assert any("one block of 2 experiments" in s and "M >= 4" in s for s in res.notes)
    u, y, excited = _experiment(3, 1e-3, seed=6, p=1)
    res = robust_bla_mimo(u, y, fs=FS, excited_bins=excited)
    assert res.var_noise is None and res.var_total is not None
    assert any("P = 1 period" in s for s in res.notes)
    u, y, excited = _experiment(2, 1e-3, seed=6, p=2)        # the smallest complete case
    res = robust_bla_mimo(u, y, fs=FS, excited_bins=excited)
    assert res.var_noise is not None and res.var_total is not None and res.detected is not None
    assert res.notes == []


def test_settle_periods_are_dropped_and_bad_input_is_named():
    u, y, excited = _experiment(3, 1e-3, seed=7)
    y_bad = y.copy()
    y_bad[:, 0] += 5.0 * np.sin(2 * np.pi * 7 * np.arange(N) / N)[None, :, None]   # transient
    clean = robust_bla_mimo(u[:, 1:], y[:, 1:], fs=FS, excited_bins=excited)
    res = robust_bla_mimo(u, y_bad, fs=FS, excited_bins=excited, settle_periods=1)
    np.testing.assert_allclose(res.G, clean.G, rtol=1e-12)
    assert res.n_periods == P - 1
    # the lines found from the first input equal the design's
    np.testing.assert_array_equal(robust_bla_mimo(u, y, fs=FS).bins, excited)
    u_dep = u.copy()
    u_dep[2:4, ..., 1] = u_dep[2:4, ..., 0]            # block 1: both inputs the same signal
    with pytest.raises(InputError, match="inputs of block 1 are not independent"):
        robust_bla_mimo(u_dep, y, fs=FS, excited_bins=excited)
    y_nan = y.copy()
    y_nan[0, 1, 5, 0] = np.nan
    with pytest.raises(InputError, match="NaN or inf"):
        robust_bla_mimo(u, y_nan, fs=FS, excited_bins=excited)
    with pytest.raises(InputError, match="expected u .* and y"):
        robust_bla_mimo(u, y[:, :, :, :1, None], fs=FS)
    with pytest.raises(InputError, match=r"settle periods T = 4 must be in 0 \.\. 3$"):
        robust_bla_mimo(u, y, fs=FS, settle_periods=4)
    with pytest.raises(InputError, match="fs must be a positive"):
        robust_bla_mimo(u, y, fs=0.0)
