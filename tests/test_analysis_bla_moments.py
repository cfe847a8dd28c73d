"""The robust BLA from line moments (a drive's line statistics) against the same estimate
from the samples: fftune.analysis.bla.robust_bla_moments fed by
fftune.analysis.stats.line_moments(line_stats(...)) must give robust_bla's G, variances,
levels and verdict flags, on a plant with odd and even distortion and noise, with the
reference known (closed loop)."""
import numpy as np
import pytest

from fftune.analysis.bla import LineMoments, robust_bla, robust_bla_moments, robust_bla_spectra
from fftune.analysis.errors import InputError
from fftune.analysis.multisine import drive_lines, drive_multisine
from fftune.analysis.stats import LineStats, line_moments, line_stats

N, M, P, FS = 512, 4, 4, 1000.0


def _closed_loop(m, *, rms=1.0, noise=1e-3, a2=0.05, a3=0.2, seed=0):
    """A closed loop with a static nonlinearity before a first-order plant: r -> u -> y."""
    lines = drive_lines(N, 3, 100, 4, 11)
    r = np.tile(drive_multisine(N, 3, 100, 4, 11, m, rms), P + 1)
    rng = np.random.default_rng(seed + m)
    y = np.zeros_like(r)
    u = np.zeros_like(r)
    state = 0.0
    for i in range(r.size):
        u[i] = r[i] - 0.5 * state
        v = u[i] + a2 * u[i] ** 2 + a3 * u[i] ** 3
        state = 0.9 * state + 0.1 * v
        y[i] = state
    y += noise * rng.standard_normal(y.size)
    u += 0.1 * noise * rng.standard_normal(u.size)
    # the first period is the transient: dropped, as the drive drops its settle periods
    return u[N:], y[N:], r[N:], lines


@pytest.fixture(scope="module")
def runs():
    return [_closed_loop(m) for m in range(M)]


def test_moments_give_the_estimate_of_the_samples(runs):
    lines = runs[0][3]
    u = np.stack([x[0].reshape(P, N) for x in runs])
    y = np.stack([x[1].reshape(P, N) for x in runs])
    r = np.stack([x[2].reshape(P, N) for x in runs])
    raw = robust_bla(u, y, r, fs=FS, excited_bins=lines.excited, warn_transient=False)
    band = np.arange(lines.excited[0], lines.excited[-1] + 1)
    stats = [line_stats(x[0], x[1], x[2], n=N, bins=band) for x in runs]
    mom = robust_bla_moments(line_moments(stats), n_period=N, fs=FS, excited_bins=lines.excited)
    np.testing.assert_allclose(mom.G, raw.G, rtol=1e-10)
    for name in ("var_total", "var_noise", "var_nl"):
        np.testing.assert_allclose(getattr(mom, name), getattr(raw, name), rtol=1e-8,
                                   atol=1e-12 * np.max(np.abs(getattr(raw, name))), err_msg=name)
    for name in ("output_db", "odd_db", "even_db", "odd_noise_db", "plant_db", "nonexcited_db"):
        np.testing.assert_allclose(getattr(mom, name), getattr(raw, name), atol=1e-8, err_msg=name)
    # the distortion is there and both say so (the plant's even and odd terms)
    assert raw.summary["odd_detected"] and raw.summary["even_detected"]
    def same(a, b, key):
        if isinstance(b, float):
            assert a == pytest.approx(b, rel=1e-8, abs=1e-8), key
        elif isinstance(b, dict):
            assert a.keys() == b.keys(), key
            for k in b:
                same(a[k], b[k], f"{key}.{k}")
        elif isinstance(b, list):
            assert len(a) == len(b), key
            for i, (x, y) in enumerate(zip(a, b)):
                same(x, y, f"{key}[{i}]")
        else:
            assert a == b, key
    # (the lines above the band are not in the moments: only the samples give them)
    assert raw.summary["above_band_lines"] > 0 and "above_band_lines" not in mom.summary
    for key, value in raw.summary.items():
        if not key.startswith("above_band_"):
            same(mom.summary[key], value, key)
    assert "transient not checked" in " ".join(mom.notes)
    assert not mom.transient.suspect


