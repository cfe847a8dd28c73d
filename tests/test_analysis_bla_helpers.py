"""The robust BLA's numeric helpers against references they do not share code with
(numpy's own unwrap / quantile / median, scipy.stats, brute-force loops): each helper
replaced a general numpy call for speed, so each is pinned on edge cases where a one-line
slip (a branch, an index, an order) would change a reported figure."""
import math

import numpy as np
import pytest
import scipy.stats

from fftune.analysis import bla
from fftune.analysis.bla import robust_bla
from fftune.analysis.multisine import multisine_realizations


def test_unwrap_is_numpys_unwrap_also_at_the_pi_boundaries():
    rng = np.random.default_rng(1)
    cases = [np.array([0.0]), np.array([]), np.array([0.0, np.pi, 0.0, -np.pi, np.pi]),
             np.array([np.pi, -np.pi, -np.pi, np.pi]), np.array([0.0, 3 * np.pi, -3 * np.pi]),
             np.array([-np.pi, 0.0, np.pi, 2 * np.pi, -2 * np.pi])]
    for _ in range(300):
        p = np.cumsum(rng.uniform(-5.0, 5.0, rng.integers(2, 40)))
        p[rng.integers(0, p.size)] = rng.choice([np.pi, -np.pi, 3 * np.pi])
        cases.append(p)
    for p in cases:
        np.testing.assert_array_equal(bla._unwrap(p), np.unwrap(p), err_msg=str(p))


def test_lagrange4_reproduces_cubics_and_the_weights_formula():
    rng = np.random.default_rng(2)
    xs = np.sort(rng.uniform(0.0, 10.0, (200, 4)), axis=1).T.copy()       # (4, n)
    xa = rng.uniform(-1.0, 11.0, 200)
    coef = rng.standard_normal((4, 1))
    cubic = lambda x: coef[0] + coef[1] * x + coef[2] * x ** 2 + coef[3] * x ** 3   # noqa: E731
    got = bla._lagrange4(xs, xa, cubic(xs))
    np.testing.assert_allclose(got, cubic(xa[None, :])[0], rtol=1e-7, atol=1e-7)
    # one node's value alone: the weight of that node, prod (xa - x_i) / (x_j - x_i)
    for j in range(4):
        values = np.zeros_like(xs)
        values[j] = 1.0
        others = [i for i in range(4) if i != j]
        w = np.prod([(xa - xs[i]) / (xs[j] - xs[i]) for i in others], axis=0)
        np.testing.assert_allclose(bla._lagrange4(xs, xa, values), w, rtol=1e-12)


def test_interp_frf_is_exact_for_a_power_law_with_phase_wraps():
    freq = np.geomspace(1.0, 900.0, 300)
    g = 3.0 / (1j * 2 * np.pi * freq) ** 2 * np.exp(-1j * 2 * np.pi * freq * 2e-3)  # wraps
    f_at = np.geomspace(1.3, 880.0, 417)
    g_at, loo = bla._interp_frf(freq, g, f_at)
    want = 3.0 / (1j * 2 * np.pi * f_at) ** 2 * np.exp(-1j * 2 * np.pi * f_at * 2e-3)
    # a delay is linear in f, not in log f: small but nonzero error; magnitude exact
    np.testing.assert_allclose(np.abs(g_at), np.abs(want), rtol=1e-9)
    assert np.max(np.abs(np.angle(g_at / want))) < 1e-3
    assert loo.shape == freq.shape and np.all(loo < 1e-3)
    # pure power law: exact phase too, leave-one-out error at rounding level
    g_at, loo = bla._interp_frf(freq, 2.0 / (1j * freq) ** 3, f_at)
    np.testing.assert_allclose(g_at, 2.0 / (1j * f_at) ** 3, rtol=1e-9)
    assert np.all(loo < 1e-9)


def _sizes_and_values(rng):
    for _ in range(400):
        n = int(rng.integers(1, 60))
        yield rng.exponential(1.0, n) ** rng.uniform(1.0, 6.0)


