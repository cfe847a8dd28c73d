"""robust_bla's fast paths (per-realization FFT buffers overwritten in place, one FFT per
realization for an exactly periodic reference) give the estimate of the plain per-period
spectra (robust_bla_spectra on every period's full rfft), also when r is the same array
as u and with settle periods."""
import numpy as np
import pytest

from fftune.analysis.bla import robust_bla, robust_bla_spectra
from fftune.analysis.multisine import multisine_realizations


def _record(seed=2, m=3, p=4, n=256, fs=256.0):
    designs = multisine_realizations(m, fs, n, f_min=2.0, f_max=60.0, seed=seed)
    rng = np.random.default_rng(seed)
    r = np.repeat(np.stack([d.period for d in designs])[:, None, :], p, axis=1)
    u = r + 0.02 * rng.standard_normal(r.shape)
    y = 0.7 * u + 0.2 * u ** 3 - 0.1 * u ** 2 + 0.01 * rng.standard_normal(u.shape)
    return designs[0].excited, r, u, y, n, fs


def _plain(u, y, r, excited, n, fs, settle):
    band = np.arange(excited[0], excited[-1] + 1)
    spec = [None if x is None else np.fft.rfft(x, axis=-1)[..., band] for x in (u, y, r)]
    return robust_bla_spectra(*spec, bins=band, n_period=n, fs=fs, settle_periods=settle,
                              excited_bins=excited, warn_transient=False)


@pytest.mark.parametrize("settle", [0, 1])
@pytest.mark.parametrize("case", ["no reference", "periodic reference", "reference is u",
                                  "noisy reference"])
def test_fast_paths_equal_the_plain_spectra(case, settle):
    excited, r, u, y, n, fs = _record()
    if case == "no reference":
        ref = None
    elif case == "periodic reference":
        ref = r
    elif case == "reference is u":
        ref = u                      # the same array object as the input
    else:
        ref = r + 1e-3 * np.random.default_rng(5).standard_normal(r.shape)
    fast = robust_bla(u, y, ref, fs=fs, excited_bins=excited, settle_periods=settle,
                      warn_transient=False)
    plain = _plain(u, y, ref, excited, n, fs, settle)
    for name in ("G", "var_total", "var_noise", "nonexcited_db", "nonexcited_noise_db",
                 "plant_db", "plant_expected_db"):
        a, b = getattr(fast, name), getattr(plain, name)
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.max(np.abs(b)),
                                   err_msg=f"{case}, T = {settle}: {name}")
    assert fast.summary["nl_detected"] == plain.summary["nl_detected"]
    assert fast.summary["excitation_distorted"] == plain.summary["excitation_distorted"]
    # the inputs are not modified by the in-place work
    excited2, r2, u2, y2, _, _ = _record()
    np.testing.assert_array_equal(u, u2)
    np.testing.assert_array_equal(y, y2)
