"""Pins of track's documented defaults and thresholds (issue 33's complete mutation run of
analysis/track.py, docs/testing.md): each number docs/track.md states (the 2x rollback,
K_a learnt while its sigma is within 50 % of it, a viscous change beyond 4 times the
baseline's scatter and 25 % of K_v, the noise bias's 1 % calibration point) is checked on
both sides of its threshold with the library's defaults, so that a changed default fails."""
import math

import numpy as np
import pytest

from fftune.analysis.track import (MODEL_MIN, NOTE_MODEL_ERROR, SYS_FLOOR_REL, VISC_BASELINE_FROM,
                                   VISC_BASELINE_N, TaskEstimate, TaskStats, Tracker, estimate_task,
                                   noise_bias_rel, viscous_shift)


def _est(k_fc=0.12, sigma=1e-3, k_a=0.0061, k_a_sigma=1e-4, rms=0.004):
    return TaskEstimate(k_fc=k_fc, k_fc_sigma=sigma, k_v=0.0, k_v_sigma=0.0, k_a=k_a, k_a_sigma=k_a_sigma,
                        offset=0.0, offset_sigma=0.0, rms_error=rms, rms_residual=0.0, condition=1.0,
                        k_v_identified=False, samples=3000)


@pytest.mark.parametrize("growth, action", [(1.9, "update"), (2.1, "rollback"), (2.5, "rollback")])
def test_default_rollback_is_an_error_grown_more_than_twice(growth, action):
    # docs/track.md: a tracking error rms above rollback_ratio (2x) the one before the update
    # undoes it
    tr = Tracker(k_fc=0.10, k_v=0.0, k_a=0.006)
    tr.after_task(_est(k_fc=0.12, rms=2e-3))               # a +20 % update (default step 25 %)
    d = tr.after_task(_est(k_fc=0.12, rms=growth * 2e-3))
    assert d.action == action
    assert d.k_fc == pytest.approx(0.10 if action == "rollback" else 0.12)


@pytest.mark.parametrize("ratio, learnt", [(0.45, True), (0.55, False), (0.8, False)])
def test_default_k_a_is_learnt_while_held_only_within_half_its_value(ratio, learnt):
    # K_fc held (its sigma 50 % of it, above the default 20 %): K_a is still learnt when its
    # own sigma is within ka_max_sigma_rel = 50 % of it (docs/track.md)
    d = Tracker(k_fc=0.12, k_v=0.0, k_a=0.0).after_task(
        _est(k_fc=0.12, sigma=0.06, k_a=0.008, k_a_sigma=ratio * 0.008))
    assert d.action == "hold"
    assert d.k_a == (pytest.approx(0.008) if learnt else 0.0)


def _shift_series(base, last):
    early = [0.03, 0.02, 0.018, 0.016]
    assert len(early) == VISC_BASELINE_FROM and len(base) == VISC_BASELINE_N
    return early + list(base) + list(last)


def test_viscous_change_needs_four_baseline_scatters():
    # a baseline whose changes scatter: its robust scatter s (MAD of the differences over
    # sqrt 2, as documented), computed here; K_v held small so that 25 % of it is not the
    # threshold; two tasks 3.5 s above the baseline are no change, 4.5 s are one
    base = np.array([0.0150, 0.0170, 0.0145, 0.0172, 0.0152])
    d = np.diff(base)
    s = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
    med = float(np.median(base))
    k_v_hold = 0.2 * 3.0 * s          # 25 % of it is 0.15 s: not the binding threshold
    settled = [0.1, 0.1003, 0.0999]
    assert viscous_shift(_shift_series(base, [med + 3.5 * s, med + 3.6 * s]), k_v_hold, settled) == (0.0, False)
    shift, seen = viscous_shift(_shift_series(base, [med + 4.5 * s, med + 4.6 * s]), k_v_hold, settled)
    assert seen and shift == pytest.approx(4.55 * s)


