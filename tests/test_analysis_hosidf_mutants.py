"""HOSIDF: the checks and edge cases that mutation testing found untested (docs/testing.md).

Each test pins a documented behaviour of fftune.analysis.hosidf at its boundary: the
search range of the sine (up to the line below Nyquist), the leakage test (both
neighbours, on a noisy on-grid sine, at exactly the tolerance), given f0 (on a line,
relative tolerance, which record is named), the Nyquist limit of the harmonics, the
repeat standard deviation against numpy, and the input checks.
"""
import re
import warnings

import numpy as np
import pytest

from fftune.analysis.errors import InputError
from fftune.analysis.hosidf import hosidf


def tone(bins_amps, n, periods=1, phase=0.3):
    """sum of a_k sin(2 pi k t / n + phase) over (k, a_k), periods blocks, shape (1, P, N)."""
    t = np.arange(n * periods)
    x = sum(a * np.sin(2 * np.pi * k * t / n + phase) for k, a in bins_amps)
    return np.asarray(x, dtype=float).reshape(1, periods, n)


def test_properties_and_default_sample_rate():
    u = tone([(5, 2.0)], 64)
    res = hosidf(u, 0.5 * u + 0.1 * u ** 3, n_harmonics=3)
    assert res.fs == 1.0 and res.f0 == pytest.approx(5 / 64)      # fs defaults to 1 Hz
    np.testing.assert_array_equal(res.magnitude, np.abs(res.H))
    np.testing.assert_array_equal(res.phase_deg, np.degrees(np.angle(res.H)))
    assert res.magnitude.shape == (3,) and res.phase_deg[0] == pytest.approx(0.0, abs=1e-9)


def test_input_checks():
    u = tone([(5, 1.0)], 64)
    with pytest.raises(InputError, match="expected an array shaped"):
        hosidf(u[0], u[0])                                       # 2-D: no repeat axis
    for fs in (0.0, -1.0):
        with pytest.raises(InputError, match="positive sample rate"):
            hosidf(u, u, fs=fs)
    with pytest.raises(InputError, match="harmonics K must be >= 1"):
        hosidf(u, u, n_harmonics=0)
    assert hosidf(u, u, n_harmonics=1).H.shape == (1,)
    with pytest.raises(InputError, match="too short"):
        hosidf(np.ones((1, 1, 2)), np.ones((1, 1, 2)))
    with pytest.raises(InputError, match="zero input"):
        hosidf(np.zeros((1, 1, 64)), np.zeros((1, 1, 64)))
    with pytest.raises(InputError, match="zero power at the sine frequency"):
        hosidf(np.zeros((1, 1, 64)), np.zeros((1, 1, 64)), f0=5.0, fs=64.0, n_harmonics=3)


