"""Pins of numbers a user trusts in tune and track (issue 33): each test uses unequal,
asymmetric inputs and an expected value computed independently of the code under test
(analytic, or a slow reference here), so that a wrong factor, divisor, sign or swapped
argument fails it."""
import math

import numpy as np
import pytest

from fftune.analysis.track import (TaskEstimate, TaskStats, Tracker, TrackSettings, estimate_task,
                                   normal_matrix)
from fftune.analysis.tuning import KfcSearch, amplitude_combination, viscous_from_harmonics

FS = 2560.0


# ---- track: the statistical sigma with more than one repetition per block ---------------------

def _one_repetition(theta, rng, samples, noise, blocks=8):
    t = np.arange(samples) / FS
    v = 3.0 * np.sin(2 * np.pi * t / t[-1]) + 0.5 * np.sin(6 * np.pi * t / t[-1])
    a = np.gradient(v, 1 / FS)
    s = np.sign(v)
    p, n = np.maximum(s, 0), np.minimum(s, 0)
    u = theta[0] * p + theta[1] * n + theta[2] * v + theta[3] * a + noise * rng.standard_normal(samples)
    e = 1e-3 * rng.standard_normal(samples)
    edges = [(b * samples) // blocks for b in range(blocks + 1)]
    design, data = [], []
    for b in range(blocks):
        sl = slice(edges[b], edges[b + 1])
        P, N, V, A, U, E = p[sl], n[sl], v[sl], a[sl], u[sl], e[sl]
        design.append([P @ P, N @ N, P @ V, P @ A, N @ V, N @ A, V @ V, V @ A, A @ A])
        data.append([P @ U, N @ U, V @ U, A @ U, E @ E, U @ U])
    return np.array(design), np.array(data)


@pytest.mark.parametrize("reps", [2, 3])
def test_track_statistical_sigma_with_several_repetitions_is_the_analytic_standard_error(reps):
    # R repetitions summed per block (what the drive does with record_repetitions R): the
    # standard error of K_fc is noise sqrt(w^T A^-1 w) with A the summed normal matrix; a
    # sigma computed with the samples of one repetition (sqrt(R) off) must fail
    theta, noise, samples = [0.13, 0.10, 0.003, 0.006], 0.037, 2500
    ratios = []
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        parts = [_one_repetition(theta, rng, samples, noise) for _ in range(reps)]
        st = TaskStats(reps, samples, sum(p[0] for p in parts), sum(p[1] for p in parts))
        A = sum(normal_matrix(d) for d in st.design)
        w = np.array([0.5, 0.5, 0.0, 0.0])
        analytic = noise * math.sqrt(w @ np.linalg.solve(A, w))
        ratios.append(estimate_task(st).k_fc_sigma_stat / analytic)
    assert 0.93 < np.mean(ratios) < 1.07, ratios


# ---- track: rollbacks separated by normal updates do not add up to a stop -------------------

def _est(k_fc, rms):
    return TaskEstimate(k_fc=k_fc, k_fc_sigma=1e-3, k_v=0.0, k_v_sigma=0.0, k_a=0.0061, k_a_sigma=1e-4,
                        offset=0.0, offset_sigma=0.0, rms_error=rms, rms_residual=0.0, condition=1.0,
                        k_v_identified=False, samples=3000)


def test_track_rollback_count_restarts_after_normal_updates():
    tr = Tracker(k_fc=0.100, k_v=0.0, k_a=0.0061, settings=TrackSettings(max_rollbacks=2, rollback_ratio=2.0))
    assert tr.after_task(_est(0.120, 0.0040)).action == "update"              # 0.100 -> 0.120
    d = tr.after_task(_est(0.121, 0.0093))                                      # error x2.3
    assert d.action == "rollback" and d.k_fc == pytest.approx(0.100)
    assert tr.after_task(_est(0.118, 0.0041)).action == "update"                # 0.100 -> 0.118
    d = tr.after_task(_est(0.133, 0.0039))                                      # a normal update
    assert d.action == "update" and d.k_fc == pytest.approx(0.133)
    d = tr.after_task(_est(0.150, 0.0087))                                      # error x2.2 after +12.7 %
    assert d.action == "rollback" and d.k_fc == pytest.approx(0.118)            # one rollback, not two
    d = tr.after_task(_est(0.131, 0.0042))
    assert d.action == "update" and d.k_fc == pytest.approx(0.131)             # the tracker goes on


# ---- tune: the flatness part sigma_fit --------------------------------------------------------

FC, GAIN = 0.1157, 2.0
BEND, CURVE = 3.0, 0.8


def _g(k_fc):
    """The signed objective's shape: bends under-compensated (x (1 + BEND x / FC)), mildly
    curved over-compensated (x (1 - CURVE x / FC)), x = FC - K."""
    x = FC - k_fc
    return x * (1 + BEND * x / FC) if x > 0 else x * (1 - CURVE * x / FC)


def _bent(k_fc):
    """Closed-loop HOSIDFs whose odd harmonics are proportional to _g(K) at fixed phases;
    |H_1| constant, so the signed objective is c _g(K) exactly."""
    h = np.zeros(7, dtype=complex)
    h[0] = GAIN
    for k in (3, 5, 7):
        h[k - 1] = (-1) ** ((k - 1) // 2) * 4 * _g(k_fc) / (k * np.pi)
    rng = np.random.default_rng(int(1e6 * k_fc) % 1000)
    return h[None, :] + 1e-9 * (rng.standard_normal((4, 7)) + 1j * rng.standard_normal((4, 7)))


def test_tune_flatness_part_is_half_the_distance_between_the_two_root_models():
    res = KfcSearch(0.0, 0.3, max_experiments=10, rtol=0.02).run(_bent)
    assert res.converged and res.regime == "signed root"
    ks = sorted(p.k_fc for p in res.points)
    under = [k for k in ks if _g(k) > 0]
    over = [k for k in ks if _g(k) < 0]
    k1, k2 = under[-1], over[0]
    # the line across the sign change, and the secant through the two over-compensated
    # points nearest the root (s is c _g: the roots do not depend on c)
    linear = k1 + (k2 - k1) * _g(k1) / (_g(k1) - _g(k2))
    o1, o2 = over[0], over[1]
    secant = o1 - _g(o1) * (o2 - o1) / (_g(o2) - _g(o1))
    assert k1 < secant < k2
    assert res.k_fc == pytest.approx(secant, rel=1e-6)
    expected = abs(secant - linear) / 2
    assert expected > 1e-3 * FC
    assert res.sigma_fit == pytest.approx(expected, rel=1e-4)


# ---- tune: the 1/A amplitude combination when the second amplitude is the smaller -------------

def test_amplitude_combination_with_the_smaller_second_amplitude():
    k1, s1, a1 = 0.1200, 0.0011, 1.6      # the search's amplitude (the larger one)
    k2, s2, a2 = 0.1290, 0.0007, 0.5
    k, noise, part, how = amplitude_combination(k1, s1, a1, k2, s2, a2)
    # the straight line through (1/a1, k1) and (1/a2, k2), at 1/A = 0
    slope = (k2 - k1) / (1 / a2 - 1 / a1)
    k_inf = k1 - slope / a1
    assert k == pytest.approx(k_inf, rel=1e-12)
    # the part is the step from the LARGER amplitude's value (k1 here), not from k2
    assert part == pytest.approx(abs(k_inf - k1), rel=1e-12)
    # noise: d k_inf / d k1 = 1 + (1/a1) / (1/a2 - 1/a1), d k_inf / d k2 = -(1/a1) / (1/a2 - 1/a1)
    g1 = 1 + (1 / a1) / (1 / a2 - 1 / a1)
    g2 = -(1 / a1) / (1 / a2 - 1 / a1)
    assert noise == pytest.approx(math.hypot(g1 * s1, g2 * s2), rel=1e-12)
    assert "extrapolated" in how


# ---- tune: the viscous estimate from harmonics with several sine cycles per period -----------

@pytest.mark.parametrize("c", [3, 5])
def test_viscous_from_harmonics_with_several_cycles_per_period(c):
    n = 8192
    w = 2 * np.pi * c * FS / n
    t = np.arange(n) / FS
    y = 0.4 * np.sin(w * t + 0.2) + 0.005 * np.sin(3 * w * t - 0.7)
    yd = 0.4 * w * np.cos(w * t + 0.2) + 0.015 * w * np.cos(3 * w * t - 0.7)
    ydd = -0.4 * w ** 2 * np.sin(w * t + 0.2) - 0.045 * w ** 2 * np.sin(3 * w * t - 0.7)
    J, b, fc = 1.7e-3, 0.040, 0.1157
    u = J * ydd + b * yd + fc * np.sign(0.4 * w * np.cos(w * t + 0.2))
    lines = c * np.arange(1, 8)
    U, Y = np.fft.fft(u)[lines], np.fft.fft(y)[lines]
    kv, fc_fit = viscous_from_harmonics(U, Y, w, n, c)
    assert kv == pytest.approx(b, rel=2e-3) and fc_fit == pytest.approx(fc, rel=2e-3)