def test_viscous_change_needs_a_quarter_of_the_held_k_v():
    # a quiet baseline (scatter far below): the threshold is 25 % of the held K_v
    base = [0.0150, 0.01501, 0.01500, 0.01502, 0.01501]
    med = float(np.median(base))
    settled = [0.1, 0.1003, 0.0999]
    k_v_hold = 0.020
    assert viscous_shift(_shift_series(base, [med + 0.20 * k_v_hold, med + 0.22 * k_v_hold]),
                         k_v_hold, settled) == (0.0, False)
    shift, seen = viscous_shift(_shift_series(base, [med - 0.30 * k_v_hold, med - 0.28 * k_v_hold]),
                                k_v_hold, settled)
    assert seen and shift == pytest.approx(-0.29 * k_v_hold)


def test_noise_bias_is_one_percent_at_its_calibration_point():
    # docs/track.md and the module's comment: 1 % at 1e-2 rad of sensor noise on
    # plant_twomass (K_fc 0.1157 V, its PD's noise gain 23.75 V/rad): r = 2.0527
    r = 23.75 * 1e-2 / 0.1157
    assert noise_bias_rel(r) == pytest.approx(0.01, rel=1e-9)
    assert noise_bias_rel(2 * r) == pytest.approx(0.04, rel=1e-9)     # r^2


def test_an_estimate_from_elsewhere_carries_no_sigma_part_or_correction():
    # TaskEstimate built with the required fields only (a user's own estimator): every
    # part of the systematic sigma and the noise correction are 0, not a made-up value
    e = _est()
    assert (e.k_fc_sigma_stat, e.k_fc_sigma_sys, e.k_fc_noise_correction, e.k_fc_sigma_viscous,
            e.k_fc_sigma_model, e.k_fc_sigma_split, e.k_v_shift) == (0.0,) * 7
    assert e.notes == ()
    assert all(math.isnan(x) for x in (e.k_v_free, e.sensor_noise_rad, e.k_fc_applied,
                                       e.k_fc_instrument_gap, e.k_v_trusted))


def test_default_steps_of_k_v_and_k_a_per_update():
    # the defaults: K_v by at most kv_max_step = 5 mV s/rad, K_a by at most 50 % of it
    tr = Tracker(k_fc=0.12, k_v=0.010, k_a=0.004)
    est = _est(k_fc=0.121, k_a=0.0130)
    est.k_v, est.k_v_identified = 0.050, True
    d = tr.after_task(est)
    assert d.action == "update"
    assert d.k_v == pytest.approx(0.015) and d.k_a == pytest.approx(0.006)


def test_default_third_rollback_in_a_row_stops():
    # docs/track.md: max_rollbacks (3) in a row stop; an update between them that grows the
    # error again does not reset the count
    tr = Tracker(k_fc=0.10, k_v=0.0, k_a=0.006)
    actions = []
    for _ in range(3):
        actions.append(tr.after_task(_est(k_fc=0.12, rms=2e-3)).action)
        actions.append(tr.after_task(_est(k_fc=0.12, rms=5e-3)).action)
    assert actions == ["update", "rollback", "update", "rollback", "update", "stop"]