def test_the_generated_reference_replaces_the_recorded_one(runs):
    """Plant-input injection: the drive records no excitation, the host's regeneration of it
    is the reference (line_moments(reference=...))."""
    lines = runs[0][3]
    band = np.arange(lines.excited[0], lines.excited[-1] + 1)
    zero_r = [line_stats(x[0], x[1], np.zeros_like(x[2]), n=N, bins=band) for x in runs]
    ref = np.stack([np.fft.rfft(drive_multisine(N, 3, 100, 4, 11, m, 1.0))[band] for m in range(M)])
    with pytest.raises(InputError, match="reference r: zero power"):
        robust_bla_moments(line_moments(zero_r), n_period=N, fs=FS, excited_bins=lines.excited)
    good = [line_stats(x[0], x[1], x[2], n=N, bins=band) for x in runs]
    a = robust_bla_moments(line_moments(zero_r, reference=ref), n_period=N, fs=FS,
                           excited_bins=lines.excited)
    b = robust_bla_moments(line_moments(good), n_period=N, fs=FS, excited_bins=lines.excited)
    np.testing.assert_allclose(a.G, b.G, rtol=1e-9)


def test_bad_moments_are_refused_with_the_reason(runs):
    lines = runs[0][3]
    band = np.arange(lines.excited[0], lines.excited[-1] + 1)
    stats = [line_stats(x[0], x[1], x[2], n=N, bins=band) for x in runs]
    # a gap in the lines: the detection lines between the excited ones are needed
    gap = [line_stats(x[0], x[1], x[2], n=N, bins=band[band != band[5]]) for x in runs]
    with pytest.raises(InputError, match="every line"):
        robust_bla_moments(line_moments(gap), n_period=N, fs=FS, excited_bins=lines.excited)
    mixed = stats[:2] + [line_stats(runs[2][0][:N], runs[2][1][:N], runs[2][2][:N], n=N, bins=band)]
    with pytest.raises(InputError, match="realization 2: 1 periods"):
        line_moments(mixed)
    with pytest.raises(InputError, match="no realization"):
        line_moments([])
    import dataclasses
    nan_y = stats[:1] + [dataclasses.replace(stats[1], Y=np.where(band == band[3], np.nan, stats[1].Y))] + stats[2:]
    with pytest.raises(InputError, match=rf"realization 1: non-finite values at 1 line\(s\), first bin {band[3]}"):
        line_moments(nan_y)
    with pytest.raises(InputError, match=r"reference spectra of shape \(1, 3\)"):
        line_moments(stats, reference=np.ones((1, 3)))
    mom = line_moments(stats)
    no_ref = LineMoments(**{**mom.__dict__, "R": None})
    with pytest.raises(InputError, match="reference R is needed"):
        robust_bla_moments(no_ref, n_period=N, fs=FS, excited_bins=lines.excited)
    bad = LineMoments(**{**mom.__dict__, "ss_y": mom.ss_y[:, :5]})
    with pytest.raises(InputError, match="ss_y: expected shape"):
        robust_bla_moments(bad, n_period=N, fs=FS, excited_bins=lines.excited)
    with pytest.raises(InputError, match="sample rate"):
        robust_bla_moments(mom, n_period=N, fs=float("nan"), excited_bins=lines.excited)


def test_one_period_gives_the_estimate_without_noise_variance(runs):
    lines = runs[0][3]
    band = np.arange(lines.excited[0], lines.excited[-1] + 1)
    one = [line_stats(x[0][:N], x[1][:N], x[2][:N], n=N, bins=band) for x in runs]
    res = robust_bla_moments(line_moments(one), n_period=N, fs=FS, excited_bins=lines.excited)
    raw = robust_bla(np.stack([x[0][:N].reshape(1, N) for x in runs]),
                     np.stack([x[1][:N].reshape(1, N) for x in runs]),
                     np.stack([x[2][:N].reshape(1, N) for x in runs]), fs=FS,
                     excited_bins=lines.excited, warn_transient=False)
    assert res.var_noise is None and res.var_nl is None
    np.testing.assert_allclose(res.var_total, raw.var_total, rtol=1e-8)
    assert isinstance(one[0], LineStats) and np.isnan(one[0].var_u).all()


def _one_line_moments(U, Y, R, ss_u=None, ss_y=None, s_yu=None, periods=4):
    """LineMoments of M realizations at the lines 5 .. 9 (5, 7, 9 excited, 6, 8 not)."""
    U, Y, R = (np.asarray(x, dtype=complex) for x in (U, Y, R))
    zeros = np.zeros(U.shape)
    return LineMoments(bins=np.arange(5, 10), n_periods=periods, U=U, Y=Y,
                       ss_u=zeros if ss_u is None else ss_u, ss_y=zeros if ss_y is None else ss_y,
                       s_yu=zeros + 0j if s_yu is None else s_yu, R=R)