def test_median_and_quantile_in_db_from_order_statistics_equal_numpy():
    rng = np.random.default_rng(3)
    for p in _sizes_and_values(rng):
        assert bla._median_db_of(p) == pytest.approx(float(np.median(bla.to_db(p))), abs=1e-12)
        for q in (0.1, 0.5, 0.9, 0.95, 1.0, 0.0):
            assert bla._quantile_db_of(p, q) == pytest.approx(
                float(np.quantile(bla.to_db(p), q)), abs=1e-12), (p, q)
    # zeros and NaN give NaN as to_db does, inf stays inf; the empty set as numpy
    assert np.isnan(bla._median_db_of(np.array([1.0, 0.0, 2.0])))
    assert np.isnan(bla._median_db_of(np.array([1.0, np.nan, 2.0])))
    assert np.isnan(bla._quantile_db_of(np.array([1.0, np.nan, 2.0]), 0.9))
    with pytest.warns(RuntimeWarning):
        assert np.isnan(bla._median_db_of(np.array([])))


def test_false_alarm_count_is_the_binomial_quantile():
    rng = np.random.default_rng(4)
    for _ in range(300):
        n = int(rng.integers(1, 4000))
        p = float(10 ** rng.uniform(-7, -0.05))
        alpha = float(rng.choice([1e-3, 1e-2, 1e-5]))
        k = bla._false_alarm_count(n, p, alpha)
        # smallest k >= 1 with P(X >= k) <= alpha (n + 1 when even k = n is not enough)
        sf = scipy.stats.binom.sf(np.arange(n + 1) - 1, n, p)      # P(X >= k)
        ok = np.flatnonzero(sf <= alpha)
        want = max(1, int(ok[0]) if ok.size else n + 1)
        assert abs(k - want) <= (1 if abs(sf[want] - alpha) < 1e-6 * alpha else 0), (n, p, alpha)
    assert bla._false_alarm_count(0, 0.1) is None


def test_f_tail_equals_scipy_for_even_numerators():
    x = np.array([0.0, 0.3, 1.0, 2.5, 10.0, 1e3])
    for d1 in (2, 4, 18, 40):
        for d2 in (2.0, 7.0, 180.0):
            np.testing.assert_allclose(bla.f_sf_even(x, d1, d2),
                                       scipy.stats.f.sf(x, d1, d2), rtol=1e-9, atol=1e-300)
    assert bla.f_sf_even(np.array(2.0), 0, 10.0) == 0.0        # no term
    assert np.shape(bla.f_sf_even(np.array(2.0), 4, 10.0)) == ()