def _exact_task(fc=0.11):
    """An asymmetric back-and-forth task whose input the model explains exactly (its own
    instrument gap 0): K_fc 0.11 V."""
    fs = 1000.0
    t = np.arange(0, 0.4, 1.0 / fs)
    v_move = 4.0 * np.minimum(1.0, np.minimum(t / 0.1, (0.4 - t) / 0.1))
    dwell = np.zeros(int(0.15 * fs))
    v = np.concatenate([v_move, dwell, -0.8 * v_move, dwell[:-20]])
    a = np.gradient(v) * fs
    s = np.sign(np.round(v, 9))
    p, n = np.maximum(s, 0.0), np.minimum(s, 0.0)
    u = (fc + 0.02) * p + (fc - 0.02) * n + 0.003 * v + 0.0071 * a
    edges = [(b * v.size) // 8 for b in range(9)]
    design, data = [], []
    for b in range(8):
        sl = slice(edges[b], edges[b + 1])
        P, N, V, A, U = p[sl], n[sl], v[sl], a[sl], u[sl]
        design.append([P @ P, N @ N, P @ V, P @ A, N @ V, N @ A, V @ V, V @ A, A @ A])
        data.append([P @ U, N @ U, V @ U, A @ U, 0.0, U @ U])
    return TaskStats(repetitions=1, samples=v.size, design=np.array(design), data=np.array(data))


@pytest.mark.parametrize("part_over_floor, named", [(0.8, False), (1.5, True)])
def test_model_error_is_named_beyond_the_floor(part_over_floor, named):
    # the model-error part is half the median gap of the tasks at the fixed point; the row
    # names it beyond MODEL_NOTE_REL (1) times the systematic floor (0.4 % of K_fc)
    stats = _exact_task()
    plain = estimate_task(stats, k_v_hold=0.003, hold_k_v=True)
    assert abs(plain.k_fc_instrument_gap) < 1e-9
    gap = 2.0 * part_over_floor * SYS_FLOOR_REL * abs(plain.k_fc)
    recent = [TaskEstimate(**{**plain.__dict__, "k_fc_instrument_gap": gap})] * MODEL_MIN
    est = estimate_task(stats, k_v_hold=0.003, hold_k_v=True, recent=recent)
    assert est.k_fc_sigma_model == pytest.approx(0.5 * gap, rel=1e-9)
    assert (NOTE_MODEL_ERROR in est.notes) is named


def test_default_k_fc_step_has_an_absolute_floor_of_five_millivolts():
    # max(max_step_rel K_fc, max_step_abs) = max(25 % x 10 mV, 5 mV) = 5 mV from K_fc 10 mV
    d = Tracker(k_fc=0.010, k_v=0.0, k_a=0.006).after_task(_est(k_fc=0.030, sigma=1e-4))
    assert d.action == "update" and d.k_fc == pytest.approx(0.015)
    # and 25 % where that is the larger: 0.12 -> 0.15
    d = Tracker(k_fc=0.12, k_v=0.0, k_a=0.006).after_task(_est(k_fc=0.30, sigma=1e-3))
    assert d.k_fc == pytest.approx(0.15)


def _stats_of(columns, u):
    """TaskStats (one block, one repetition) of regressor columns p, n, v, a and input u."""
    P, N, V, A = columns
    design = np.array([[P @ P, N @ N, P @ V, P @ A, N @ V, N @ A, V @ V, V @ A, A @ A]])
    data = np.array([[P @ u, N @ u, V @ u, A @ u, 0.0, u @ u]])
    return TaskStats(repetitions=1, samples=P.size, design=design, data=data)


def _sign_regressors(m, fs=1000.0):
    """p, n, a of a two-tone reference of m samples (the sign instruments and the
    acceleration; no physical task, only regressors with every sign and a level of each)."""
    t = np.arange(m) / fs
    base = np.sin(2 * np.pi * 1.3 * t) + 0.3 * np.sin(2 * np.pi * 3.1 * t + 0.4)
    s = np.sign(base)
    return np.maximum(s, 0), np.minimum(s, 0), np.gradient(base, 1.0 / fs)


@pytest.mark.parametrize("unique, identified", [(0.01, False), (0.04, True)])
def test_default_k_v_needs_two_percent_of_v_unexplained(unique, identified):
    # docs/track.md: K_v is estimated when at least 2 % of v_r's energy is not explained by
    # p, n, a_r; v here is a combination of them plus an orthogonal part of the given share
    rng = np.random.default_rng(7)
    m = 4000
    p, n, a = _sign_regressors(m)
    X = np.column_stack([p, n, a])
    v0 = 1.7 * p + 0.9 * n + 0.002 * a
    z = rng.standard_normal(m)
    z -= X @ np.linalg.lstsq(X, z, rcond=None)[0]          # orthogonal to p, n, a
    scale = math.sqrt(unique / (1 - unique) * (v0 @ v0) / (z @ z))
    v = v0 + scale * z
    got = 1 - np.sum((v - X @ np.linalg.lstsq(X, v, rcond=None)[0]) ** 2) / (v @ v)
    assert 1 - got == pytest.approx(unique, rel=1e-6)       # the share, by its definition
    u = 0.12 * p + 0.10 * n + 0.004 * v + 0.006 * a
    est = estimate_task(_stats_of((p, n, v, a), u))
    assert est.k_v_identified is identified


def test_viscous_unresolved_takes_the_larger_of_the_last_eight_and_four():
    # docs/track.md: the mean shift of the free coefficient over the last 8 tasks (and over
    # the last 4, the larger) from its baseline, with its standard error in quadrature;
    # reference computed here with the documented windows
    from fftune.analysis.track import viscous_unresolved
    early = [0.03, 0.02, 0.018, 0.016]
    base = [0.0150, 0.0153, 0.0149, 0.0152, 0.0151]
    for tail in ([0.0162, 0.0161, 0.0163, 0.0160, 0.0150, 0.0151, 0.0149, 0.0150, 0.0152],   # 8 wins
                 [0.0150, 0.0151, 0.0150, 0.0149, 0.0152, 0.0171, 0.0170, 0.0173, 0.0169]):  # 4 wins
        x = np.array(early + base + tail)
        d = np.diff(x[4:])
        scat = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
        med = np.median(base)
        ref = {k: math.hypot(np.mean(x[-k:]) - med, scat * math.sqrt(1 / k + 1 / 5)) for k in (8, 4)}
        assert viscous_unresolved(list(x)) == pytest.approx(max(ref.values()), rel=1e-12)
    # (the two cases differ in which window is the larger)


def test_model_error_part_needs_three_gaps():
    from fftune.analysis.track import model_error_sigma
    assert model_error_sigma([0.004, 0.010]) == 0.0
    assert model_error_sigma([0.004, 0.010, -0.002]) == pytest.approx(0.002)
    assert model_error_sigma([np.nan, 0.004, 0.010, np.nan]) == 0.0


def test_default_rollback_needs_an_error_above_one_milliradian():
    # an error grown 3x after a +20 % update but under rollback_min_rms_rad (1 mrad, the
    # default) is the plant's own variation, no rollback; above it, a rollback
    tr = Tracker(k_fc=0.10, k_v=0.0, k_a=0.006)
    tr.after_task(_est(k_fc=0.12, rms=3e-4))
    assert tr.after_task(_est(k_fc=0.12, rms=9e-4)).action == "update"
    tr = Tracker(k_fc=0.10, k_v=0.0, k_a=0.006)
    tr.after_task(_est(k_fc=0.12, rms=4e-4))
    assert tr.after_task(_est(k_fc=0.12, rms=1.2e-3)).action == "rollback"


def test_viscous_change_needs_at_least_the_absolute_floor():
    # K_v held at 0 and a quiet baseline: the threshold is VISC_SHIFT_MIN_ABS, 0.2 mV s/rad
    base = [0.0150, 0.01500, 0.01501, 0.01500, 0.01500]
    med = float(np.median(base))
    settled = [0.1, 0.1003, 0.0999]
    assert viscous_shift(_shift_series(base, [med + 1.5e-4, med + 1.6e-4]), 0.0, settled) == (0.0, False)
    shift, seen = viscous_shift(_shift_series(base, [med + 2.5e-4, med + 2.6e-4]), 0.0, settled)
    assert seen and shift == pytest.approx(2.55e-4)


def test_a_singular_split_with_k_v_allowed_is_held_or_named_not_a_linalg_error():
    # kv_unique_min = 0 (a caller's setting) lets K_v be tried on a task whose velocity
    # regressor is empty (v_r 0 in every sample): the four-gain solve is singular. With the
    # run's history the split is held (K_v at its trusted value, K_fc from the rest); without
    # it the task is named collinear. Never numpy's LinAlgError.
    from fftune.analysis.track import NOTE_KV_SPLIT_HELD, NotIdentifiable
    m = 3000
    p, n, a = _sign_regressors(m)
    u = 0.12 * p + 0.10 * n + 0.006 * a
    stats = _stats_of((p, n, np.zeros(m), a), u)
    est = estimate_task(stats, kv_unique_min=0.0, recent=[])
    assert est.k_fc == pytest.approx(0.11, rel=1e-9) and NOTE_KV_SPLIT_HELD in est.notes
    assert not est.k_v_identified and math.isnan(est.k_v_free)
    with pytest.raises(NotIdentifiable) as info:
        estimate_task(stats, kv_unique_min=0.0)
    assert info.value.cause == "collinear"