def test_known_reference_variances_by_their_formulas():
    """G = mean Y / mean U over the rotated realizations; var_total = (s2y + |G|^2 s2u
    - 2 Re(conj G c_yu)) / |U|^2 from the spread of the realizations' means, var_noise the
    same from the period sums / (P (P - 1) M^2) (docs/method.md), computed here by hand."""
    rng = np.random.default_rng(5)
    M, L, P = 3, 5, 4
    R = np.exp(2j * np.pi * rng.random((M, L)))
    U = (2.0 + 0.3 * rng.standard_normal((M, L))) * R
    Y = (1.0 - 0.5j + 0.2 * rng.standard_normal((M, L))) * U
    ss_u, ss_y = 0.1 + rng.random((M, L)), 0.2 + rng.random((M, L))
    s_yu = 0.05 * (rng.standard_normal((M, L)) + 1j * rng.standard_normal((M, L)))
    res = robust_bla_moments(_one_line_moments(U, Y, R, ss_u, ss_y, s_yu, periods=P), n_period=64,
                             fs=0.5, excited_bins=[5, 7, 9])
    e = [0, 2, 4]
    rot = np.conj(R[:, e] / np.abs(R[:, e]))
    Um, Ym = U[:, e] * rot, Y[:, e] * rot
    Ub, Yb = Um.mean(0), Ym.mean(0)
    G = Yb / Ub
    np.testing.assert_allclose(res.G, G, rtol=1e-13)
    du, dy = Um - Ub, Ym - Yb
    k = M * (M - 1)
    s2u, s2y, cyu = (np.abs(du) ** 2).sum(0) / k, (np.abs(dy) ** 2).sum(0) / k, (dy * np.conj(du)).sum(0) / k
    var_total = (s2y + np.abs(G) ** 2 * s2u - 2 * np.real(np.conj(G) * cyu)) / np.abs(Ub) ** 2
    np.testing.assert_allclose(res.var_total, var_total, rtol=1e-12)
    k = P * (P - 1) * M ** 2
    var_noise = (ss_y[:, e].sum(0) / k + np.abs(G) ** 2 * ss_u[:, e].sum(0) / k
                 - 2 * np.real(np.conj(G) * s_yu[:, e].sum(0) / k)) / np.abs(Ub) ** 2
    np.testing.assert_allclose(res.var_noise, var_noise, rtol=1e-12)
    np.testing.assert_allclose(res.var_nl, M * (var_total - var_noise), rtol=1e-12)
    assert res.fs == 0.5 and res.freq[0] == pytest.approx(5 * 0.5 / 64)


def test_an_excited_line_without_input_power_is_named():
    """The input's power at an excited line, P |mean U|^2 + its sum of squares over the
    realizations: 1e-7 of the others in amplitude is 1e-14 in power, "zero"."""
    M = 3
    R = np.ones((M, 5), complex)
    U = np.ones((M, 5), complex)
    U[:, 2] = 1e-7                     # bin 7
    with pytest.raises(InputError, match=r"input u: zero power at 1 excited line\(s\) 0.109375 Hz"):
        robust_bla_moments(_one_line_moments(U, 2 * U, R), n_period=64, fs=1.0, excited_bins=[5, 7, 9])
    # the sums of squares count too: the same mean with a period-to-period spread is not zero
    ss_u = np.zeros((M, 5))
    ss_u[:, 2] = 1e-6
    res = robust_bla_moments(_one_line_moments(U, 2 * U, R, ss_u=ss_u), n_period=64, fs=1.0,
                             excited_bins=[5, 7, 9])
    np.testing.assert_allclose(res.G, 2.0)


def test_moments_defaults_and_the_periods_check():
    M = 3
    R = np.ones((M, 5), complex)
    U = np.ones((M, 5), complex)
    res = robust_bla_moments(_one_line_moments(U, 2 * U, R), n_period=64, excited_bins=[5, 7, 9])
    assert res.fs == 1.0 and res.settle_periods == 0 and res.n_periods == 4
    assert res.freq[1] == pytest.approx(7 / 64)
    with pytest.raises(InputError, match="P = 0 periods"):
        robust_bla_moments(_one_line_moments(U, 2 * U, R, periods=0), n_period=64, excited_bins=[5, 7, 9])


def test_a_noisy_reference_is_not_a_distorted_one():
    """The reference's spread over periods at the non-excited lines is its noise: a
    reference with noise but no distortion is not reported distorted (its sums of squares
    reach the estimator with the known reference)."""
    rng = np.random.default_rng(3)
    lines = drive_lines(N, 3, 100, 4, 11)
    u, y, r = [], [], []
    for m in range(M):
        one = drive_multisine(N, 3, 100, 4, 11, m, 1.0)
        rm = np.tile(one, (P, 1)) + 1e-3 * rng.standard_normal((P, N))
        r.append(rm)
        u.append(rm)
        y.append(0.5 * rm + 1e-3 * rng.standard_normal((P, N)))
    res = robust_bla(np.stack(u), np.stack(y), np.stack(r), fs=FS, excited_bins=lines.excited,
                     warn_transient=False)
    assert res.summary["excitation_nonexcited_re_excited_db"] > -100.0   # the noise is visible
    assert res.summary["excitation_distorted"] is False
    np.testing.assert_allclose(np.abs(res.G), 0.5, rtol=1e-2)


