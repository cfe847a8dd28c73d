"""Pins of track's numbers and policy, second set (issue 33's hand-written bug audit,
docs/testing.md): every expected value is computed here from the raw samples or the
documented rule (a slow reference), with unequal, asymmetric inputs, so that a wrong
divisor, a swapped weight, an ignored repetition count or a comparison at its threshold
fails. No drive_sim run: the estimator's and the tracker's contracts only."""
import math

import numpy as np
import pytest

from fftune.analysis.track import (TaskEstimate, TaskStats, Tracker, TrackSettings, drift_trend,
                                   estimate_task)

FS = 2560.0


def _raw_task(theta, rng, samples, noise_per_block, blocks):
    """One repetition's raw regressors and input: a fast short forward move and a slow long
    move back (asymmetric), noise of a different level in every block."""
    t = np.arange(samples) / FS
    T = t[-1]
    v = np.where(t < 0.3 * T, 5.0 * np.sin(np.pi * t / (0.3 * T)),
                 -1.6 * np.sin(np.pi * (t - 0.3 * T) / (0.7 * T)))
    v = v + 0.4 * np.sin(7 * np.pi * t / T)
    a = np.gradient(v, 1 / FS)
    s = np.sign(v)
    p, n = np.maximum(s, 0), np.minimum(s, 0)
    edges = [(b * samples) // blocks for b in range(blocks + 1)]
    sd = np.concatenate([np.full(edges[b + 1] - edges[b], noise_per_block[b]) for b in range(blocks)])
    u = theta[0] * p + theta[1] * n + theta[2] * v + theta[3] * a + sd * rng.standard_normal(samples)
    e = 2e-3 * rng.standard_normal(samples) + 1e-3
    return np.column_stack([p, n, v, a]), u, e, edges


def _stats_from_raw(reps, samples, blocks, theta, noise_per_block, seed):
    """The drive's block sums over ``reps`` repetitions, and the raw samples themselves."""
    rng = np.random.default_rng(seed)
    design = np.zeros((blocks, 9))
    data = np.zeros((blocks, 6))
    raw = []
    for _ in range(reps):
        Phi, u, e, edges = _raw_task(theta, rng, samples, noise_per_block, blocks)
        raw.append((Phi, u, e))
        for b in range(blocks):
            sl = slice(edges[b], edges[b + 1])
            P, N, V, A = Phi[sl].T
            U, E = u[sl], e[sl]
            design[b] += [P @ P, N @ N, P @ V, P @ A, N @ V, N @ A, V @ V, V @ A, A @ A]
            data[b] += [P @ U, N @ U, V @ U, A @ U, E @ E, U @ U]
    return TaskStats(reps, samples, design, data), raw, edges


def _reference(raw, edges, blocks):
    """Least squares on the raw samples of every repetition (all four parameters), and the
    sandwich covariance A^-1 (sum_b s2_b A_b) A^-1 with s2_b the block's residual variance
    (its RSS over its samples, times n / (n - 4))."""
    Phi = np.vstack([r[0] for r in raw])
    u = np.concatenate([r[1] for r in raw])
    e = np.concatenate([r[2] for r in raw])
    theta, *_ = np.linalg.lstsq(Phi, u, rcond=None)
    n, k = u.size, 4
    A = Phi.T @ Phi
    meat = np.zeros((4, 4))
    resid_all = 0.0
    for b in range(blocks):
        rows = np.concatenate([r[0][edges[b]:edges[b + 1]] for r in raw])
        ub = np.concatenate([r[1][edges[b]:edges[b + 1]] for r in raw])
        res = ub - rows @ theta
        resid_all += res @ res
        s2 = (res @ res) / ub.size * n / (n - k)
        meat += s2 * rows.T @ rows
    Ai = np.linalg.inv(A)
    V = Ai @ meat @ Ai
    return theta, V, math.sqrt(resid_all / n), math.sqrt(e @ e / n), n


@pytest.mark.parametrize("reps", [1, 3])
def test_estimate_against_a_least_squares_on_the_raw_samples(reps):
    """Every number of one task estimate against the raw-sample reference: the offset's
    sigma from its own weights (F_+ - F_-) / 2 (not K_fc's), the sandwich with each
    block's variance over that block's samples, and rms_error / rms_residual over every
    recorded sample (repetitions x samples)."""
    blocks, samples = 6, 3001
    theta_true = [0.142, 0.097, 0.011, 0.0052]
    noise = [0.02, 0.09, 0.035, 0.005, 0.06, 0.015]
    st, raw, edges = _stats_from_raw(reps, samples, blocks, theta_true, noise, seed=11 + reps)
    est = estimate_task(st, kv_unique_min=0.0)
    assert est.k_v_identified
    theta, V, rms_res, rms_err, n = _reference(raw, edges, blocks)
    w_fc, w_off = np.array([0.5, 0.5, 0, 0]), np.array([0.5, -0.5, 0, 0])
    assert est.samples == n == reps * samples
    assert est.k_fc == pytest.approx(w_fc @ theta, rel=1e-6)
    assert est.offset == pytest.approx(w_off @ theta, rel=1e-5, abs=1e-9)
    assert est.k_v == pytest.approx(theta[2], rel=1e-5)
    assert est.k_a == pytest.approx(theta[3], rel=1e-5)
    sig_fc, sig_off = math.sqrt(w_fc @ V @ w_fc), math.sqrt(w_off @ V @ w_off)
    # the data make the two clearly different (so swapped weights cannot pass)
    assert abs(sig_off / sig_fc - 1) > 0.1
    assert est.k_fc_sigma_stat == pytest.approx(sig_fc, rel=1e-4)
    assert est.offset_sigma == pytest.approx(sig_off, rel=1e-4)
    assert est.k_v_sigma == pytest.approx(math.sqrt(V[2, 2]), rel=1e-4)
    assert est.k_a_sigma == pytest.approx(math.sqrt(V[3, 3]), rel=1e-4)
    assert est.rms_residual == pytest.approx(rms_res, rel=1e-5)
    assert est.rms_error == pytest.approx(rms_err, rel=1e-9)


def _est(k_fc=0.12, sigma=1e-3, k_a=0.0061, k_a_sigma=1e-4, rms=0.004, k_v=0.0, kv_ok=False):
    return TaskEstimate(k_fc=k_fc, k_fc_sigma=sigma, k_v=k_v, k_v_sigma=0.0, k_a=k_a, k_a_sigma=k_a_sigma,
                        offset=0.0, offset_sigma=0.0, rms_error=rms, rms_residual=0.0, condition=1.0,
                        k_v_identified=kv_ok, samples=3000)


def test_sigma_exactly_at_the_limit_is_certain():
    # "above this fraction holds K_fc": a sigma equal to max_sigma_rel K_fc updates
    # (0.2 x 0.5 = 0.1 exactly in binary); one ulp above holds
    s = TrackSettings(max_sigma_rel=0.2, ka_max_sigma_rel=0.5)
    d = Tracker(k_fc=0.45, k_v=0.0, k_a=0.006, settings=s).after_task(_est(k_fc=0.5, sigma=0.1, k_a=0.006))
    assert d.action == "update" and d.k_fc == pytest.approx(0.5)
    d = Tracker(k_fc=0.45, k_v=0.0, k_a=0.006, settings=s).after_task(
        _est(k_fc=0.5, sigma=math.nextafter(0.1, 1.0), k_a=0.006))
    assert d.action == "hold" and d.k_fc == 0.45
    # K_a's own limit while K_fc is held: sigma equal to half of K_a still learns it
    d = Tracker(k_fc=0.45, k_v=0.0, k_a=0.0, settings=s).after_task(
        _est(k_fc=0.5, sigma=0.2, k_a=0.008, k_a_sigma=0.004))
    assert d.action == "hold" and d.k_a == pytest.approx(0.008)


def test_k_a_step_is_bounded_relative_to_k_a_on_update_and_hold():
    s = TrackSettings(ka_max_step_rel=0.5)
    # update: K_a 0.004 -> estimate 0.0130: at most +50 % of 0.004 = 0.006
    tr = Tracker(k_fc=0.12, k_v=0.0, k_a=0.004, settings=s)
    d = tr.after_task(_est(k_fc=0.121, k_a=0.0130))
    assert d.action == "update" and d.k_a == pytest.approx(0.006)
    d = tr.after_task(_est(k_fc=0.121, k_a=0.0130))
    assert d.k_a == pytest.approx(0.009)
    d = tr.after_task(_est(k_fc=0.121, k_a=0.0020))      # down: at most -50 % of 0.009
    assert d.k_a == pytest.approx(0.0045)
    # hold (K_fc uncertain): the same bound
    tr = Tracker(k_fc=0.12, k_v=0.0, k_a=0.004, settings=s)
    d = tr.after_task(_est(k_fc=0.121, sigma=0.1, k_a=0.0130))
    assert d.action == "hold" and d.k_a == pytest.approx(0.006)


def test_k_v_is_updated_only_where_the_task_identifies_it():
    s = TrackSettings(kv_max_step=0.005)
    tr = Tracker(k_fc=0.12, k_v=0.010, k_a=0.006, settings=s)
    d = tr.after_task(_est(k_fc=0.121, k_v=0.050, kv_ok=False))
    assert d.action == "update" and d.k_v == 0.010
    d = tr.after_task(_est(k_fc=0.121, k_v=0.050, kv_ok=True))
    assert d.k_v == pytest.approx(0.015)                  # bounded by kv_max_step
    d = tr.after_task(_est(k_fc=0.121, k_v=0.0171, kv_ok=True))
    assert d.k_v == pytest.approx(0.0171)
    tr = Tracker(k_fc=0.12, k_v=0.010, k_a=0.006, settings=TrackSettings(update_kv=False))
    assert tr.after_task(_est(k_fc=0.121, k_v=0.0123, kv_ok=True)).k_v == 0.010


def test_drift_trend_share_rule_tolerance_is_two_noises_of_a_change():
    # a ramp (zero second differences: the scatter is the floor s) whose last three
    # changes are 1.3, 0.25, 1.45 (mean 1.0): the smallest passes the share rule when
    # 0.25 >= 0.5 - 2 sqrt(2) s, i.e. s >= 0.0884 (a change's noise is sqrt 2 s); below,
    # no trend
    x = list(np.arange(7.0)) + [7.3, 7.55, 9.0]
    assert drift_trend(x, scatter_floor=0.11) == pytest.approx((1.3 + 0.25 + 1.45) / 3)
    assert drift_trend(x, scatter_floor=0.085) == 0.0
    # |m| must exceed 3 s
    assert drift_trend(x, scatter_floor=0.34) == 0.0


def test_scatter_sigma_reads_the_newest_window_only():
    from fftune.analysis.track import SCATTER_WINDOW, curvature_scatter, scatter_sigma
    rng = np.random.default_rng(5)
    old = list(0.2 + 0.05 * rng.standard_normal(7))              # noisy early tasks
    new = [0.1200, 0.1203, 0.1199, 0.1206, 0.1201, 0.1198, 0.1204, 0.1202, 0.1197, 0.1205]
    assert len(new) == SCATTER_WINDOW
    d = np.diff(new)
    expected = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
    assert scatter_sigma(old + new) == pytest.approx(expected, rel=1e-12)
    c = np.diff(new, 2)
    assert curvature_scatter(old + new) == pytest.approx(
        1.4826 * np.median(np.abs(c - np.median(c))) / math.sqrt(6.0), rel=1e-12)


# ---- second round: identifiability, the viscous watch, the noise note, the stops' limits --------

def test_kv_unique_fraction_is_one_minus_r2_of_v_on_p_n_a():
    from fftune.analysis.track import _kv_unique_fraction
    st, raw, _ = _stats_from_raw(1, 3001, 6, [0.142, 0.097, 0.011, 0.0052], [0.02] * 6, seed=3)
    Phi = raw[0][0]
    X, v = Phi[:, [0, 1, 3]], Phi[:, 2]
    coef, *_ = np.linalg.lstsq(X, v, rcond=None)
    frac = np.sum((v - X @ coef) ** 2) / np.sum(v ** 2)
    A = sum(normal_matrix_of(d) for d in st.design)
    assert 0.05 < frac < 0.95
    assert _kv_unique_fraction(A) == pytest.approx(frac, rel=1e-6)
    # a task whose velocity is nearly +-constant does not identify K_v: held, named
    est = estimate_task(st, kv_unique_min=frac * 1.01, k_v_hold=0.0123)
    assert not est.k_v_identified and est.k_v == 0.0123
    est = estimate_task(st, kv_unique_min=frac * 0.99)
    assert est.k_v_identified and est.k_v_free == pytest.approx(est.k_v, rel=1e-12)


def normal_matrix_of(d):
    from fftune.analysis.track import normal_matrix
    return normal_matrix(d)


def test_viscous_shift_count_latch_and_settled_rule():
    from fftune.analysis.track import (VISC_BASELINE_FROM, VISC_BASELINE_N, VISC_SHIFT_MIN_ABS,
                                       viscous_shift)
    base = [0.0150, 0.0152, 0.0149, 0.0151, 0.0153]
    early = [0.03, 0.02, 0.018, 0.016]
    assert len(early) == VISC_BASELINE_FROM and len(base) == VISC_BASELINE_N
    x = early + base + [0.0195, 0.0192]               # two tasks 27 % above: a change
    settled = [10.0, 10.03, 9.99]                    # K_fc within 0.5 % of its median
    shift, seen = viscous_shift(x, 0.015, settled)
    assert seen and shift == pytest.approx(np.median([0.0195, 0.0192]) - np.median(base))
    # one task less than the baseline plus two: nothing yet (even when the baseline's last
    # and the new one lie beyond the threshold; the baseline's median ignores its last)
    z = early + base[:-1] + [0.0196, 0.0195]
    assert viscous_shift(z, 0.015, settled) == (0.0, False)
    assert viscous_shift(z + [0.0194], 0.015, settled)[1]
    # K_fc not settled (0.8 % apart): no viscous change read
    assert viscous_shift(x, 0.015, [10.0, 10.08, 9.99]) == (0.0, False)
    # latched: the median of the last two minus the baseline, whatever its size
    y = early + base + [0.0158, 0.0149, 0.0161]
    shift, seen = viscous_shift(y, 0.015, None, latched=True)
    assert seen and shift == pytest.approx(np.median([0.0149, 0.0161]) - np.median(base))
    assert VISC_SHIFT_MIN_ABS < 0.0038


def test_noise_correction_its_note_and_its_part_of_the_systematic_sigma():
    """The bias model of issue 32's third pass: relative bias NOISE_BIAS_PER_RAD2 x
    (K_cal / gain_cal)^2 x r^2, r = gain x (the smallest noise bound of this and the
    earlier tasks) / |K_fc| (with this task's own bound r is the residual's rms over K_fc,
    whatever the gain); its note above a tenth of the floor; its size a part of the
    systematic sigma."""
    from fftune.analysis.track import (NOISE_BIAS_PER_RAD2, NOISE_CAL_GAIN_V_PER_RAD, NOISE_CAL_K_FC_V,
                                       NOTE_NOISE_CORRECTED, SCATTER_WINDOW, SYS_FLOOR_REL)
    coef = NOISE_BIAS_PER_RAD2 * (NOISE_CAL_K_FC_V / NOISE_CAL_GAIN_V_PER_RAD) ** 2
    gain = 31.0
    for scale, case in ((1.0, "bound"), (1.0, "own"), (2.5, "own")):
        st, raw, edges = _stats_from_raw(2, 3001, 6, [0.142, 0.097, 0.011, 0.0052],
                                         [scale * v for v in (0.02, 0.09, 0.035, 0.005, 0.06, 0.015)], seed=21)
        plain = estimate_task(st, kv_unique_min=0.0)
        sigma_n = plain.rms_residual / gain
        if case == "bound":       # an earlier task's smaller bound: r = gain b / K_fc
            b = 0.6 * sigma_n
            prev = [TaskEstimate(**{**plain.__dict__, "sensor_noise_rad": b})]
            r = gain * b / abs(plain.k_fc)
        else:                     # this task's own bound: r = rms_residual / K_fc
            prev = [TaskEstimate(**{**plain.__dict__, "sensor_noise_rad": 1.0})]
            r = plain.rms_residual / abs(plain.k_fc)
        est = estimate_task(st, kv_unique_min=0.0, noise_gain=gain, recent=prev)
        assert est.sensor_noise_rad == pytest.approx(sigma_n, rel=1e-9)
        corr = coef * r ** 2 * plain.k_fc
        assert est.k_fc_noise_correction == pytest.approx(corr, rel=1e-9)
        assert est.k_fc == pytest.approx(plain.k_fc + corr, rel=1e-12)
        assert (NOTE_NOISE_CORRECTED in est.notes) is (abs(corr) > 0.1 * SYS_FLOOR_REL * abs(plain.k_fc + corr))
        # (the split and model-error parts need earlier tasks: plain has none of them)
        assert plain.k_fc_sigma_split == plain.k_fc_sigma_model == 0.0
        assert est.k_fc_sigma_sys ** 2 == pytest.approx(
            plain.k_fc_sigma_sys ** 2 + corr ** 2 + est.k_fc_sigma_split ** 2 + est.k_fc_sigma_model ** 2
            + est.k_fc_sigma_viscous ** 2 - plain.k_fc_sigma_viscous ** 2, rel=1e-9)
    assert NOTE_NOISE_CORRECTED in est.notes          # (the 2.5x noise: the note; scale 1: none)
    # the smallest bound of the last SCATTER_WINDOW - 1 earlier tasks: an older one is not read
    older = [TaskEstimate(**{**plain.__dict__, "sensor_noise_rad": 1e-9})]
    recent = older + [TaskEstimate(**{**plain.__dict__, "sensor_noise_rad": 1.0})] * (SCATTER_WINDOW - 1)
    est2 = estimate_task(st, kv_unique_min=0.0, noise_gain=gain, recent=recent)
    assert est2.k_fc_noise_correction == pytest.approx(est.k_fc_noise_correction, rel=1e-9)


def test_stop_and_rollback_limits():
    s = TrackSettings(rms_limit_rad=0.25, rollback_ratio=2.0, rollback_min_rms_rad=1e-3)
    # rms exactly at the limit: not above it, no stop
    assert Tracker(k_fc=0.12, k_v=0.0, k_a=0.006, settings=s).after_task(_est(k_fc=0.121, rms=0.25)).action == "update"
    assert Tracker(k_fc=0.12, k_v=0.0, k_a=0.006, settings=s).after_task(
        _est(k_fc=0.121, rms=math.nextafter(0.25, 1.0))).action == "stop"
    # the error grew 3x after a +20 % update but stays under rollback_min_rms_rad: no rollback
    tr = Tracker(k_fc=0.10, k_v=0.0, k_a=0.006, settings=s)
    tr.after_task(_est(k_fc=0.12, rms=2e-4))
    assert tr.after_task(_est(k_fc=0.12, rms=6e-4)).action == "update"
    tr = Tracker(k_fc=0.10, k_v=0.0, k_a=0.006, settings=s)
    tr.after_task(_est(k_fc=0.12, rms=4e-4))
    assert tr.after_task(_est(k_fc=0.12, rms=1.2e-3)).action == "rollback"


def test_curvature_scatter_needs_scatter_min_plus_one_and_trend_keep_and_slow_down():
    from fftune.analysis.track import SCATTER_MIN, curvature_scatter
    assert curvature_scatter(list(np.arange(SCATTER_MIN) * 0.1)) is None
    assert curvature_scatter(list(np.arange(SCATTER_MIN + 1) * 0.1)) == pytest.approx(0.0, abs=1e-15)
    # a trend seen before continues while |m| > 2 s (3 s to start one)
    x = list(0.25 * np.arange(10.0))                  # changes 0.25: no curvature, s the floor
    assert drift_trend(x, scatter_floor=0.1, active=False) == 0.0          # 0.25 < 3 x 0.1
    assert drift_trend(x, scatter_floor=0.1, active=True) == pytest.approx(0.25)
    assert drift_trend(x, scatter_floor=0.13, active=True) == 0.0          # 0.25 < 2 x 0.13
    # the last change falls short of the ones before by more than 2 sqrt(3) s: the last
    # change times its ratio to their mean; by less (but more than 2 sqrt(2) s): the mean
    # by less: the smaller of the mean and the last change (issue 32's third pass); a last
    # change above the mean: the mean
    s = 0.1
    for drop, slowed in ((2 * math.sqrt(3) * s * 1.05, True), (2 * math.sqrt(3) * s * 0.95, False),
                         (-0.1, False)):
        d = [2.0, 2.0, 2.0 - drop]
        x = list(2.0 * np.arange(7.0)) + list(12.0 + np.cumsum(d))
        m = float(np.mean(d))
        expected = d[-1] * min(1.0, d[-1] / 2.0) if slowed else min(m, d[-1])
        assert drift_trend(x, scatter_floor=s) == pytest.approx(expected, rel=1e-12)


def test_parse_refuses_a_length_that_is_not_whole_blocks_of_float32_sums():
    from fftune.analysis.errors import FftuneError
    from fftune.analysis.track import parse_task_stats
    import struct
    head = struct.pack("<II", 2, 100)
    design = head + np.arange(9, dtype="<f4").tobytes()
    data = head + np.arange(6, dtype="<f4").tobytes()
    assert parse_task_stats(design, data).repetitions == 2
    with pytest.raises(FftuneError, match="not an 8-byte header"):
        parse_task_stats(head + bytes(9 * 3), data)        # 27 bytes: a multiple of 9, not of 36


def test_held_k_v_viscous_part_is_the_held_fits_k_fc_per_k_v_times_the_unresolved_change():
    from fftune.analysis.track import SYS_FLOOR_REL, VISC_SEEN_FRACTION, viscous_unresolved
    st, raw, _ = _stats_from_raw(1, 3001, 6, [0.142, 0.097, 0.011, 0.0052], [0.02, 0.05, 0.01, 0.03, 0.02, 0.04],
                                 seed=9)
    Phi = raw[0][0]
    u = raw[0][1]
    X, v = Phi[:, [0, 1, 3]], Phi[:, 2]
    # the held fit's K_fc per V s/rad of the held K_v: -0.5 (e_p + e_n) (X^T X)^-1 X^T v
    g = -0.5 * float(np.linalg.solve(X.T @ X, X.T @ v)[:2].sum())
    k_v_free = float(np.linalg.lstsq(Phi, u, rcond=None)[0][2])
    kvf = [0.020, 0.016, 0.012, 0.011, 0.0108, 0.0112, 0.0105, 0.0111, 0.0123]
    kfc = [0.11, 0.12, 0.125, 0.118, 0.121, 0.119, 0.12, 0.10, 0.13]      # not settled: no detection
    base = dict(k_fc_sigma=1e-3, k_v=0.011, k_v_sigma=0.0, k_a=0.0052, k_a_sigma=1e-4, offset=0.0,
                offset_sigma=0.0, rms_error=1e-3, rms_residual=0.02, condition=1.0, k_v_identified=False,
                samples=3001)
    recent = [TaskEstimate(k_fc=f, k_v_free=kv, **base) for f, kv in zip(kfc, kvf)]
    hold = 0.0110
    est = estimate_task(st, k_v_hold=hold, hold_k_v=True, recent=recent, kv_unique_min=0.0)
    assert not est.k_v_identified and est.k_v_shift == 0.0
    assert est.k_v_free == pytest.approx(k_v_free, rel=1e-6)
    # K_fc of the held fit: u - hold v on p, n, a
    theta = np.linalg.lstsq(X, u - hold * v, rcond=None)[0]
    assert est.k_fc == pytest.approx(0.5 * (theta[0] + theta[1]), rel=1e-6)
    unresolved = viscous_unresolved(kvf + [k_v_free], [True] * 10)
    assert unresolved > 0
    part = abs(g * unresolved) / VISC_SEEN_FRACTION
    assert est.k_fc_sigma_viscous == pytest.approx(part, rel=1e-6)
    assert est.k_fc_sigma_sys == pytest.approx(math.hypot(SYS_FLOOR_REL * est.k_fc, part), rel=1e-6)
    # the derivative by a finite step of the held K_v (the same fit): g
    theta2 = np.linalg.lstsq(X, u - (hold + 1e-3) * v, rcond=None)[0]
    assert (0.5 * (theta2[0] + theta2[1]) - 0.5 * (theta[0] + theta[1])) / 1e-3 == pytest.approx(g, rel=1e-6)