def _brute_class_flags(level, reference, nu, tail, known=None, margin=8.0):
    """The strongest line's Bonferroni test over every line, as first written."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = level / reference
        if known is not None:
            thr = margin * known
            ex = np.maximum(level - thr, 0.0) / np.maximum(reference - known, 1e-300)
            p_lines = np.where(level > thr, tail(ex), 1.0)
        else:
            p_lines = np.where(ratio > 0, tail(np.where(ratio > 0, ratio, 0.0)), 1.0)
        excess = 10 * np.log10(ratio)
    med = float(np.median(excess)) if not np.isnan(excess).any() else float("nan")
    strongest = bool(np.any(~np.isnan(p_lines)) and level.size * np.nanmin(p_lines) <= 1e-3)
    return med, strongest


@pytest.mark.parametrize("kind", ["power tail", "F tail", "known part"])
def test_class_test_strongest_line_and_median_equal_the_full_computation(kind):
    rng = np.random.default_rng({"power tail": 5, "F tail": 6, "known part": 7}[kind])
    nu = 9
    f_tail = lambda x: bla.f_sf_even(x, 18, 180.0)           # noqa: E731
    tail = f_tail if kind == "F tail" else (lambda x: (1.0 + np.maximum(x, 0) / nu) ** (-nu))
    hits = 0
    for _ in range(600):
        n = int(rng.integers(1, 50))
        level, reference = rng.exponential(1.0, n), rng.exponential(1.0, n)
        level[rng.integers(0, n)] *= rng.choice([1.0, 30.0, 1e4])
        for arr in (level, reference):
            for _ in range(int(rng.integers(0, 3))):
                arr[rng.integers(0, n)] = rng.choice([0.0, np.nan, np.inf])
        known = reference * rng.uniform(0.0, 0.9, n) if kind == "known part" else None
        out = bla._class_stats(level, reference, nu, "x_", tail=f_tail if kind == "F tail" else None,
                               known=known)
        med, strongest = _brute_class_flags(level, reference, nu, tail, known)
        got_med = out["x_line_median_re_noise_db"]
        assert (got_med is None) == (not np.isfinite(med)), (level, reference)
        if got_med is not None:
            assert got_med == pytest.approx(med, abs=1e-9)
        over = int(np.sum(level > 4.0 * reference))
        assert out["x_lines_over_noise_6db"] == over
        assert out["x_detected"] == (over >= out["x_lines_needed"] or strongest), (level, reference)
        hits += strongest
    assert hits > 50            # the strongest-line test was exercised both ways


def _band_figures_reference(odd_bins, odd_power, odd_noise, even_bins, even_power, even_noise,
                            det_bins, det_power, det_noise, fs, n, parity):
    """Per band and class, the figures by a plain loop over the lines."""
    bands = bla._band_figures(odd_bins, odd_power, odd_noise, even_bins, even_power,
                              even_noise, det_bins, det_power, det_noise, fs, n, parity)
    classes = ([("odd", odd_bins, odd_power, odd_noise), ("even", even_bins, even_power, even_noise)]
               if parity else [("nonexcited", det_bins, det_power, det_noise)])
    for entry in bands:
        a = round(entry["f_lo_hz"] * n / fs)
        b = round(entry["f_hi_hz"] * n / fs) + 1
        for name, bins, power, noise in classes:
            sel = (bins >= a) & (bins < b)
            got = entry[name]
            assert got["lines"] == int(sel.sum())
            if not sel.any():
                assert got["power_db"] is None
                continue
            mean = float(np.mean(power[sel]))
            want_db = 10 * np.log10(max(mean, 1e-300))
            assert got["power_db"] == pytest.approx(want_db, abs=1e-9, nan_ok=True)
            if noise is None:
                assert got["median_re_noise_db"] is None
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                ex = 10 * np.log10(power[sel] / noise[sel])
            ex = np.where(np.isfinite(ex), ex, -np.inf)
            med, top = float(np.median(ex)), float(ex.max())
            assert got["median_re_noise_db"] == (pytest.approx(med, abs=1e-9)
                                                 if np.isfinite(med) else None)
            assert got["max_re_noise_db"] == (pytest.approx(top, abs=1e-9)
                                              if np.isfinite(top) else None)
            assert got["lines_over_noise_6db"] == int(np.sum(ex > 10 * np.log10(4.0)))
    return bands


def test_octave_figures_equal_a_per_line_loop():
    rng = np.random.default_rng(8)
    n_bands_seen = 0
    for _ in range(300):
        lo, count = int(rng.integers(1, 50)), int(rng.integers(0, 300))
        det = np.sort(rng.choice(np.arange(lo, lo + 3 * count + 10), size=count, replace=False))
        power, noise = rng.exponential(1.0, count), rng.exponential(0.3, count)
        for arr in (power, noise):
            if count and rng.random() < 0.3:
                arr[rng.integers(0, count)] = rng.choice([0.0, np.inf])
        noise = None if rng.random() < 0.2 else noise
        odd, even = det % 2 == 1, det % 2 == 0
        sel = lambda a, s: None if a is None else a[s]          # noqa: E731
        bands = _band_figures_reference(det[odd], power[odd], sel(noise, odd), det[even],
                                        power[even], sel(noise, even), det, power, noise,
                                        1000.0, 4096, bool(rng.random() < 0.7))
        n_bands_seen += len(bands)
    assert n_bands_seen > 500


def test_output_resolution_is_read_from_every_realization_and_period():
    """Noise-free periodic data: the noise at the non-excited lines is the rounding floor
    4 (2 r)^2 / 12 / N with r = 2^-53 max|y| (float64) or 2^-24 max|y| (float32): the
    largest |y| must be found wherever it lies (a late realization, a settle period)."""
    m, p, n, fs = 4, 3, 256, 256.0
    d = multisine_realizations(m, fs, n, f_min=2.0, f_max=60.0, seed=3)
    u = np.repeat(np.stack([x.period for x in d])[:, None, :], p, axis=1)
    y = 0.5 * u + 0.1 * u ** 3
    for where in [(3, 0, 17), (2, 2, 200), (0, 1, 5)]:
        for dtype, eps in ((np.float64, 2.0 ** -53), (np.float32, 2.0 ** -24)):
            yy = y.astype(dtype)
            peak = 40.0 * float(np.max(np.abs(y)))
            yy[where] = -peak                              # the largest |y|, negative
            peak = float(-yy[where])                       # (as stored: float32 rounds)
            res = robust_bla(u.astype(dtype), yy, fs=fs, excited_bins=d[0].excited,
                             settle_periods=1 if where[1] == 0 else 0, warn_transient=False)
            floor = 4.0 * (2.0 * peak * eps) ** 2 / 12.0 / n
            noise = 10 ** (np.asarray(res.nonexcited_noise_db) / 10)
            # the spike breaks periodicity (noise above the floor) except in a dropped
            # settle period: there the floor alone is left
            if where[1] == 0:
                np.testing.assert_allclose(noise, floor, rtol=1e-9)
            else:
                assert np.all(noise >= floor * (1 - 1e-9))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_bad_value_in_a_dropped_settle_period_changes_nothing(bad):
    """Once, a NaN in a settle period (dropped) made the rounding floor NaN and with it
    every noise level and verdict of the non-excited lines, without an error."""
    m, p, n, fs = 3, 4, 256, 256.0
    d = multisine_realizations(m, fs, n, f_min=2.0, f_max=60.0, seed=4)
    rng = np.random.default_rng(4)
    u = np.repeat(np.stack([x.period for x in d])[:, None, :], p, axis=1)
    y = 0.5 * u + 0.2 * u ** 3 + 1e-4 * rng.standard_normal(u.shape)
    clean = robust_bla(u, y, fs=fs, settle_periods=1, warn_transient=False)
    for x in ("u", "y"):
        uu, yy = u.copy(), y.copy()
        # at a value the input's float32 sample reads (every 97th of the flat record)
        (uu if x == "u" else yy)[1, 0, 43] = bad
        assert (1 * p * n + 43) % 97 == 0
        res = robust_bla(uu, yy, fs=fs, excited_bins=d[0].excited, settle_periods=1,
                         warn_transient=False)
        for name in ("G", "var_noise", "nonexcited_noise_db", "plant_expected_db"):
            np.testing.assert_allclose(getattr(res, name), getattr(clean, name), rtol=1e-12,
                                       err_msg=f"{x}: {name}")
        assert res.summary["nl_detected"] == clean.summary["nl_detected"] is True
    # in a kept period it is an error naming the input
    yy = y.copy()
    yy[1, 2, 7] = bad
    with pytest.raises(bla.InputError, match="output y"):
        robust_bla(u, yy, fs=fs, settle_periods=1, warn_transient=False)


@pytest.mark.parametrize("sigma_re_q", [0.0, 0.03, 0.06, 0.2, 0.5, 1.5])
def test_mean_quantisation_error_equals_the_gaussian_average(sigma_re_q):
    """E[q round((s + n) / q)] - s for Gaussian n: the Fourier series (dithered) or the
    plain rounding error (sigma < 0.05 q) against the expectation of the rounding itself, over offsets across two steps (exactly, from the normal cdf)."""
    q = 2 * np.pi / 200
    sigma = sigma_re_q * q
    s = np.linspace(-1.3 * q, 0.9 * q, 157)
    got = bla._mean_quantisation_error(s, q, sigma)
    if sigma < 0.05 * q:
        want = q * np.round(s / q) - s
    else:
        # exactly: q sum_j j P(round((s + n) / q) = j), from the normal cdf
        j = np.arange(-40, 41)[:, None]
        prob = (scipy.stats.norm.cdf((q * (j + 0.5) - s) / sigma)
                - scipy.stats.norm.cdf((q * (j - 0.5) - s) / sigma))
        want = q * np.sum(j * prob, axis=0) - s
    np.testing.assert_allclose(got, want, atol=2e-4 * q)
    # odd in s about a step's centre, periodic in q
    np.testing.assert_allclose(bla._mean_quantisation_error(-s, q, sigma), -got, atol=1e-12 * q)
    np.testing.assert_allclose(bla._mean_quantisation_error(s + q, q, sigma), got, atol=1e-9 * q)
    # the lines of a periodic signal's error: the rfft of the same error at the bins
    t = np.arange(64)
    sig = 3.1 * q * np.sin(2 * np.pi * t / 64) + 0.2 * q
    lines = bla.quantisation_error_lines(sig, q, sigma, np.array([1, 3, 5, 2]))
    np.testing.assert_allclose(
        lines, np.fft.rfft(bla._mean_quantisation_error(sig, q, sigma))[[1, 3, 5, 2]],
        rtol=1e-12, atol=1e-15)


def test_level_independence_note_on_its_edges():
    flat = [{"nl_re_output_db": -20.0 + d, "excited_detected": True} for d in (0.0, 1.0, 2.5)]
    # levels below 1 (mV or rad records): 0.1 .. 0.4 spans 12 dB
    note = bla.level_independence_note([0.1, 0.2, 0.4], flat)
    assert note is not None and "-20.0 .. -17.5 dB over 12 dB" in note
    assert bla.level_independence_note([0.1, 0.19], flat[:2]) is None          # < 6 dB span
    assert bla.level_independence_note([0.1, 0.0, 0.4], flat) is None          # a zero level
    assert bla.level_independence_note([0.3], flat[:1]) is None                 # one level
    moving = [dict(s, nl_re_output_db=-20.0 + 4 * i) for i, s in enumerate(flat)]
    assert bla.level_independence_note([0.1, 0.2, 0.4], moving) is None        # a scale
    undetected = [dict(flat[0]), dict(flat[1], excited_detected=False), dict(flat[2])]
    assert bla.level_independence_note([0.1, 0.2, 0.4], undetected) is None


def test_grid_classes_at_their_smallest_sizes():
    assert bla.classify_grid(np.array([1, 5]), 64)["grid"] == "odd-odd"
    assert bla.classify_grid(np.array([3, 7]), 64)["grid"] == "odd-odd"
    assert bla.classify_grid(np.array([1, 3]), 64)["grid"] == "odd"
    assert bla.classify_grid(np.array([1, 7]), 64)["grid"] == "random odd"
    assert bla.classify_grid(np.array([5]), 64)["grid"] == "odd"
    assert bla.classify_grid(np.array([2, 4]), 64)["grid"] == "even"
    assert bla.classify_grid(np.array([1, 2]), 64)["grid"] == "full"
    assert bla.classify_grid(np.array([1, 2, 4]), 64)["grid"] == "full with removed lines"
    assert bla.classify_grid(np.array([5, 1, 5]), 64)["grid"] == "odd-odd"     # unsorted


@pytest.mark.parametrize("n_zero, more", [(5, False), (6, True)])
def test_zero_input_lines_are_listed_up_to_five(n_zero, more):
    m, p, n, fs = 2, 2, 128, 128.0
    exc = np.arange(1, 40, 2)                       # 20 lines: the median is excited
    spec = np.zeros((m, n // 2 + 1), complex)
    spec[:, exc] = 1.0
    spec[:, exc[:n_zero]] = 0.0                     # given as excited, but not excited
    u = np.repeat(np.fft.irfft(spec, n=n, axis=-1)[:, None, :], p, axis=1)
    with pytest.raises(bla.InputError) as err:
        robust_bla(u, 2 * u, fs=fs, excited_bins=exc, warn_transient=False)
    msg = str(err.value)
    assert f"zero power at {n_zero} excited line(s)" in msg
    assert msg.count(" Hz") == 5 and (" ..." in msg) == more


def test_a_transient_warns_once_and_the_floor_is_reported():
    m, p, n, fs = 3, 5, 256, 256.0
    d = multisine_realizations(m, fs, n, f_min=2.0, f_max=60.0, seed=9)
    u = np.repeat(np.stack([x.period for x in d])[:, None, :], p, axis=1)
    y = 0.5 * u + 1e-5 * np.random.default_rng(9).standard_normal(u.shape)
    y[:, 0] += 0.3 * np.exp(-np.arange(n) / 40.0)                # decays in period 0
    with pytest.warns(bla.TransientWarning) as rec:
        res = robust_bla(u, y, fs=fs, excited_bins=d[0].excited)
    assert len([w for w in rec if issubclass(w.category, bla.TransientWarning)]) == 1
    assert res.transient.suspect
    # the quantisation model's level is reported (dB of its mean power over the lines)
    q = 1e-3
    res = robust_bla(u[:, 1:], np.round(y[:, 1:] / q) * q, fs=fs, excited_bins=d[0].excited,
                     y_quantisation_step=q)
    floor = res.summary["quantisation_floor_db"]
    assert floor is not None and floor == pytest.approx(
        10 * np.log10(np.mean(10 ** (res.quantisation_db / 10))), abs=1e-9)
    assert floor < -60.0


def test_level_independence_note_with_two_levels():
    two = [{"nl_re_output_db": -20.0, "excited_detected": True},
           {"nl_re_output_db": -21.0, "excited_detected": True}]
    assert "over 12 dB" in bla.level_independence_note([0.1, 0.4], two)


def test_running_mean_is_the_window_mean_shrunk_at_the_ends():
    x = np.random.default_rng(10).standard_normal(23)
    for hw in (0, 1, 3, 8, 30):
        want = [np.mean(x[max(i - hw, 0):i + hw + 1]) for i in range(x.size)]
        np.testing.assert_allclose(bla._running_mean(x, hw), want, rtol=1e-12)


def _levels(found, base=0.0, at=None):
    level = np.full(found.max() + 5, -80.0)
    level[found - 1] = base
    for b, v in (at or {}).items():
        level[b - 1] = v
    return level


def test_stray_lines_by_parity_grid_and_level():
    odd = np.arange(1, 120, 2)                                   # 60 odd lines
    # one even line among odd ones: a stray tone
    found = np.sort(np.append(odd, 40))
    kept, strays = bla._stray_lines(_levels(found), found)
    np.testing.assert_array_equal(strays, [40])
    np.testing.assert_array_equal(kept, odd)
    # one odd line among even ones (an even grid)
    even = np.arange(2, 122, 2)
    found = np.sort(np.append(even, 41))
    kept, strays = bla._stray_lines(_levels(found), found)
    np.testing.assert_array_equal(strays, [41])
    # a 4k+3 line among 4k+1 lines (odd-odd grid), and the other way round
    oo = np.arange(1, 240, 4)
    for grid, extra in ((oo, 43), (oo + 2, 41)):
        found = np.sort(np.append(grid, extra))
        kept, strays = bla._stray_lines(_levels(found), found)
        np.testing.assert_array_equal(strays, [extra])
        np.testing.assert_array_equal(kept, grid)
    # many even lines among odd ones: a full grid, no stray
    full = np.sort(np.concatenate([odd, np.arange(2, 40, 2)]))
    kept, strays = bla._stray_lines(_levels(full), full)
    assert strays.size == 0 and kept.size == full.size
    # a line 10 dB under both sides is a stray; a designed step (one side level) is not
    kept, strays = bla._stray_lines(_levels(odd, at={61: -10.0}), odd)
    np.testing.assert_array_equal(strays, [61])
    step = _levels(odd)
    step[odd[odd > 60] - 1] = -12.0                              # the upper half 12 dB down
    kept, strays = bla._stray_lines(step, odd)
    assert strays.size == 0
    # more low lines than a handful: the design, not strays
    many = _levels(odd, at={b: -10.0 for b in odd[5:55:4]})
    assert bla._stray_lines(many, odd)[1].size == 0
    # fewer than 20 lines: nothing is judged
    few = odd[:18]
    kept, strays = bla._stray_lines(_levels(np.append(few, 40)), np.sort(np.append(few, 40)))
    assert strays.size == 0


@pytest.mark.parametrize("dither_re_q, low_db, high_db", [(0.02, -6.0, 0.0), (0.3, 0.0, 8.0)])
def test_quantisation_model_matches_the_measured_error_of_a_linear_plant(dither_re_q, low_db,
                                                                        high_db):
    """A linear plant, its output quantised (a 200-count encoder on a 2-rad signal): what
    the plant-referred lines hold is the quantisation error. The model (the offset fitted
    to the samples, the dither from the measured noise) lies at that level: the measured
    median re the model -3.5 dB with little dither (the model is the running mean doubled:
    on the safe side), +4 .. +5 dB with 0.3 q of noise (3 seeds); a model fed the period
    sum instead of the mean, or a dither estimate that keeps the q^2/12 of the steps in it,
    gives +12 .. +21 dB there."""
    m, p, n, fs = 4, 4, 1024, 1024.0
    d = multisine_realizations(m, fs, n, k_min=1, k_max=120, seed=11, rms=1.0)
    u = np.repeat(np.stack([x.period for x in d])[:, None, :], p, axis=1)
    rng = np.random.default_rng(11)
    h = np.fft.irfft(np.fft.rfft(u, axis=-1) * (0.9 / (1 + 1j * np.arange(n // 2 + 1) / 40.0)),
                     n=n, axis=-1)
    q = 2 * np.pi / 200
    y = np.round((h + 0.3 * q + dither_re_q * q * rng.standard_normal(h.shape)) / q) * q
    res = robust_bla(u, y, fs=fs, excited_bins=d[0].excited, y_quantisation_step=q,
                     warn_transient=False)
    med = res.summary["plant_line_median_re_quantisation_floor_db"]
    assert med is not None and low_db < med < high_db, med
    assert res.summary["plant_nl_detected"] is False


def test_full_grid_quantisation_floor_is_the_white_model():
    """No non-excited line (a full grid): the quantisation floor reported is the white
    model 4 (q^2 / 12) / N at the line level."""
    m, p, n, fs = 3, 3, 256, 256.0
    d = multisine_realizations(m, fs, n, k_min=1, k_max=60, kind="full", seed=12)
    u = np.repeat(np.stack([x.period for x in d])[:, None, :], p, axis=1)
    q = 1e-3
    y = np.round((0.5 * u + 1e-4 * np.random.default_rng(12).standard_normal(u.shape)) / q) * q
    res = robust_bla(u, y, fs=fs, excited_bins=d[0].excited, y_quantisation_step=q,
                     warn_transient=False)
    assert res.nonexcited_bins.size == 0
    assert res.summary["quantisation_floor_db"] == pytest.approx(
        10 * np.log10(q ** 2 / (3.0 * n)), abs=1e-9)