def test_settle_periods_must_leave_a_period_and_four_samples_are_enough():
    U = np.ones((2, 3, 5), complex)
    with pytest.raises(InputError, match=r"settle periods T = 3 must be in 0 \.\. 2"):
        robust_bla_spectra(U, U, U, bins=np.arange(5, 10), n_period=64, settle_periods=3,
                           excited_bins=[5, 7, 9])
    # N = 4: one excited line (bin 1), the smallest period robust_bla takes
    t = np.arange(4)
    r = np.stack([np.tile(np.cos(np.pi / 2 * t + ph), (3, 1)) for ph in (0.1, 1.0)])
    res = robust_bla(r, 3 * r, r, excited_bins=[1], warn_transient=False)
    np.testing.assert_allclose(res.G, [3.0])
    with pytest.raises(InputError, match="N = 3 is too small"):
        robust_bla(r[..., :3], r[..., :3], excited_bins=[1])


def test_plant_figures_from_five_excited_lines_and_the_residual_spread():
    """y = 0.5 u exactly, period by period, with noise in u at every line: the plant-referred
    residual Y - G U is 0 in each period, so its spread (the cross term cancels the two
    squares) leaves only the rounding floor; five excited lines are enough for it."""
    rng = np.random.default_rng(9)
    n, m_real, p = 64, 3, 4
    excited = np.array([5, 7, 9, 11, 13])
    bins = np.arange(5, 14)
    R = np.zeros((m_real, p, bins.size), complex)
    R[:, :, np.isin(bins, excited)] = np.exp(2j * np.pi * rng.random((m_real, 1, excited.size)))
    U = R + 1e-2 * (rng.standard_normal(R.shape) + 1j * rng.standard_normal(R.shape))
    res = robust_bla_spectra(U, 0.5 * U, R, bins=bins, n_period=n, excited_bins=excited)
    assert res.plant_db is not None and res.plant_expected_db is not None
    u_noise_db = 10 * np.log10((2.0 / n) ** 2 * 1e-4 * 2 / p)      # the input's noise per line
    assert np.nanmax(np.where(np.isnan(res.plant_db), -np.inf, res.plant_db)) < u_noise_db - 100.0
    # the output is at its noise at the detection lines: G U there is taken as the input's
    # measurement noise (issue 23), so it is what is expected, not distortion
    g_u_db = 10 * np.log10((2.0 / n) ** 2 * np.mean(np.abs(0.5 * U.mean(axis=1)[:, [1, 3, 5, 7]]) ** 2, axis=0))
    np.testing.assert_allclose(res.plant_expected_db, g_u_db, atol=0.5)
    four = robust_bla_spectra(U[..., :-1], 0.5 * U[..., :-1], R[..., :-1], bins=bins[:-1], n_period=n,
                              excited_bins=excited[:-1])
    assert four.plant_db is None


def test_excited_level_of_the_reference_is_per_line_over_realizations():
    """excitation_nonexcited_re_excited_db: median over the lines of the realizations' mean
    power, against the same at the non-excited lines (one realization 40 dB louder)."""
    M = 3
    R = np.ones((M, 5), complex)
    R[2] *= 100.0
    R[:, [1, 3]] = 1e-3                    # the non-excited lines 6 and 8
    U = R.copy()
    ss = np.full((M, 5), 1e-8)
    res = robust_bla_moments(LineMoments(bins=np.arange(5, 10), n_periods=4, U=U, Y=2 * U, ss_u=ss,
                                         ss_y=ss, s_yu=np.zeros((M, 5), complex), R=R),
                             n_period=64, excited_bins=[5, 7, 9])
    exc = np.mean(np.abs(R[:, [0, 2, 4]]) ** 2, axis=0)          # per line over realizations
    det = np.mean(np.abs(R[:, [1, 3]]) ** 2, axis=0)
    expected = 10 * np.log10(np.median(det)) - 10 * np.log10(np.median(exc))
    assert res.summary["excitation_nonexcited_re_excited_db"] == pytest.approx(expected, abs=1e-9)


# ---- internals of the detection, by their definitions -----------------------------------------