def test_sine_search_range_reaches_the_line_below_nyquist_and_skips_nyquist():
    n = 64
    # the highest line that can carry a sine (N/2 - 1) and one above N/3
    for k in (n // 2 - 1, 25):
        u = tone([(k, 1.0)], n)
        assert hosidf(u, u, fs=float(n), n_harmonics=1).bin == k
    # a Nyquist component (alternating samples) larger than the sine is not the sine
    u = tone([(5, 1.0)], n) + 3.0 * (-1.0) ** np.arange(n)
    assert hosidf(u, u, fs=float(n), n_harmonics=3).bin == 5


def test_leakage_test_uses_the_smaller_neighbour_on_either_side():
    """(other lines of 0.2 are a second signal: allowed explicitly, other_line_tol=1)"""
    n = 256
    # a line next to the peak on ONE side is a neighbour signal, not leakage
    for side in (-1, +1):
        u = tone([(40, 1.0), (40 + side, 0.2)], n)
        assert hosidf(u, u, fs=float(n), n_harmonics=3, other_line_tol=1.0).bin == 40
    # lines one and two bins away on different sides: still no leakage (the 2-away
    # line is not a neighbour)
    u = tone([(40, 1.0), (39, 0.2), (42, 0.2)], n)
    assert hosidf(u, u, fs=float(n), n_harmonics=3, other_line_tol=1.0).bin == 40
    # an on-grid sine with a little noise has neighbours far below leakage_tol of the peak
    rng = np.random.default_rng(3)
    u = tone([(40, 1.0)], n, periods=2) + 1e-3 * rng.standard_normal((1, 2, n))
    assert hosidf(u, u, fs=float(n), n_harmonics=3).bin == 40
    # the test applies from bin 2 on (bin 1 has DC and the 2nd harmonic as neighbours)
    t = np.arange(n)
    off = np.sin(2 * np.pi * 2.3 * t / n).reshape(1, 1, n)
    with pytest.raises(InputError, match="off the DFT grid"):
        hosidf(off, off, fs=float(n), n_harmonics=3)


def test_leakage_at_exactly_the_tolerance_is_accepted():
    n = 256
    u = tone([(40, 1.0), (39, 0.02), (41, 0.03)], n)
    mag = np.abs(np.fft.rfft(u.sum(axis=-2), axis=-1))[0]
    exact = min(mag[39], mag[41]) / mag[40]          # the same arithmetic as the module
    assert hosidf(u, u, fs=float(n), n_harmonics=3, leakage_tol=exact).bin == 40
    with pytest.raises(InputError, match="off the DFT grid"):
        hosidf(u, u, fs=float(n), n_harmonics=3, leakage_tol=exact * (1 - 1e-9))


def test_off_grid_message_names_the_first_bad_record():
    n = 256
    t = np.arange(n)
    rows = [np.sin(2 * np.pi * k * t / n) for k in (10, 20.4, 30.4)]   # records 1 and 2 bad
    u = np.stack(rows).reshape(3, 1, 1, n)
    with pytest.raises(InputError, match=re.escape("record (1, 0) has its sine off the DFT grid")
                       + ".*near 20 Hz"):
        hosidf(u, u, fs=float(n), n_harmonics=3)


def test_given_f0_on_a_line_relative_tolerance_and_named_record():
    n, fs = 4096, 4096.0
    u = tone([(1000, 1.0)], n)
    # within 1e-6 relative of the line (5e-4 bins at bin 1000): accepted as that line
    assert hosidf(u, u, fs=fs, f0=1000.0005, n_harmonics=2).bin == 1000
    # bin 1 given explicitly is a valid line; 0 Hz is not
    one = tone([(1, 1.0)], n)
    assert hosidf(one, one, fs=fs, f0=1.0, n_harmonics=2).bin == 1
    with pytest.raises(InputError, match="not on a DFT line"):
        hosidf(one, one, fs=fs, f0=0.0, n_harmonics=2)
    # f0 per record (leading axes): record 0 at bin 1 is fine, record 1 is off the grid
    both = np.stack([one[0], tone([(7, 1.0)], n)[0]]).reshape(2, 1, 1, n)
    with pytest.raises(InputError, match=re.escape("record (1, 0)")):
        hosidf(both, both, fs=fs, f0=[1.0, 7.3], n_harmonics=2)
    # f0 broadcast over two leading axes
    grid = np.broadcast_to(u, (2, 3, 1, 1, n))
    assert hosidf(grid, grid, fs=fs, f0=1000.0, n_harmonics=2).H.shape == (2, 3, 2)


def test_harmonic_at_exactly_nyquist_is_refused():
    n = 64
    u = tone([(4, 1.0)], n)
    assert hosidf(u, u, fs=64.0, n_harmonics=7).H.shape == (7,)       # 7 * 4 = 28 < 32
    with pytest.raises(InputError, match=re.escape("the sine at 4 Hz lies at or above fs/2 = 32 Hz")):
        hosidf(u, u, fs=64.0, n_harmonics=8)                           # 8 * 4 = 32


def test_repeat_std_equals_numpy_complex_std():
    rng = np.random.default_rng(7)
    n, p = 128, 2
    for r in (2, 5):
        # (repeats of one level: 1 % apart; 10 % apart are levels, refused since issue 31)
        u = np.concatenate([tone([(6, 1.0 + 0.01 * i)], n, periods=p, phase=0.2 * i)
                            for i in range(r)])                          # (R, P, N)
        y = np.tanh(u) + 0.05 * rng.standard_normal(u.shape)
        res = hosidf(u, y, fs=float(n), n_harmonics=4)
        assert res.H_repeats.shape == (r, 4)
        np.testing.assert_allclose(res.H_std, np.std(res.H_repeats, axis=-2, ddof=1), rtol=1e-12)
    # one repeat: NaN, quietly (no 0/0 warning)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = hosidf(u[:1], y[:1], fs=float(n), n_harmonics=4)
    assert np.all(np.isnan(res.H_std))


def test_keyword_only_options_and_defaults():
    u = tone([(3, 1.0)], 64)
    assert hosidf(u, u).H.shape == (7,)                             # K = 7 by default
    with pytest.raises(TypeError):
        hosidf(u, u, 64.0)                                          # fs is keyword-only


def test_repeats_at_different_frequencies_are_refused():
    n = 64
    u = np.concatenate([tone([(5, 1.0)], n), tone([(6, 1.0)], n)])  # R = 2
    with pytest.raises(InputError, match="different frequencies"):
        hosidf(u, u, fs=float(n), n_harmonics=3)


def test_leakage_test_at_the_line_below_nyquist():
    n = 64
    # peak at N/2 - 1, a neighbour signal below it, nothing at Nyquist: not leakage
    u = tone([(31, 1.0), (30, 0.2)], n)
    assert hosidf(u, u, fs=float(n), n_harmonics=1, other_line_tol=1.0).bin == 31


def test_given_f0_tolerance_near_bin_one_and_the_record_named():
    n = 256
    fs = float(n)                                   # f0 in Hz = bins
    one = tone([(1, 1.0)], n)
    with pytest.raises(InputError, match="not on a DFT line"):
        hosidf(one, one, fs=fs, f0=1 + 1.5e-6, n_harmonics=3)      # 1.5e-6 bins off: refused
    assert hosidf(one, one, fs=fs, f0=1 - 9.999995e-7, n_harmonics=3).bin == 1
    rec = np.stack([tone([(1, 1.0)], n)[0], tone([(7, 1.0)], n)[0],
                    tone([(9, 1.0)], n)[0]]).reshape(3, 1, 1, n)
    # the first bad record is named, whatever the good ones look like
    for first, name in (((1 + 1.5e-6), "(0, 0)"), (1 - 9.999995e-7, "(1, 0)"), (1.0, "(1, 0)")):
        with pytest.raises(InputError, match=re.escape(f"(record {name})")):
            hosidf(rec, rec, fs=fs, f0=[first, 7.3, 9.3], n_harmonics=3)
    big = np.stack([tone([(100, 1.0)], n * 16)[0], tone([(7, 1.0)], n * 16)[0]]).reshape(2, 1, 1, -1)
    with pytest.raises(InputError, match=re.escape("(record (1, 0))")):
        hosidf(big, big, fs=fs * 16, f0=[100.00005, 7.3], n_harmonics=3)


def test_hosidf_from_lines_by_definition_and_keyword_only_sizes():
    """H_k = Y_k exp(-j k angle U_1) / |U_1| per repeat, then the mean; amplitude 2 |U_1| / (N P);
    N, P and fs are keyword-only (a positional 64 cannot be taken for N by mistake)."""
    import numpy as np
    import pytest

    from fftune.analysis.hosidf import hosidf_from_lines
    U1 = np.array([3.0 * np.exp(0.4j), 3.0 * np.exp(0.4j)])
    Yk = np.array([[1.0 + 1.0j, 0.2j], [1.0 + 1.2j, 0.1]])
    res = hosidf_from_lines(U1, Yk, 4, n=64, n_blocks=2, fs=100.0)
    expected = (Yk * np.exp(-1j * np.array([1, 2]) * 0.4) / 3.0).mean(axis=0)
    np.testing.assert_allclose(res.H, expected, rtol=1e-12)
    assert res.amplitude == pytest.approx(2 * 3.0 / (64 * 2)) and res.f0 == pytest.approx(4 * 100.0 / 64)
    with pytest.raises(TypeError):
        hosidf_from_lines(U1, Yk, 4, 64, 2, 100.0)


def test_too_short_blocks_are_refused_for_batched_records_too():
    """(experiments, R, P, N) with N = 3: no line between DC and Nyquist to find a sine on."""
    import numpy as np
    import pytest

    from fftune.analysis.errors import InputError
    from fftune.analysis.hosidf import hosidf
    u = np.ones((2, 3, 2, 3))
    with pytest.raises(InputError, match="too short"):
        hosidf(u, u, fs=1.0)