def test_split_by_gap_keeps_min_lower_values_under_the_split():
    from fftune.analysis.bla import _split_by_gap
    # the largest gap (38 dB) leaves exactly 2 values under it: allowed, threshold mid-gap
    assert _split_by_gap(np.array([50.0, 49.0, 48.0, 10.0, 9.0]), 2) == (29.0, 38.0)
    # 3 needed under it: the next allowed gap
    assert _split_by_gap(np.array([50.0, 49.0, 48.0, 10.0, 9.0]), 3) == (49.5, 1.0)
    assert _split_by_gap(np.array([5.0, 4.0]), 2) == (None, 0.0)


def test_false_alarm_count_and_class_detection_at_the_count():
    from fftune.analysis.bla import _class_stats, _false_alarm_count
    assert _false_alarm_count(1, 1e-9) == 1          # at least one line, whatever the odds
    assert _false_alarm_count(0, 0.5) is None
    nu = 40
    p_line = (1.0 + 4.0 / nu) ** (-nu)
    need = _false_alarm_count(50, p_line)
    level = np.ones(50)
    level[:need] = 4.5                               # exactly `need` lines 6 dB over (not alone
    ref = np.ones(50)                                # significant: 50 x p(4.5) > 1e-3)
    out = _class_stats(level, ref, nu, "x_")
    assert out["x_lines_over_noise_6db"] == need == out["x_lines_needed"]
    assert out["x_detected"] is True
    level[need - 1] = 1.0
    assert _class_stats(level, ref, nu, "x_")["x_detected"] is False
    # one complex degree of freedom is enough for the statistics (M = 1, P = 2)
    assert _class_stats(level, ref, 1, "x_")["x_detected"] is not None


def test_duplicate_excited_bins_count_once_and_tiny_excitations_are_found():
    from fftune.analysis.bla import detect_excited_lines
    M = 3
    R = np.ones((M, 5), complex)
    res = robust_bla_moments(_one_line_moments(R, 2 * R, R), n_period=64, excited_bins=[9, 5, 5, 7])
    np.testing.assert_array_equal(res.bins, [5, 7, 9])
    # an excitation of 1e-9 amplitude: its lines stand 120 dB over exact zeros all the same
    lines = drive_lines(N, 3, 100, 4, 11)
    x = np.stack([np.tile(drive_multisine(N, 3, 100, 4, 11, m, 1e-9), (2, 1)) for m in range(2)])
    np.testing.assert_array_equal(detect_excited_lines(x), lines.excited)
    with pytest.raises(InputError, match="zero power in the input spectrum"):
        detect_excited_lines(np.zeros((2, 2, 64)))


def test_db_helpers_at_zero_and_non_finite_without_warnings():
    import warnings
    from fftune.analysis.bla import _db_ratio, to_db
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # no log10(0) taken and then discarded
        np.testing.assert_array_equal(to_db(np.array([0.0, -1.0, 100.0])), [np.nan, np.nan, 20.0])
    assert _db_ratio(np.inf, 1.0) is None and _db_ratio(1.0, np.nan) is None
    assert _db_ratio(10.0, 1.0) == pytest.approx(10.0)


def test_robust_bla_call_conventions_notes_and_warnings():
    import warnings
    from fftune.analysis.bla import TransientWarning
    n = 64
    t = np.arange(n)
    x = sum(np.cos(2 * np.pi * k * t / n + k) for k in (3, 5, 7, 9, 11))
    r = np.tile(x, (1, 1, 1))                       # M = 1, P = 1: two notes
    res = robust_bla(r, 2 * r, r, warn_transient=False)
    assert res.fs == 1.0
    assert res.notes[0].startswith("excited lines found from the spectrum of r: 5 lines")
    assert len(res.notes) >= 3
    with pytest.raises(TypeError):
        robust_bla(r, 2 * r, r, 2.0)                # fs only by keyword
    with pytest.raises(InputError, match=r"bins must lie in 1 \.\. 31 for N = 64"):
        robust_bla(r, 2 * r, r, excited_bins=[40])
    # a transient: warned once, from robust_bla, pointing at the caller; none when not asked
    tr = np.tile(x, (2, 4, 1))
    y = 2 * tr
    y[:, 0] += 5.0 * np.cos(2 * np.pi * 3 * t / n)
    with pytest.warns(TransientWarning) as rec:
        robust_bla(tr, y, tr)
    assert len(rec) == 1 and rec[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        robust_bla(tr, y, tr, warn_transient=False)


def test_quantisation_step_from_three_levels_and_bla_levels_rms_over_all_periods():
    from fftune.analysis.bla import bla_levels, estimate_quantisation_step
    assert estimate_quantisation_step([0.0, 0.25, 0.5]) == 0.25
    assert estimate_quantisation_step([0.0, 0.25]) is None
    assert estimate_quantisation_step([1.0, 1.0, 1.0]) is None
    n = 64
    t = np.arange(n)
    x = sum(np.cos(2 * np.pi * k * t / n + k) for k in (3, 5, 7, 9, 11))
    r = np.stack([np.stack([x, x]) * s for s in (1.0, 1.0)])
    # the first realization louder (a louder first period is a level step, refused since
    # issue 31; realizations at two levels are kept with a note)
    r[0] *= 3.0
    lv = bla_levels([r], [2 * r], [r], excited_bins=[3, 5, 7, 9, 11], warn_transient=False)
    assert lv.rms[0] == pytest.approx(np.sqrt(np.mean(r ** 2)))
    assert any("2 different levels" in note for note in lv.results[0].notes)


def test_linear_verdict_names_the_saturated_share():
    from fftune.analysis.bla import level_verdict
    summary = {"odd_detected": False, "even_detected": False, "nl_detected": False,
               "parity_classifiable": True}
    v = level_verdict(summary, 0.01, "1 V rms")
    assert v["causes"] == ["linear"]
    assert v["text"] == ("linear at 1 V rms: no nonlinear distortion above the noise "
                         "(though 1 % of the samples at u_max)")


def _spectrum_signal(n, amplitudes):
    """One period of a real signal with the given line amplitudes (bin -> amplitude)."""
    X = np.zeros(n // 2 + 1, complex)
    for k, a in amplitudes.items():
        X[k] = a * n / 2 * np.exp(1j * 0.7 * k)
    return np.fft.irfft(X, n)


def test_excited_lines_found_by_the_gap_and_its_limits():
    from fftune.analysis.bla import detect_excited_lines
    n = 32                                            # 15 lines: no local-threshold fallback
    exc = {1: 1.0, 3: 1.0, 5: 1.0, 9: 1.0, 11: 1.0, 13: 1.0}
    low = 10 ** (-9.5 / 20)                           # the others 9.5 dB under
    x = _spectrum_signal(n, {k: exc.get(k, low) for k in range(1, 16)})
    x = np.tile(x, (2, 2, 1))
    with pytest.raises(InputError, match="cannot tell excited"):
        detect_excited_lines(x)                       # gap 9.5 dB < 10 dB
    found, info = detect_excited_lines(x, min_gap_db=9.5 - 1e-9, return_info=True)
    np.testing.assert_array_equal(found, sorted(exc))
    # exactly at the gap: still found (>=)
    np.testing.assert_array_equal(detect_excited_lines(x, min_gap_db=info["separation_db"]), sorted(exc))


def _sloped(n, over_db, slope_db=1.0):
    """Odd lines excited over a spectrum falling `slope_db` a line; the even lines `over_db`
    under their odd neighbours: no clean gap overall, a clear one re the local floor."""
    amps = {}
    for k in range(1, (n + 1) // 2):
        lvl = -slope_db * k - (0.0 if k % 2 else over_db)
        amps[k] = 10 ** (lvl / 20)
    return np.tile(_spectrum_signal(n, amps), (2, 2, 1))


def test_excited_lines_by_the_local_floor_from_64_lines_on():
    from fftune.analysis.bla import detect_excited_lines
    x = _sloped(130, 30.0)                            # 64 lines
    found, info = detect_excited_lines(x, return_info=True)
    assert info["method"] == "local threshold"
    # every found line is excited; the top one (63, beside the reflected edge of the
    # window) may be missed
    assert set(found) <= set(range(1, 65, 2)) and found.size >= 31
    assert "3.1 % of the lines lie within 3 dB" in info["note"]     # 2 of 64, at the edges
    with pytest.raises(InputError, match="cannot tell excited"):
        detect_excited_lines(_sloped(128, 30.0))      # 63 lines: the gap alone
    # 15 dB re the local floor: too little separation (needs 2 x 10 dB), though no line lies
    # within 3 dB of the threshold (128 lines, 0.3 dB a line)
    with pytest.raises(InputError, match="cannot tell excited"):
        detect_excited_lines(_sloped(258, 15.0, 0.3))
    # robust_bla names both how the lines were found and that the input looks distorted
    res = robust_bla(x, 2 * x, warn_transient=False)
    assert res.notes[0].startswith(f"excited lines found from the spectrum of u: {found.size} lines")
    assert res.notes[1].startswith("excited lines found by a threshold on the level re the local floor")


def test_transient_check_thresholds_by_construction():
    """Per period: the excited lines' deviation from the steady state (the mean of the last
    half), re its power. Kept periods 1 .. 4: the noise is their median after the first
    (delta^2); the first kept period and the last settle period at 9.5 delta^2 are not
    over 10 x the noise, at 10.5 delta^2 they are."""
    d = 1e-2
    bins = np.arange(5, 10)

    def run(k0, k1):
        dev = np.array([np.sqrt(k0) * d, np.sqrt(k1) * d, d, d, -d])
        Y = (1.0 + dev)[None, :, None] * np.ones((2, 5, 5))
        U = np.ones((2, 5, 5), complex)
        return robust_bla_spectra(U, Y, bins=bins, n_period=64, settle_periods=1,
                                  excited_bins=[5, 7, 9], warn_transient=False).transient

    quiet = run(9.5, 9.5)
    assert quiet.suspect is False and quiet.settle_differs is False
    np.testing.assert_allclose(10 ** (quiet.level_db / 10), np.array([9.5, 9.5, 1, 1, 1]) * d ** 2, rtol=1e-9)
    loud = run(10.5, 10.5)
    assert loud.suspect is True and loud.settle_differs is True
    # P = 1 kept period: the steady state is that period (level 0 there, finite elsewhere)
    Y1 = np.ones((2, 2, 5))
    Y1[:, 0] = 1.3                                    # the settle period 0.3 off
    one = robust_bla_spectra(np.ones((2, 2, 5), complex), Y1, bins=bins, n_period=64,
                             settle_periods=1, excited_bins=[5, 7, 9], warn_transient=False).transient
    np.testing.assert_allclose(10 ** (one.level_db[0] / 10), 0.09, rtol=1e-9)
    # no output at all: no level to compare with, NaN and no warning
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        zero = robust_bla_spectra(np.ones((2, 3, 5), complex), np.zeros((2, 3, 5)), bins=bins,
                                  n_period=64, excited_bins=[5, 7, 9], warn_transient=False)
    assert np.all(np.isnan(zero.transient.level_db))


def test_float64_records_keep_their_own_rounding_floor():
    """y in float64 (not float32 values): the rounding floor is 2^-53 of max|y|, so a
    distortion 180 dB under the output at an even line is still seen; a float32 floor
    would hide it."""
    n = 64
    x = _spectrum_signal(n, {3: 1.0, 5: 1.0, 7: 1.0, 9: 1.0, 13: 1.0})
    y = 2 * x + _spectrum_signal(n, {8: 1e-9})
    res = robust_bla(np.tile(x, (2, 3, 1)), np.tile(y, (2, 3, 1)), np.tile(x, (2, 3, 1)),
                     excited_bins=[3, 5, 7, 9, 13], warn_transient=False, fs=2.0)
    assert res.summary["even_detected"] is True
    np.testing.assert_array_equal(res.even_freq, res.even_bins * 2.0 / n)
    assert list(res.odd_bins) == [11]
    np.testing.assert_array_equal(res.odd_freq, [11 * 2.0 / n])


def _crafted(det_levels, det_ratio, r_det_db=None):
    """Line moments at bins 5 .. 13 (5, 7, 9, 11, 13 excited; 6, 8, 10, 12 not), M = 3, P = 4:
    the output's period mean at the non-excited lines over its noise as given (input 0
    there, so the plant-referred residual is the output itself)."""
    M, P = 3, 4
    bins = np.arange(5, 14)
    exc = np.isin(bins, [5, 7, 9, 11, 13])
    U = np.where(exc, 1.0, 0.0) * np.ones((M, 1)) + 0j
    R = U.copy()
    if r_det_db is not None:
        R[:, ~exc] = 10 ** (r_det_db / 20)
    Y = 2.0 * U
    ss_y = np.full((M, bins.size), 1e-6)
    Y[:, ~exc] = np.sqrt(np.asarray(det_ratio) * 1e-6 / (P * (P - 1))) * np.asarray(det_levels)
    return LineMoments(bins=bins, n_periods=P, U=U, Y=Y, ss_u=np.zeros((M, bins.size)), ss_y=ss_y,
                       s_yu=np.zeros((M, bins.size), complex), R=R,
                       ss_r=np.full((M, bins.size), 1e-40))


def test_six_db_counts_by_construction():
    """A line counts as 6 dB over its noise at 4 x its noise power: ratios 4.5 and 3.5 give one
    such line of four, plant-referred and in the closed loop alike."""
    res = robust_bla_moments(_crafted([1, 1, 0, 0], [4.5, 3.5, 1, 1]), n_period=64,
                             excited_bins=[5, 7, 9, 11, 13])
    assert res.summary["plant_above_noise_lines"] == 1
    assert res.summary["nonexcited_lines_over_noise_6db"] == 1


def test_nonlinear_over_noise_fraction_at_six_db():
    """var_total = 4.5 var_noise (ratio var_nl / (M var_noise) 3.5): no line 6 dB over; at
    5.5 (4.5) every line."""
    M, P, s = 3, 4, 1e-4
    bins = np.arange(5, 10)
    for total_re_noise, expected in ((4.5, 0.0), (5.5, 1.0)):
        a = np.sqrt(total_re_noise * s / (P * (P - 1)))
        Y = (2.0 + np.array([a, -a, 0.0]))[:, None] * np.ones((1, 5)) + 0j
        mom = LineMoments(bins=bins, n_periods=P, U=np.ones((M, 5), complex), Y=Y,
                          ss_u=np.zeros((M, 5)), ss_y=np.full((M, 5), s),
                          s_yu=np.zeros((M, 5), complex), R=np.ones((M, 5), complex))
        res = robust_bla_moments(mom, n_period=64, excited_bins=[5, 7, 9])
        np.testing.assert_allclose(res.var_total / res.var_noise, total_re_noise, rtol=1e-9)
        assert res.summary["line_fraction_nl_over_noise_6db"] == expected


def test_reference_distortion_is_named_from_100_db_under_the_lines():
    for db, distorted in ((-100.5, False), (-99.5, True)):
        res = robust_bla_moments(_crafted([0, 0, 0, 0], [1, 1, 1, 1], r_det_db=db), n_period=64,
                                 excited_bins=[5, 7, 9, 11, 13])
        assert res.summary["excitation_nonexcited_re_excited_db"] == pytest.approx(db, abs=1e-9)
        assert res.summary["excitation_distorted"] is distorted, db


def test_grid_with_its_top_line_removed_and_a_quantised_record_far_from_zero():
    from fftune.analysis.bla import classify_grid, estimate_quantisation_step
    assert classify_grid([1, 2, 3, 4, 6], 64)["grid"] == "full with removed lines"
    assert classify_grid([1, 2, 3, 4, 5], 64)["grid"] == "full"
    # one value off its step by 0.02 q + 3.6 eps max|v|: inside the float32 tolerance (4 eps)
    v = [0.0, 1.0, 2.0, 1000.0 + 0.02 + 3.6 * np.finfo(np.float32).eps * 1000.0]
    assert estimate_quantisation_step(v) == 1.0
    v[-1] = 1000.0 + 0.02 + 4.4 * np.finfo(np.float32).eps * 1000.0
    assert estimate_quantisation_step(v) is None


def test_more_definitions_sample_rate_settle_notes_and_floors():
    from fftune.analysis.bla import _median_db
    M = 2
    R = np.ones((M, 5), complex)
    U = np.ones((M, 5), complex)
    U[:, 2] = 1e-5                       # -100 dB: weak, not "zero" (that is -120 dB)
    for fs in (0.0, -0.5):
        with pytest.raises(InputError, match="positive sample rate"):
            robust_bla_moments(_one_line_moments(U, 2 * U, R, periods=2), n_period=64, fs=fs,
                               excited_bins=[5, 7, 9])
    res = robust_bla_moments(_one_line_moments(U, 2 * U, R, periods=2), n_period=64, fs=2.0,
                             excited_bins=[5, 7, 9], y_quantisation_step=1e-3)
    np.testing.assert_allclose(res.G, 2.0)
    # M = 2, P = 2: both variances, so neither "M = 1" nor "P = 1" note
    assert not any(n.startswith(("M = 1", "P = 1")) for n in res.notes)
    np.testing.assert_allclose(res.even_freq, res.even_bins * 2.0 / 64)
    q = robust_bla_moments(_crafted([1, 1, 1, 1], [4.5, 3.5, 2, 1]), n_period=64,
                           excited_bins=[5, 7, 9, 11, 13], y_quantisation_step=1e-3)
    # per line against the quantisation model at that line (issue 23: the model is per line)
    assert q.summary["plant_line_median_re_quantisation_floor_db"] == pytest.approx(
        float(np.median(q.plant_db - q.quantisation_db)), abs=1e-9)
    Us = np.ones((2, 2, 5), complex)
    with pytest.raises(InputError, match="settle periods T = -1"):
        robust_bla_spectra(Us, Us, Us, bins=np.arange(5, 10), n_period=64, settle_periods=-1,
                           excited_bins=[5, 7, 9])
    assert _median_db([]) is None and _median_db([5.0]) == 5.0
