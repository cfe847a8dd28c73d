"""K_fc root search: the Illinois step on one-sided convex objectives (issue 16).

The other tests use objectives that are near-linear or odd-symmetric about the root, on
which plain regula falsi is already fast, so halving the wrong end (or not halving) went
unnoticed. On a convex objective one bracket end stays fixed for many steps: only the
Illinois halving of that end's value keeps the convergence superlinear.
"""
import numpy as np
import pytest

from fftune.analysis.tuning import SignedRootSearch

# s > 0 at K = 0 and s < 0 at K = 1 for both, as for an under-/over-compensated drive
CONVEX_OBJECTIVES = {
    # root 0.37, convex: regula falsi keeps the upper end (a = the moving end)
    "root-low-convex": (0.37, lambda k: np.exp(3 * (0.37 - k)) - 1),
    # root 0.63, concave: the lower end is kept (b = the moving end)
    "root-high-concave": (0.63, lambda k: 1 - np.exp(3 * (k - 0.63))),
}


@pytest.mark.parametrize("name", list(CONVEX_OBJECTIVES))
def test_illinois_search_needs_few_evaluations_on_one_sided_objective(name):
    root, objective = CONVEX_OBJECTIVES[name]
    calls = []

    def counted(k):
        calls.append(k)
        return objective(k)

    res = SignedRootSearch(0.0, 1.0, xtol=1e-6, max_evaluations=60).run(counted)
    assert res.converged
    assert res.k_fc == pytest.approx(root, abs=1e-5)
    assert res.n_evaluations == len(calls)
    # Illinois: 11 evaluations here; halving the wrong end takes 39, no halving 20
    assert res.n_evaluations <= 14, res.history


# --- the rest of what mutation testing found untested (docs/testing.md) ------------------

import re  # noqa: E402

from scipy.optimize import minimize_scalar  # noqa: E402

from fftune.analysis.errors import InputError  # noqa: E402
from fftune.analysis.tuning import (RatioMinimizer, odd_ratio, reference_phases,  # noqa: E402
                                    signed_odd_ratio)


def _rotated_hosidf(scale, phases, k_max=7):
    """H_1 = 2 and H_k = scale / k exp(j phi_k) for odd k >= 3 (arbitrary phases)."""
    h = np.zeros(k_max, complex)
    h[0] = 2.0
    for k, phi in zip((3, 5, 7), phases):
        h[k - 1] = scale / k * np.exp(1j * phi)
    return h


def test_objectives_are_vectorised_and_use_the_reference_phase():
    phases = np.array([0.7, -1.9, 2.6])                 # not 0 or pi: a rotation matters
    stack = np.stack([_rotated_hosidf(s, phases) for s in (0.3, -0.1, 0.05)])   # (3, 7)
    np.testing.assert_allclose(reference_phases(stack[0]), phases, atol=1e-15)
    expected = np.array([np.mean([s / 3, s / 5, s / 7]) / 2 for s in (0.3, -0.1, 0.05)])
    np.testing.assert_allclose(signed_odd_ratio(stack, phases), expected, rtol=1e-12)
    per_row = [odd_ratio(h) for h in stack]
    np.testing.assert_allclose(odd_ratio(stack), per_row, rtol=1e-15)
    with pytest.raises(InputError, match=re.escape("H holds only 7 harmonics")):
        odd_ratio(stack, harmonics=(3, 9))


def test_search_argument_checks_and_defaults():
    for bad in (0.0, -1e-3):
        with pytest.raises(InputError, match="xtol must be > 0"):
            SignedRootSearch(0.0, 1.0, xtol=bad)
    with pytest.raises(InputError, match="max_evaluations must be >= 3"):
        RatioMinimizer(0.0, 1.0, max_evaluations=2)
    assert RatioMinimizer(0.0, 1.0, max_evaluations=3).max_evaluations == 3
    assert SignedRootSearch(0.0, 2.0).xtol == pytest.approx(2e-4)
    assert RatioMinimizer(0.0, 2.0).xtol == pytest.approx(2e-3)
    # default caps: 20 experiments for the minimiser, 12 for the root search
    capped = RatioMinimizer(0.0, 1.0, xtol=1e-12).run(lambda k: abs(k - 0.3137) ** 0.3)
    assert capped.n_evaluations == 20 and not capped.converged
    slow = SignedRootSearch(0.0, 1.0, xtol=1e-12).run(lambda k: np.cbrt(0.3 - k))
    assert slow.n_evaluations <= 12 and (slow.converged or slow.n_evaluations == 12)


def test_tell_accepts_only_the_value_asked():
    search = SignedRootSearch(100.0, 300.0)
    k = search.ask()
    assert k == 100.0
    search.tell(k + 5e-11, 1.0)                         # within 1e-12 |k|: the same point
    search = SignedRootSearch(1e-3, 1.0)
    search.tell(1e-3 + 5e-13, 1.0)                      # within 1e-12 absolute near 0
    search = SignedRootSearch(0.5, 1.0)
    with pytest.raises(InputError, match="asked"):
        search.tell(0.5 * (1 + 1e-6), 1.0)
    done = SignedRootSearch(0.0, 1.0)
    assert done.run(lambda k: 0.4 - k).converged and done.done
    with pytest.raises(InputError, match="finished"):
        done.ask()
    with pytest.raises(InputError, match="finished"):
        done.tell(0.4, 0.0)


def test_result_before_and_during_the_search():
    search = RatioMinimizer(0.2, 0.6)
    res = search.result                                   # nothing measured yet
    assert res.k_fc == pytest.approx(0.4) and res.uncertainty == pytest.approx(0.2)
    assert not res.converged and res.reason == "running" and res.n_evaluations == 0
    search = SignedRootSearch(0.2, 0.6)
    res = search.result
    assert (res.k_fc, res.uncertainty, res.n_evaluations) == (pytest.approx(0.4),
                                                              pytest.approx(0.2), 0)
    search.tell(search.ask(), 0.1)
    assert search.result.uncertainty == pytest.approx(0.2)           # no bracket yet
    search.tell(search.ask(), -0.5)
    res = search.result
    assert res.k_fc == 0.2 and not res.converged                     # the smaller |s| so far


def test_converging_on_the_last_allowed_evaluation_is_converged():
    res = SignedRootSearch(0.0, 1.0, max_evaluations=3).run(lambda k: 0.4 - k)
    assert res.converged and res.n_evaluations == 3 and res.k_fc == pytest.approx(0.4)


def test_ratio_minimizer_follows_brent_fmin_as_scipy():
    """The same algorithm as scipy's bounded minimize_scalar (Forsythe, Malcolm, Moler
    fmin) on r^2: the same experiments in the same order."""
    assert RatioMinimizer(0.0, 1.0).ask() == pytest.approx((3 - np.sqrt(5)) / 2, rel=1e-15)
    objectives = [lambda k: abs(k - 0.3) + 0.01, lambda k: np.sqrt(3 * (k - 0.1157) ** 2 + 0.02),
                  lambda k: np.exp(2 * (k - 0.6)) - 2 * (k - 0.6), lambda k: abs(k - 0.93) ** 0.7,
                  lambda k: max(abs(k - 0.3), 0.1)]                  # flat: equal values
    for objective in objectives:
        for xtol in (1e-3, 1e-5):
            ours = []
            res = RatioMinimizer(0.0, 1.0, xtol=xtol, max_evaluations=200).run(
                lambda k: (ours.append(k), objective(k))[1])
            ref = []
            minimize_scalar(lambda k: (ref.append(k), objective(k) ** 2)[1], bounds=(0.0, 1.0),
                            method="bounded", options={"xatol": xtol, "maxiter": 200})
            assert len(ours) == len(ref)
            np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-9)
            assert res.converged and res.k_fc == min(res.history, key=lambda kv: kv[1])[0]


def _illinois_reference(f, a, b, xtol, max_evaluations):
    """Textbook Illinois (Dowell and Jarratt 1971) with the documented stopping rules."""
    fa, fb = f(a), f(b)
    xs, side, c_prev = [a, b], 0, None
    while len(xs) < max_evaluations:
        c = (a * fb - b * fa) / (fb - fa)
        fc = f(c)
        xs.append(c)
        if fc == 0:
            break
        if np.sign(fc) == np.sign(fb):
            b, fb = c, fc
            if side == -1:
                fa /= 2
            side = -1
        else:
            a, fa = c, fc
            if side == +1:
                fb /= 2
            side = +1
        if abs(b - a) <= 2 * xtol or (c_prev is not None and abs(c - c_prev) <= xtol):
            break
        c_prev = c
    return xs


@pytest.mark.parametrize("objective", [
    lambda k: np.exp(3 * (0.37 - k)) - 1, lambda k: 1 - np.exp(3 * (k - 0.63)),
    lambda k: np.tanh(5 * (0.37 - k)) + 0.3 * (0.37 - k) ** 3, lambda k: 0.2 - k ** 3,
    lambda k: np.cbrt(0.55 - k)])
def test_signed_root_search_follows_textbook_illinois(objective):
    res = SignedRootSearch(0.0, 1.0, xtol=1e-7, max_evaluations=40).run(objective)
    ref = _illinois_reference(objective, 0.0, 1.0, 1e-7, 40)
    np.testing.assert_allclose([k for k, _ in res.history], ref, rtol=0, atol=1e-12)


def test_signed_root_search_uncertainty():
    # bracket [c, 1] after the third experiment: half of it is below the last step
    f = lambda k: np.tanh(3 * (0.8 - k))                               # noqa: E731
    res = SignedRootSearch(0.0, 1.0, max_evaluations=3).run(f)
    c = res.history[-1][0]
    assert f(c) > 0 and res.k_fc == c
    assert res.uncertainty == pytest.approx((1.0 - c) / 2, rel=1e-12)
    # bracket [0, c] with c near 1: the last step |c - 1| is the smaller one
    g = lambda k: np.exp(3 * (0.75 - k)) - 1                           # noqa: E731
    res = SignedRootSearch(0.0, 1.0, max_evaluations=3).run(g)
    c = res.history[-1][0]
    assert g(c) < 0 and res.uncertainty == pytest.approx(1.0 - c, rel=1e-12)
    # a root at an end of the bracket: exact, zero uncertainty
    for lo, hi in ((0.25, 1.0), (0.0, 0.25)):
        res = SignedRootSearch(lo, hi).run(lambda k: 0.25 - k)
        assert res.converged and res.k_fc == 0.25 and res.uncertainty == 0.0
        assert res.n_evaluations == (1 if lo == 0.25 else 2)


# --- the K_fc search's point statistics (docs/testing.md): first-order propagation checked
# --- against a numerical gradient, the per-period variances against numpy ------------------

from fftune.analysis.tuning import KfcSearch, odd_ratio, reference_phases, signed_odd_ratio  # noqa: E402


def _relay(k_fc, fc=0.3, amplitude=0.5, gain=1.0, k_max=7):
    h = np.zeros(k_max, dtype=complex)
    h[0] = gain + 4 * (fc - k_fc) / (np.pi * amplitude)
    for k in range(3, k_max + 1, 2):
        h[k - 1] = (-1) ** ((k - 1) // 2) * 4 * (fc - k_fc) / (k * np.pi * amplitude)
    return h * np.exp(0.3j)


def _delta_method_std(f, H, H_var, P, eps=1e-7):
    """sqrt(sum_j |grad_j f|^2 H_var_j / 2 / P): circular lines, numerical gradient."""
    var = 0.0
    for j in range(H.size):
        for unit in (1.0, 1j):
            dH = np.zeros(H.size, complex)
            dH[j] = unit * eps
            g = (f(H + dH) - f(H - dH)) / (2 * eps)
            var += g ** 2 * H_var[j] / 2
    return np.sqrt(var / P)


def test_moment_point_standard_errors_are_first_order_propagation():
    H = _relay(0.05)
    H_var = np.array([4e-6, 1e-7, 3e-6, 2e-6, 1e-6, 5e-7, 2e-7])
    P = 4
    search = KfcSearch(0.0, 1.0)
    k = search.ask()
    search.tell_moments(k, H, H_var, P)
    pt = search.points[k]
    assert pt.ratio == pytest.approx(odd_ratio(H))
    assert pt.ratio_std == pytest.approx(_delta_method_std(odd_ratio, H, H_var, P), rel=1e-5)
    phases = reference_phases(_relay(0.0))
    s, s_se = search._signed([pt], phases)
    assert s[0] == pytest.approx(signed_odd_ratio(H, phases))
    assert s_se[0] == pytest.approx(
        _delta_method_std(lambda h: signed_odd_ratio(h, phases), H, H_var, P), rel=1e-5)


def test_period_point_variances_and_a_motor_that_does_not_move():
    rng = np.random.default_rng(2)
    Hp = _relay(0.1) + 1e-3 * (rng.standard_normal((5, 7)) + 1j * rng.standard_normal((5, 7)))
    search = KfcSearch(0.0, 1.0)
    k = search.ask()
    search.tell(k, Hp)
    pt = search.points[k]
    np.testing.assert_allclose(pt.H_var, np.var(Hp.real, axis=0, ddof=1) + np.var(Hp.imag, axis=0, ddof=1))
    assert pt.ratio_std == pytest.approx(np.std(odd_ratio(Hp), ddof=1) / np.sqrt(5))
    phases = reference_phases(_relay(0.0))
    _, s_se = search._signed([pt], phases)
    assert s_se[0] == pytest.approx(np.std(signed_odd_ratio(Hp, phases), ddof=1) / np.sqrt(5))
    # a first harmonic that averages out over the periods: the motor does not move
    flip = _relay(0.1)[None, :] * np.array([1, -1, 1, -1 + 1e-5])[:, None]
    flip[:, 1:] = 1e-9
    k = search.ask()
    search.tell(k, flip)
    assert np.isinf(search.points[k].ratio)
    two = KfcSearch(0.0, 1.0)
    two.tell_moments(two.ask(), _relay(0.5), np.full(7, 1e-8), 2)      # P = 2 is enough
    still = KfcSearch(0.0, 1.0)
    k = still.ask()
    H = np.full(7, 1e-7 + 0j)
    still.tell_moments(k, H, np.zeros(7), 4)
    assert np.isinf(still.points[k].ratio)


def test_first_interior_point_is_the_secant_root_of_s():
    """Ends told (upper first, then lower): the third experiment is where the straight line
    through s(lower) > 0 > s(upper) crosses zero (not the midpoint)."""
    search = KfcSearch(0.1, 1.0)
    H = {}
    for _ in range(2):
        k = search.ask()
        H[k] = _relay(k)
        search.tell_moments(k, H[k], np.full(7, 1e-10), 4)
    phases = reference_phases(H[0.1] - H[1.0])
    s0, s1 = signed_odd_ratio(H[0.1], phases), signed_odd_ratio(H[1.0], phases)
    assert s0 > 0 > s1
    secant = 0.1 + 0.9 * s0 / (s0 - s1)
    assert search.ask() == pytest.approx(secant)
    assert abs(secant - 0.55) > 0.05


def test_smallest_ratio_at_the_drive_limit_fails_with_the_top_bracket():
    search = KfcSearch(0.0, 0.05, k_limit=0.12)
    while not search.done:
        k = search.ask()
        search.tell_moments(k, _relay(k), np.full(7, 1e-10), 4)
    res = search.result
    assert not res.converged and "drive's limit" in res.reason
    ks = sorted(p.k_fc for p in res.points)
    assert res.bracket == (ks[-2], ks[-1]) and ks[-1] == pytest.approx(0.12)


def test_both_ends_under_compensated_extend_to_the_extrapolated_zero():
    """s(lower) > s(upper) > 0: the third experiment is 1.15 x the zero of the line through
    both ends, kept within [1.25, 4] x upper and the drive's limit."""
    search = KfcSearch(0.05, 0.25, k_limit=2.0)
    H = {}
    for _ in range(2):
        k = search.ask()
        H[k] = _relay(k)
        search.tell_moments(k, H[k], np.full(7, 1e-10), 4)
    phases = reference_phases(H[0.05] - H[0.25])
    s0, s1 = signed_odd_ratio(H[0.05], phases), signed_odd_ratio(H[0.25], phases)
    assert s0 > s1 > 0
    root = 0.05 + 0.2 * s0 / (s0 - s1)
    expected = 1.15 * root
    assert 1.25 * 0.25 < expected < 4 * 0.25          # inside the clamps
    assert search.ask() == pytest.approx(expected) and search.extended_to == pytest.approx(expected)


def test_t_factor_and_empty_bracket():
    from scipy.stats import t as student_t

    from fftune.analysis.errors import InputError
    from fftune.analysis.tuning import SignedRootSearch, _t_factor
    assert _t_factor(10 ** 4) == pytest.approx(1.0, abs=1e-3)   # 2 sigma of a normal
    assert _t_factor(3) == pytest.approx(student_t.ppf(0.9772, 3) / 2)
    with pytest.raises(InputError):
        SignedRootSearch(1.0, 1.0)


def test_clean_search_converges_on_the_signed_root_and_says_so():
    """Noise-free relay: the signed-root regime, verified by s = 0 at the estimate (not by
    a bracketed sign change), K_fc* = Fc."""
    search = KfcSearch(0.0, 1.0, max_experiments=12)
    while not search.done:
        k = search.ask()
        search.tell_moments(k, _relay(k), np.full(7, 1e-12), 4)
    res = search.result
    assert res.converged and res.regime == "signed root", res.reason
    assert res.k_fc == pytest.approx(0.3, abs=1e-3)
    assert "has s = " in res.reason and "bracketed" not in res.reason


def test_ratio_minimiser_step_is_the_vertex_of_the_parabola_in_r_squared():
    """Odd phases that rotate with K_fc: the next experiment is the vertex of the parabola
    through r^2 at the smallest ratio and its two neighbours (numpy polyfit as reference)."""
    def rotating(k):
        h = _relay(k)
        return h * np.exp(1j * 7.0 * np.arange(1, 8) * k * (np.arange(1, 8) > 1))
    search = KfcSearch(0.0, 1.0)
    for k in (0.0, 0.2, 0.27, 0.36, 0.45, 0.6, 1.0):
        search.points[k] = search._point_from_moments(k, rotating(k), np.full(7, 1e-12), 4)
    est = search._estimate(0.2, 0.6)
    assert search.regime == "ratio minimiser" and not est["stop"]
    near = (0.2, 0.27, 0.36)                        # the smallest ratio and its neighbours
    c = np.polyfit(near, [odd_ratio(rotating(k)) ** 2 for k in near], 2)
    vertex = -c[1] / (2 * c[0])
    assert 0.2 + 0.016 < vertex < 0.36 - 0.016 and abs(vertex - 0.27) > 0.008  # a parabolic step
    assert est["next"] == pytest.approx(vertex, rel=1e-9)


def test_signed_root_search_without_sign_change_reports_the_smaller_objective():
    from fftune.analysis.tuning import SignedRootSearch
    res = SignedRootSearch(0.2, 1.0).run(lambda k: 2.0 - k)      # no sign change
    assert not res.converged and res.n_evaluations == 2
    assert res.k_fc == 1.0                 # |s(1.0)| = 1.0 < |s(0.2)| = 1.8


def _rotating(k):
    """Odd phases that rotate with K_fc: the search falls back on the ratio minimiser."""
    return _relay(k) * np.exp(1j * 7.0 * np.arange(1, 8) * k * (np.arange(1, 8) > 1))


@pytest.mark.parametrize("width_in_tol, stops", [(1.9, True), (2.5, False)])
def test_ratio_minimiser_stops_when_the_bracket_is_two_tolerances(width_in_tol, stops):
    """The ratio minimiser stops when the bracket around the smallest ratio is at most
    2 tol wide, with sigma = max(width / (2 sqrt 3), tol) = tol there."""
    tol = 0.004
    search = KfcSearch(0.0, 1.0, xtol=tol, rtol=0.0)
    x = 0.3
    w = width_in_tol * tol
    for k in (0.0, 0.2, 0.27, x - w / 2, x, x + w / 2, 0.36, 0.45, 0.6, 1.0):
        search.points[k] = search._point_from_moments(k, _rotating(k), np.full(7, 1e-12), 4)
    est = search._estimate(0.2, 0.6)
    assert search.regime == "ratio minimiser" and est["stop"] is stops
    if stops:
        res = est["result"]
        assert res.converged and res.k_fc == x and res.sigma == pytest.approx(tol)
        assert np.isfinite(res.sigma_signed) and res.sigma_signed > 0   # pooled s noise
        assert res.sigma_fit == 0.0       # one model only: no flatness / model part
        assert res.bracket == pytest.approx((x - w / 2, x + w / 2))


def test_ratio_minimizer_default_xtol_is_a_thousandth_of_the_bracket():
    assert RatioMinimizer(0.2, 1.0).xtol == pytest.approx(0.8e-3)


# --- round 3 (issue 16): the K_fc search's rules, each against what it is for -------------

def test_told_k_fc_must_match_within_1e_12_near_zero():
    """Near K_fc = 0 the told value must match the asked one within 1e-12 absolute (not
    2e-12): a host that rounds the gain it ran is caught."""
    search = SignedRootSearch(1e-3, 1.0)
    with pytest.raises(InputError, match="asked"):
        search.tell(1e-3 + 1.5e-12, 1.0)
    search.tell(1e-3 + 0.9e-12, 1.0)


def test_t_factor_with_one_degree_of_freedom_is_finite():
    """One degree of freedom (two periods at one experiment) still gives a (wide) interval:
    Student's t with 1 dof, not 'infinitely uncertain'; none at all gives inf."""
    from scipy.stats import t as student_t

    from fftune.analysis.tuning import _t_factor
    assert _t_factor(1) == pytest.approx(student_t.ppf(0.9772, 1) / 2)
    assert np.isfinite(_t_factor(1)) and _t_factor(0) == np.inf


def test_kfc_search_runs_with_the_smallest_budget_of_three_experiments():
    search = KfcSearch(0.0, 1.0, max_experiments=3)
    assert search.max_experiments == 3
    res = search.run(lambda k: _relay(k)[None, :] + 1e-6 * np.arange(2)[:, None])
    assert not res.converged and res.n_experiments == 3 and "max_experiments (now 3)" in res.reason
    with pytest.raises(InputError, match="max_experiments must be >= 3"):
        KfcSearch(0.0, 1.0, max_experiments=2)


def test_ratio_standard_error_is_continuous_where_the_odd_lines_vanish():
    """With every odd line exactly 0 (q = 0, where the gradient formula divides by q) the
    ratio's standard error is the limit of the general formula as the lines go to 0 (equal
    line variances), not a different constant."""
    search = KfcSearch(0.0, 1.0)
    H = np.array([2.0, 0, 0, 0, 0, 0, 0], complex)
    H_var = np.full(7, 1e-6)
    at_zero = search._point_from_moments(0.5, H, H_var, 4)
    tiny = H.copy()
    tiny[2], tiny[4], tiny[6] = 1e-9, 1e-9j, -1e-9
    near_zero = search._point_from_moments(0.5, tiny, H_var, 4)
    assert at_zero.ratio == 0.0
    assert at_zero.ratio_std == pytest.approx(near_zero.ratio_std, rel=1e-9)
    # sqrt(n v / (2 n^2) / |H_1|^2 / P) with n = 3 lines of variance v
    assert at_zero.ratio_std == pytest.approx(np.sqrt(3e-6 / 18 / 4 / 4))


def test_first_interior_point_too_close_to_an_end_is_the_midpoint():
    """A secant root within 5 % of the bracket from an end says little (one end dominates):
    the third experiment is the midpoint instead."""
    search = KfcSearch(0.0, 1.0)
    H = {}
    for _ in range(2):
        k = search.ask()
        H[k] = _relay(k, fc=0.02)
        search.tell_moments(k, H[k], np.full(7, 1e-10), 4)
    phases = reference_phases(H[0.0] - H[1.0])
    s0, s1 = signed_odd_ratio(H[0.0], phases), signed_odd_ratio(H[1.0], phases)
    assert 0 < s0 / (s0 - s1) < 0.05                  # the secant root: near the lower end
    assert search.ask() == 0.5


# The verification rules of KfcSearch._estimate on hand-made experiments: H_1 = 1 and the
# odd lines H_3 = H_5 = H_7 = s + j f, so that the signed objective is s (reference phase
# 0), the ratio sqrt(s^2 + f^2), and both have the standard error SIGMA (line variances).
SIGMA, PERIODS = 1e-3, 4


def _shaped(s, floor=0.0, sigma=SIGMA):
    H = np.zeros(7, complex)
    H[0] = 1.0
    H[2] = H[4] = H[6] = s + 1j * floor
    H_var = np.zeros(7)
    H_var[2] = H_var[4] = H_var[6] = 6 * PERIODS * sigma ** 2
    return H, H_var, PERIODS


def _made(points, **kw):
    """A KfcSearch holding experiments {k: s or (s, floor[, sigma])}."""
    search = KfcSearch(0.0, 1.0, **kw)
    for k, spec in points.items():
        search.points[k] = search._point_from_moments(k, *_shaped(*np.atleast_1d(spec)))
    return search


def _sigma_noise(slope, n_points, sigma=SIGMA):
    """The documented noise part of sigma(K_fc*): the pooled standard error of s through the
    slope, times t_{0.977, dof} / 2 with dof = the experiments' periods - 1, summed."""
    from fftune.analysis.tuning import _t_factor
    return sigma / abs(slope) * _t_factor(n_points * (PERIODS - 1))


def test_made_experiments_have_the_intended_objective_and_noise():
    search = _made({0.1: 0.2, 0.5: (-0.1, 0.05)})
    s, s_se = search._signed(search._sorted(), np.zeros(3))
    np.testing.assert_allclose(s, [0.2, -0.1], rtol=1e-12)
    np.testing.assert_allclose(s_se, SIGMA, rtol=1e-12)
    assert search.points[0.5].ratio == pytest.approx(np.hypot(0.1, 0.05), rel=1e-12)
    assert search.points[0.5].ratio_std == pytest.approx(SIGMA, rel=1e-12)


def test_estimate_verified_by_s_zero_at_a_measured_point():
    """s = 0.5 (0.3 - K) measured at K = 0.3: verified there, sigma = the noise part alone."""
    search = _made({0.0: 0.15, 0.2: 0.05, 0.3: 0.0, 0.4: -0.05, 1.0: -0.35})
    est = search._estimate(0.2, 0.4)
    assert est["stop"]
    res = est["result"]
    assert res.converged and res.regime == "signed root" and res.k_fc == pytest.approx(0.3, abs=1e-15)
    assert res.slope == pytest.approx(-0.5, rel=1e-12)
    assert res.sigma_signed == pytest.approx(SIGMA, rel=1e-12)
    assert res.sigma == pytest.approx(_sigma_noise(0.5, 5), rel=1e-12)
    assert res.bracket == (0.2, 0.4) and res.n_experiments == 5
    assert "K_fc = 0.3 has s = 0 (noise 0.001)" in res.reason


def test_estimate_uses_the_over_compensated_secant_inside_the_sign_change():
    """Under-compensated s bends (stick-slip), over-compensated it is linear: the next
    experiment is where the line through the two over-compensated points nearest the root
    crosses zero, not the interpolation across the sign change."""
    under = {0.0: 0.15 + 0.27, 0.2: 0.05 + 0.03}         # 0.5 (0.3 - K) + 3 (0.3 - K)^2
    search = _made({**under, 0.4: -0.05, 0.5: -0.1, 1.0: -0.35})
    est = search._estimate(0.2, 0.5)
    assert not est["stop"] and est["next"] == pytest.approx(0.3, abs=1e-12)
    # an over-compensated side that flattens: its secant falls outside the sign change and
    # the linear interpolation across the sign change is used
    search = _made({**under, 0.4: -0.05, 0.5: -0.06, 1.0: -0.35})
    est = search._estimate(0.2, 0.5)
    assert not est["stop"] and est["next"] == pytest.approx(0.2 + 0.2 * 0.08 / 0.13, rel=1e-12)


@pytest.mark.parametrize("offset", [2e-4, -2e-4, 1e-3])
def test_estimate_on_an_unverified_measured_point_probes_one_tolerance_beside_it(offset):
    """The estimate falls on a measured point (within a quarter tolerance) whose ratio is
    too high to verify it: the next experiment is one tolerance beside the estimate, on
    the side of the sign change (towards the other sign of s). Farther from the point
    (1e-3, half a tolerance) the estimate itself is the next experiment."""
    k_m = 0.3 + offset
    search = _made({0.0: 0.15, 0.2: 0.05, k_m: (0.5 * (0.3 - k_m), 0.1), 0.4: -0.05, 1.0: -0.35})
    est = search._estimate(0.2, 0.4)
    tol = _sigma_noise(0.5, 5)
    assert tol > 0.3 * 5e-3                            # the noise sets the tolerance
    assert not est["stop"]
    probe = abs(offset) < 0.25 * tol
    assert est["next"] == pytest.approx(0.3 - np.sign(offset) * tol * probe, rel=1e-9)


def test_estimate_probe_outside_the_sign_change_falls_back_to_its_midpoint():
    k_m, k_n = 0.2998, 0.301
    search = _made({0.0: 0.15, 0.2: 0.05, k_m: (0.5 * (0.3 - k_m), 0.1), k_n: 0.5 * (0.3 - k_n),
                    0.4: -0.05, 1.0: -0.35})
    est = search._estimate(0.2, 0.4)
    assert not est["stop"] and est["next"] == pytest.approx(0.5 * (k_m + k_n), rel=1e-12)


@pytest.mark.parametrize("excess, verified", [(-1e-3, True), (1e-3, False)])
def test_estimate_verification_ratio_within_two_standard_errors_and_one_percent(excess, verified):
    """The ratio at the verification may exceed the smallest other measured ratio (here
    far away, at K = 1) by at most 2 combined standard errors plus 1 % of it."""
    best = 0.35
    floor = best + 2 * np.hypot(SIGMA, SIGMA) + 0.01 * best + excess
    # a ratio floor of 0.4 around the optimum: its neighbours are higher (a local minimum)
    search = _made({0.0: (0.15, 0.4), 0.2: (0.05, 0.4), 0.3: (0.0, floor), 0.4: (-0.05, 0.4),
                    1.0: -best})
    est = search._estimate(0.2, 0.4)
    assert est["stop"] is verified
    if not verified:
        assert est["next"] == pytest.approx(0.3 - _sigma_noise(0.5, 5), rel=1e-9)   # s = 0: below


@pytest.mark.parametrize("side", ["left", "right"])
def test_estimate_verification_needs_a_local_minimum_of_the_ratio(side):
    """Within the 1 % allowance of the smallest ratio, but the nearest measured point on
    one side lies below the verification's ratio by more than 2 standard errors: not a
    local minimum, not verified. Within 2 standard errors it is."""
    band = 2 * np.hypot(SIGMA, SIGMA)
    for extra, verified in ((1.5e-4, False), (-1.5e-4, True)):
        low, high = 0.025, (0.025, 0.05)             # ratios 0.025 and 0.056 beside K = 0.3
        near = {0.25: low, 0.35: (-high[0], high[1])} if side == "left" else \
            {0.25: high, 0.35: -low}
        search = _made({0.0: 0.15, 0.2: 0.05, **near, 0.3: (0.0, low + band + extra),
                        0.4: -0.05, 1.0: -0.35})
        assert search._estimate(0.2, 0.4)["stop"] is verified, (side, extra)


@pytest.mark.parametrize("noisy", [0.25, 0.3])
def test_s_rising_within_its_noise_still_counts_as_falling(noisy):
    """Monotone within the noise: a rise of s between neighbours up to 2 standard errors
    of their difference is tolerated (the noisier point's error counts, before or after
    the rise), a larger one sends the search to the ratio minimiser."""
    big = 0.01
    for rise, regime in ((1.8 * np.hypot(big, SIGMA), "signed root"),
                         (2.2 * np.hypot(big, SIGMA), "ratio minimiser")):
        se = {0.25: SIGMA, 0.3: SIGMA, noisy: big}
        search = _made({0.0: 0.15, 0.2: 0.05, 0.25: (0.04, 0.0, se[0.25]),
                        0.3: (0.04 + rise, 0.0, se[0.3]), 0.4: -0.05, 1.0: -0.35})
        search._estimate(0.2, 0.4)
        assert search.regime == regime, rise


def _lack_of_fit(ks, s):
    """Slope and rms residual (n - 2 dof) of the straight line fitted through (ks, s)."""
    fit = np.polyfit(ks, s, 1)
    return fit[0], np.sqrt(np.sum((s - np.polyval(fit, ks)) ** 2) / (len(ks) - 2))


@pytest.mark.parametrize("near, how", [((0.25, 0.29, 0.31, 0.35), "has s = 0.015"),
                                       ((0.24, 0.26, 0.28, 0.29, 0.31, 0.32, 0.34, 0.36),
                                        "sign change of s bracketed in [0.29, 0.31]")])
def test_scatter_of_s_from_k_to_k_above_the_noise_sets_sigma(near, how):
    """s jumps by 0.02 at the root (quantisation, a limit cycle), far more than the period
    noise: with 4 or more experiments within 25 % of the estimate, the rms residual of a
    line through them is the noise of s (dof: their number - 2) and the line's slope is
    the slope; a sign change bracketed within the tolerance verifies."""
    jump = 0.01
    s_of = {k: 0.5 * (0.3 - k) + jump * np.sign(0.3 - k) for k in near}
    search = _made({0.0: 0.15 + jump, 0.2: 0.05 + jump, **s_of, 0.4: -0.05 - jump})
    est = search._estimate(0.2, 0.4)
    assert est["stop"]
    res = est["result"]
    slope, lof = _lack_of_fit(np.array(near), np.array([s_of[k] for k in near]))
    assert lof > 5 * SIGMA
    assert res.converged and how in res.reason and res.k_fc == pytest.approx(0.3, abs=1e-12)
    assert res.sigma_signed == pytest.approx(lof, rel=1e-9)
    assert res.slope == pytest.approx(slope, rel=1e-9)
    from fftune.analysis.tuning import _t_factor
    sigma = np.hypot(lof / abs(slope) * _t_factor(len(near) - 2), 0.01)       # |K_m - K*| = 0.01
    if "bracketed" in how:
        sigma = np.hypot(sigma, 0.02 / np.sqrt(12))       # and the bracket's uniform spread
    assert res.sigma == pytest.approx(sigma, rel=1e-9)


def test_s_on_a_line_keeps_the_period_noise():
    """Four experiments near the estimate exactly on a line: no lack of fit, sigma from
    the period noise as without them."""
    near = {k: 0.5 * (0.3 - k) for k in (0.25, 0.28, 0.3, 0.33, 0.36)}
    search = _made({0.0: 0.15, 0.2: 0.05, **near, 0.4: -0.05})
    res = search._estimate(0.2, 0.4)["result"]
    assert res.converged and res.sigma_signed == pytest.approx(SIGMA, rel=1e-9)
    assert res.sigma == pytest.approx(_sigma_noise(0.5, 8), rel=1e-9)


def _asked(search, s_of_k, n):
    """The first n experiments the search asks for, told the made-up objective s(K)."""
    asked = []
    while not search.done and len(asked) < n:
        k = search.ask()
        asked.append(k)
        search.tell_moments(k, *_shaped(s_of_k(k)))
    return asked


@pytest.mark.parametrize("root, third", [(0.25, 0.25), (0.23, 0.6), (0.95, 0.95), (0.97, 0.6)])
def test_first_interior_point_kept_unless_within_5_percent_of_an_end(root, third):
    """On [0.2, 1.0] the secant root of s is the third experiment when it lies 5 % of the
    bracket (0.04) or more inside it, else the midpoint."""
    asked = _asked(KfcSearch(0.2, 1.0), lambda k: 0.5 * (root - k), 3)
    assert asked[:2] == [1.0, 0.2] and asked[2] == pytest.approx(third, abs=1e-12)


@pytest.mark.parametrize("root, k_limit, third", [(2.0, 10.0, 1.0), (0.26, 10.0, 0.3125),
                                                  (0.5, 10.0, 0.575), (0.5, 0.4, 0.4)])
def test_extension_when_both_ends_are_under_compensated(root, k_limit, third):
    """s > 0 at both ends and falling: the third experiment is 1.15 x the extrapolated root,
    within [1.25, 4] x upper and the drive's limit."""
    asked = _asked(KfcSearch(0.0, 0.25, k_limit=k_limit), lambda k: 0.5 * (root - k), 3)
    assert asked[2] == pytest.approx(third, rel=1e-12)


def test_extension_doubles_the_top_while_its_ratio_is_the_smallest():
    search = KfcSearch(0.0, 0.25, k_limit=10.0, max_experiments=8)
    asked = _asked(search, lambda k: 0.5 * (20.0 - k), 8)
    assert asked == pytest.approx([0.25, 0.0, 1.0, 2.0, 4.0, 8.0, 10.0])
    res = search.result
    assert not res.converged and "drive's limit" in res.reason and res.extended_to == 10.0


def test_ratio_minimizer_follows_scipy_on_a_shifted_bracket_and_quantised_objectives():
    """As test_ratio_minimizer_follows_brent_fmin_as_scipy, on a bracket that does not start
    at 0 and on objectives with many equal values (a quantised measurement)."""
    objectives = [lambda k: abs(k - 0.71) + 0.02, lambda k: abs(k - 0.55) ** 0.5 + 0.01,
                  lambda k: abs(k - 0.95) ** 0.5 + 0.01,
                  lambda k: np.round(abs(k - 0.5) * 20) / 20,
                  lambda k: np.round(np.sqrt((k - 0.93) ** 2 + 0.01) * 8) / 8]
    for objective in objectives:
        for lower, upper in ((0.2, 1.3), (0.0, 1.0)):
            ours = []
            res = RatioMinimizer(lower, upper, xtol=1e-4, max_evaluations=200).run(
                lambda k: (ours.append(k), objective(k))[1])
            ref = []
            minimize_scalar(lambda k: (ref.append(k), objective(k) ** 2)[1], bounds=(lower, upper),
                            method="bounded", options={"xatol": 1e-4, "maxiter": 200})
            assert len(ours) == len(ref)
            np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-9)
            assert res.converged


def test_ratio_minimizer_says_how_narrow_the_bracket_got():
    res = RatioMinimizer(0.0, 1.0, xtol=3e-3).run(lambda k: abs(k - 0.3) + 0.01)
    assert res.converged and res.reason == "bracket below 0.004"      # 4 (xtol / 3 + eps |K|)


def test_signed_root_search_result_before_any_evaluation_is_not_converged():
    res = SignedRootSearch(0.2, 0.6).result
    assert not res.converged and res.reason == "running" and res.history == []


def test_signed_root_search_without_sign_change_and_equal_ends_reports_the_upper():
    res = SignedRootSearch(0.25, 0.75).run(lambda k: 1.0 + (k - 0.5) ** 2)
    assert not res.converged and res.k_fc == 0.75


def test_a_motor_hardly_moving_within_its_noise_has_no_ratio():
    """|H_1| below 1e-3 of its own noise (its standard deviation per period): the motor
    does not follow the sine, the ratio is inf (not a number from noise)."""
    search = KfcSearch(0.0, 1.0)
    k = search.ask()
    H = _relay(0.1) * 0 + 1e-3
    H_var = np.full(7, 1e-8)
    H_var[0] = 4.0                                    # sqrt: 2 >> 1e3 |H_1|
    search.tell_moments(k, H, H_var, 4)
    assert np.isinf(search.points[k].ratio)
    k = search.ask()
    H_var[0] = 0.25                                   # sqrt: 0.5 < 1e3 |H_1|
    search.tell_moments(k, H, H_var, 4)
    assert np.isfinite(search.points[k].ratio)


def test_both_ends_under_compensated_at_the_drive_limit_take_the_midpoint():
    """upper = k_limit (the default): no room to extend, the third experiment is the
    midpoint and the search says it hit the drive's limit; no experiment is repeated."""
    search = KfcSearch(0.0, 0.25)
    asked = _asked(search, lambda k: 0.5 * (2.0 - k), 8)
    assert asked[2] == 0.125 and search.extended_to is None
    assert len(set(asked)) == len(asked)
    assert search.done and "drive's limit" in search.result.reason


@pytest.mark.parametrize("which, offset, repeat", [(1, 5e-10, True), (1, 1.5e-9, False),
                                                   (2, -2e-9, True), (2, -4e-9, False)])
def test_a_step_onto_a_measured_experiment_stalls_the_search(which, offset, repeat):
    """A next experiment within 1e-9 of a measured one (relative above |K| = 1; here 0.3
    and 3.0) cannot add information: the search stops, not converged, and says so."""
    search = KfcSearch(0.0, 3.0, max_experiments=12)
    search._estimate = lambda a, b: {"stop": False, "next": sorted(search.points)[which] + offset}
    asked = _asked(search, lambda k: 0.5 * (0.3 - k), 3)
    assert asked[2] == pytest.approx(0.3)
    assert search.done is repeat
    if repeat:
        assert "stalled" in search.result.reason and not search.result.converged
    else:
        assert search.ask() == sorted(search.points)[which] + offset


def test_s_at_the_nearest_point_beyond_its_noise_is_not_verified():
    """Under-compensated s is offset by 3.8 standard errors (a stuck motor), the over-
    compensated points put the root at 0.3: the experiment 5e-4 beside the root is within
    the tolerance but its s is not 0 within 2 standard errors (plus slope x tolerance):
    not verified, the next experiment is the estimate itself."""
    jump = 3.8 * SIGMA
    search = _made({0.0: 0.15 + jump, 0.2995: 0.5 * (0.3 - 0.2995) + jump, 0.31: -0.005,
                    0.4: -0.05, 1.0: -0.35})
    est = search._estimate(0.0, 0.4)
    assert not est["stop"] and est["next"] == pytest.approx(0.3, abs=1e-12)


def _ratios_only(ratios, **kw):
    """Experiments with s = 0 and the given ratios: the odd phases give no signed root."""
    return _made({k: (0.0, r) for k, r in ratios.items()}, **kw)


@pytest.mark.parametrize("x, cases", [
    (0.84, ((0.91, 0.84 - 0.381966 * 0.84), (0.88, 0.84 - 0.381966 * 0.84), (0.895, 0.895))),
    (0.16, ((0.09, 0.16 + 0.381966 * 0.84), (0.12, 0.16 + 0.381966 * 0.84), (0.105, 0.105)))])
def test_ratio_minimiser_rejects_a_parabolic_step_near_the_bracket_end(x, cases):
    """Smallest ratio at x in [0, 1]: the vertex of the parabola through r^2 is taken
    unless it lies within 10 % of the bracket from its end or within 5 % of x; then a
    golden-section step into the larger part instead."""
    for vertex, expected in cases:
        search = _ratios_only({k: np.sqrt(2.0 * (k - vertex) ** 2 + 0.01) for k in (0.0, x, 1.0)})
        est = search._estimate(0.0, 1.0)
        assert search.regime == "ratio minimiser" and not est["stop"]
        assert est["next"] == pytest.approx(expected, rel=1e-9), vertex


def test_a_sub_bracket_keeps_the_reference_phases_of_the_bracket_that_holds_it():
    """Near the optimum a quadrature component (the ratio's floor) turns the odd phases:
    the sub-bracket's own ends would give phases under which s rises (ratio minimiser).
    The earlier bracket that holds it, with s falling over it, keeps the signed root."""
    search = _made({0.0: 0.15, 0.4: -0.05, 1.0: -0.35})
    first = search._estimate(0.0, 0.4)
    assert search.regime == "signed root" and first["next"] == pytest.approx(0.3)
    for k, spec in {0.25: (0.025, 0.2), 0.3: (0.0, 0.25), 0.35: (-0.025, 0.0)}.items():
        search.points[k] = search._point_from_moments(k, *_shaped(*spec))
    own, _ = search._signed([search.points[k] for k in (0.25, 0.3, 0.35)], search._phases(0.25, 0.35))
    assert own[1] - own[0] > 0.04                                # rises with its own phases
    search._estimate(0.25, 0.35)
    assert search.regime == "signed root"
    search._estimate(0.25, 0.4)                                 # sharing its upper end
    assert search.regime == "signed root"
    # a bracket the earlier one does not hold: its own phases, the ratio minimiser here
    search.points[0.45] = search._point_from_moments(0.45, *_shaped(-0.075, 0.3))
    search._estimate(0.3, 0.45)
    assert search.regime == "ratio minimiser"


def test_golden_step_of_the_ratio_minimiser_goes_into_the_lower_half_on_a_tie():
    """Equal halves around the smallest ratio (0.5 in [0, 1]) and a parabolic vertex too
    close to it (0.51): the golden-section step goes into the lower half."""
    search = _ratios_only({k: np.sqrt(2.0 * (k - 0.51) ** 2 + 0.01) for k in (0.0, 0.5, 1.0)})
    est = search._estimate(0.0, 1.0)
    assert search.regime == "ratio minimiser"
    assert est["next"] == pytest.approx(0.5 - 0.381966 * 0.5, rel=1e-12)


def test_per_period_points_of_a_motor_that_does_not_move():
    """|H_1| ~ 1e-7 in every period (steady, so not 'averaged out'): below the absolute
    floor 1e-6, the motor does not move: no ratio (inf) and no spread (0); a point without
    a ratio gets no signed objective (NaN) and does not stop the others'."""
    search = KfcSearch(0.0, 1.0)
    k = search.ask()
    search.tell(k, np.full((4, 7), 1e-7 + 0j) + 1e-9 * np.arange(4)[:, None])
    assert np.isinf(search.points[k].ratio) and search.points[k].ratio_std == 0.0
    k2 = search.ask()
    search.tell_moments(k2, np.full(7, 1e-7 + 0j), np.zeros(7), 4)
    assert np.isinf(search.points[k2].ratio) and search.points[k2].ratio_std == 0.0
    moving = search._point_from_moments(0.5, *_shaped(0.1))
    s, s_se = search._signed([search.points[k], search.points[k2], moving], np.zeros(3))
    assert np.isnan(s[:2]).all() and np.isnan(s_se[:2]).all()
    assert s[2] == pytest.approx(0.1) and s_se[2] == pytest.approx(SIGMA)


def test_local_minimum_rule_looks_at_the_nearest_point_on_each_side_only():
    """A lower ratio farther out (here at K = 0.1, with the 1 % allowance) does not make
    the verification fail: only the nearest measured point on each side must not be below
    it by more than the noise."""
    best = 0.35
    floor = best + 2 * np.hypot(SIGMA, SIGMA) + 0.01 * best - 1e-3
    search = _made({0.0: (0.15, 0.4), 0.1: (0.1, np.sqrt(best ** 2 - 0.1 ** 2)), 0.2: (0.05, 0.4),
                    0.3: (0.0, floor), 0.4: (-0.05, 0.4), 1.0: -best})
    assert search.points[0.1].ratio == pytest.approx(best)
    assert search._estimate(0.2, 0.4)["stop"]


def test_signed_root_search_stops_at_a_bracket_of_exactly_two_xtol():
    """s(0) = 1, s(1) = -3: the secant step lands on 0.25 where s = -1, leaving [0, 0.25]:
    exactly 2 xtol (xtol = 0.125) stops the search, as below 2 xtol does."""
    f = lambda k: 1 - 8 * k if k <= 0.25 else -1 - (k - 0.25) * 8 / 3      # noqa: E731
    res = SignedRootSearch(0.0, 1.0, xtol=0.125).run(f)
    assert res.converged and res.reason == "bracket below 2 xtol" and res.n_evaluations == 3


def test_signed_root_search_stops_at_a_step_of_exactly_xtol():
    """Two successive secant estimates exactly xtol apart stop the search (step below or
    at xtol), the bracket still wide."""
    values = {0.0: 1.0, 1.0: -3.0, 0.25: 0.5}
    c2 = (0.25 * -3.0 - 1.0 * 0.5) / (-3.0 - 0.5)          # the step after 0.25, as computed
    res = SignedRootSearch(0.0, 1.0, xtol=abs(c2 - 0.25)).run(lambda k: values.get(k, 0.2))
    assert [k for k, _ in res.history] == [0.0, 1.0, 0.25, c2]
    assert res.converged and res.reason == "step below xtol"


def test_search_defaults():
    """Defaults a caller relies on: 8 experiments for KfcSearch, xtol 1e-4 of the bracket
    for SignedRootSearch (as 1e-3 for RatioMinimizer), also off zero."""
    assert KfcSearch(0.0, 1.0).max_experiments == 8
    assert SignedRootSearch(0.2, 1.0).xtol == pytest.approx(0.8e-4)


def test_a_lower_end_that_does_not_move_leaves_the_ratio_minimiser():
    """The lower end of the bracket has no ratio (the motor did not move): no reference
    phases, the ratio minimiser takes a golden-section step into the larger part."""
    search = _made({0.2: 0.02, 0.5: -0.1, 1.0: -0.35})
    search.points[0.0] = search._point_from_moments(0.0, np.full(7, 1e-7 + 0j), np.zeros(7), 4)
    est = search._estimate(0.0, 0.5)
    assert search.regime == "ratio minimiser" and not est["stop"]
    assert est["next"] == pytest.approx(0.2 + 0.381966 * 0.3, rel=1e-12)


def test_points_beyond_two_tolerances_of_the_estimate_count_as_other_points():
    """A measured point 2.5 tolerances beside the estimate is another K_fc (not the same
    within the resolution): its smaller ratio makes the verification at 0.3 fail."""
    tol = _sigma_noise(0.5, 6)
    k_o = 0.3 + 2.5 * tol
    search = _made({0.0: 0.15, 0.2: 0.05, 0.3: (0.0, 0.01), k_o: 0.5 * (0.3 - k_o), 0.4: -0.05,
                    1.0: -0.35})
    assert not search._estimate(0.2, 0.4)["stop"]


def test_empty_bracket_is_refused_whatever_the_tolerance():
    for search in (SignedRootSearch, RatioMinimizer):
        with pytest.raises(InputError, match="lower < upper"):
            search(1.0, 1.0, xtol=1e-3)


def test_stopping_tolerance_has_a_floor():
    """xtol = rtol = 0: the stopping tolerance is 1e-12, never 0."""
    search = KfcSearch(0.0, 1.0, xtol=0.0, rtol=0.0)
    assert search._tol(0.3) == 1e-12 and search._tol(0.0) == 1e-12


def test_failed_search_reports_the_measured_point_with_the_smallest_ratio():
    search = KfcSearch(0.0, 0.05, k_limit=0.12)
    while not search.done:
        k = search.ask()
        search.tell_moments(k, _relay(k), np.full(7, 1e-10), 4)
    res = search.result
    assert not res.converged
    assert res.k_fc == min(res.points, key=lambda p: p.ratio).k_fc == pytest.approx(0.12)
    # nothing moved: no best point
    still = KfcSearch(0.0, 1.0, max_experiments=3)
    while not still.done:
        still.tell_moments(still.ask(), np.full(7, 1e-7 + 0j), np.zeros(7), 4)
    assert not still.result.converged and np.isnan(still.result.k_fc)


def test_signed_ratio_std_is_vectorised_over_experiments():
    from fftune.analysis.tuning import signed_odd_ratio_std
    rng = np.random.default_rng(4)
    H = _relay(0.1) + 0.01 * rng.standard_normal((3, 7))
    H_std = 1e-3 * (1 + rng.random((3, 7)))
    rows = [signed_odd_ratio_std(h, s, 4) for h, s in zip(H, H_std)]
    np.testing.assert_allclose(signed_odd_ratio_std(H, H_std, 4), rows, rtol=1e-12)


def test_signed_root_search_while_running_reports_the_end_with_the_smaller_objective():
    search = SignedRootSearch(0.2, 0.6)
    search.tell(search.ask(), 0.5)
    search.tell(search.ask(), -0.1)
    assert search.result.k_fc == 0.6 and search.result.reason == "running"


def test_s_crossing_zero_twice_within_the_noise_uses_the_first_sign_change():
    """s falls through 0, comes back above it within the noise and falls again: the first
    sign change (between 0.25 and 0.3) gives the estimate, by linear interpolation."""
    big = 0.02
    search = _made({0.2: 0.05, 0.25: (0.01, 0.0, big), 0.3: (-0.01, 0.0, big), 0.35: (0.01, 0.0, big),
                    0.4: -0.05})
    est = search._estimate(0.2, 0.4)
    assert search.regime == "signed root" and est["stop"]
    assert est["result"].k_fc == pytest.approx(0.275, rel=1e-9)


def test_three_scattered_points_near_the_estimate_are_no_lack_of_fit():
    """A line through three points has one degree of freedom: no lack-of-fit estimate from
    fewer than four; with the period noise the estimate (0.3, 0.01 from the nearest points)
    is not verified and is the next experiment."""
    jump = 0.01
    near = {k: 0.5 * (0.3 - k) + jump * np.sign(0.3 - k) for k in (0.27, 0.29, 0.31)}
    search = _made({0.0: 0.15 + jump, 0.2: 0.05 + jump, **near, 0.4: -0.05 - jump})
    est = search._estimate(0.2, 0.4)
    assert not est["stop"] and est["next"] == pytest.approx(0.3, abs=1e-12)


def test_slope_of_exactly_minus_one_gives_a_finite_sigma():
    search = _made({0.0: 0.375, 0.25: 0.125, 0.375: 0.0, 0.5: -0.125, 1.0: -0.625})
    res = search._estimate(0.25, 0.5)["result"]
    assert res.converged and res.slope == -1.0
    assert res.sigma == pytest.approx(_sigma_noise(1.0, 5), rel=1e-12)


def test_points_within_two_tolerances_of_the_estimate_are_the_same_k_fc():
    """A measured point 1.5 tolerances beside the estimate is the same K_fc within the
    resolution: its smaller ratio does not fail the verification at 0.3."""
    tol = _sigma_noise(0.5, 6)
    k_o = 0.3 + 1.5 * tol
    search = _made({0.0: 0.15, 0.2: 0.05, 0.3: (0.0, 0.01), k_o: 0.5 * (0.3 - k_o), 0.4: -0.05,
                    1.0: -0.35})
    assert search._estimate(0.2, 0.4)["stop"]


def test_ratio_minimiser_at_the_lower_end_takes_a_golden_step():
    """The smallest ratio at the bracket's lower end: no parabola (no point below it), a
    golden-section step up; one not-moving point two below the smallest ratio does not
    stop the parabola through the smallest and its neighbours."""
    search = _ratios_only({0.0: 0.01, 0.3: 0.05, 1.0: 0.2})
    est = search._estimate(0.0, 0.3)
    assert search.regime == "ratio minimiser" and est["next"] == pytest.approx(0.381966 * 0.3, rel=1e-12)
    r = {k: np.sqrt(2.0 * (k - 0.3) ** 2 + 0.01) for k in (0.1, 0.25, 0.5)}
    search = _ratios_only(r)
    search.points[0.0] = search._point_from_moments(0.0, np.full(7, 1e-7 + 0j), np.zeros(7), 4)
    est = search._estimate(0.0, 0.5)
    assert search.regime == "ratio minimiser" and est["next"] == pytest.approx(0.3, rel=1e-9)


def test_a_small_steady_first_harmonic_is_a_moving_motor():
    search = KfcSearch(0.0, 1.0)
    k = search.ask()
    H = _relay(0.1) * 0.01
    search.tell(k, H[None, :] * (1 + 1e-3 * np.arange(4))[:, None])
    assert np.isfinite(search.points[k].ratio)


def test_a_point_with_s_exactly_zero_is_not_over_compensated():
    """s = 0 at 0.3: the over-compensated points (s < 0) are 0.35 and 0.4, whose line
    crosses zero at 0.29, inside the sign change [0.2, 0.3]: the next experiment."""
    search = _made({0.0: 0.15, 0.2: 0.05, 0.3: 0.0, 0.35: -0.03, 0.4: -0.055, 1.0: -0.35})
    est = search._estimate(0.2, 0.4)
    assert not est["stop"] and est["next"] == pytest.approx(0.29, rel=1e-9)


def test_pooled_standard_error_of_unequal_experiments_is_their_rms():
    """Experiments of unequal noise (stick-slip points are noisier): the pooled standard
    error of s is the rms of theirs, sqrt((1 + 9 + 1 + 1) / 4) SIGMA = sqrt(3) SIGMA, not
    their mean (1.5 SIGMA)."""
    from fftune.analysis.tuning import pooled_standard_error
    search = _made({0.0: (0.15, 0.0, SIGMA), 0.2: (0.05, 0.0, 3 * SIGMA), 0.3: (0.0, 0.0, SIGMA),
                    1.0: (-0.35, 0.0, SIGMA)})
    assert search._pooled_signed_se(np.zeros(3)) == pytest.approx(np.sqrt(3) * SIGMA, rel=1e-9)
    assert pooled_standard_error([SIGMA, 3 * SIGMA, SIGMA, SIGMA, np.nan]) == pytest.approx(
        np.sqrt(3) * SIGMA, rel=1e-12)
    assert np.isnan(pooled_standard_error([np.nan]))


def test_uncertainty_budget_is_the_root_sum_of_squares_of_its_parts():
    from fftune.analysis.tuning import uncertainty_budget
    total, parts = uncertainty_budget({"noise": 3e-3, "amplitude": 4e-3, "encoder": None,
                                       "flatness": np.nan, "viscous": 12e-3})
    assert total == pytest.approx(13e-3, rel=1e-12)
    assert set(parts) == {"noise", "amplitude", "viscous"}


def test_check_experiment_names_saturation_and_no_motion():
    from fftune.analysis.tuning import check_experiment
    ok = check_experiment(1.02, saturated_fraction=0.01, u_max_v=10)
    assert ok["cause"] is None
    sat = check_experiment(0.9, saturated_fraction=0.81, amplitude_rad=8.0, u_max_v=0.6)
    assert sat["cause"] == "saturation" and "u_max = 0.6 V in 81 %" in sat["text"]
    stuck = check_experiment(0.0, saturated_fraction=0.97, u_max_v=0.4)
    assert stuck["cause"] == "no motion" and "the friction exceeds what the drive can give" in stuck["text"]
    # statistics only: the lower bound from rms(u) / u_max = 0.9 is (0.81 - 0.64) / 0.36
    bound = check_experiment(1.0, u_rms_re_max=0.9)
    assert bound["saturated_fraction"] == pytest.approx(0.17 / 0.36) and bound["cause"] == "saturation"
    assert check_experiment(1.0, u_rms_re_max=0.7)["saturated_fraction"] == 0.0


def test_root_at_slope_and_encoder_floor():
    from fftune.analysis.tuning import encoder_floor_v, encoder_step_estimate, root_at_slope
    assert root_at_slope(0.1, 0.02, -0.5) == pytest.approx(0.14)
    assert np.isnan(root_at_slope(0.1, 0.02, 0.5))
    q = 2 * np.pi / 256
    f0 = encoder_floor_v(q, 1.0, 0.0, -0.2)
    assert f0 == pytest.approx(q ** 1.5 / np.pi / 0.2)
    # noise dithers the quantiser: exp(-2 pi^2 (sigma / q)^2)
    assert encoder_floor_v(q, 1.0, q / 4, -0.2) == pytest.approx(f0 * np.exp(-2 * np.pi ** 2 / 16))
    assert encoder_floor_v(0.0, 1.0, 0.0, -0.2) == 0.0
    rng = np.random.default_rng(1)
    t = np.arange(8192) / 2560
    y = q * np.round(0.5 * np.sin(2 * np.pi * 0.625 * t) / q) + 1e-4 * rng.standard_normal(t.size)
    assert encoder_step_estimate(y, 1e-4) == pytest.approx(q, rel=0.02)
    assert encoder_step_estimate(y, q / 3) is None       # noise hides (dithers) the steps
    # no noise given: the steps of a clean quantised angle
    clean = q * np.round(0.5 * np.sin(2 * np.pi * 0.625 * t) / q)
    assert encoder_step_estimate(clean) == pytest.approx(q, rel=1e-9)


def test_amplitude_combination_rules():
    from fftune.analysis.tuning import amplitude_combination
    # a real trend (difference 0.02 >> noise): extrapolated in 1/A, A2 = 2 A1: 2 k2 - k1
    k, noise, part, how = amplitude_combination(1.00, 0.001, 0.5, 0.98, 0.002, 1.0)
    assert k == pytest.approx(0.96) and part == pytest.approx(0.02) and "extrapolated" in how
    assert noise == pytest.approx(np.hypot(0.001, 2 * 0.002))
    # agreement within the noise: inverse-variance mean, the whole difference the part
    k, noise, part, how = amplitude_combination(1.000, 0.004, 0.5, 0.996, 0.002, 1.0)
    assert k == pytest.approx((1.000 / 16 + 0.996 / 4) / (1 / 16 + 1 / 4))
    assert part == pytest.approx(0.004) and noise == pytest.approx(1 / np.sqrt(1 / 16e-6 + 1 / 4e-6))
    # noise-free values (a simulation without noise) do not divide by zero
    k, noise, part, _ = amplitude_combination(1.0, 0.0, 0.5, 1.0, 0.0, 1.0)
    assert k == pytest.approx(1.0) and part == 0.0
    assert amplitude_combination(1.0, 0.001, 0.5, 0.98, 0.002, 1.0, rule="first")[:3] == (1.0, 0.001, pytest.approx(0.02))


def test_viscous_from_harmonics_recovers_a_rigid_plant():
    """u = J y'' + b y' + F_c sgn(y') (per volt) for a sliding sine y with a small third
    harmonic: the fit returns b and F_c; J, b, F_c unequal so a swapped column fails."""
    from fftune.analysis.tuning import viscous_feedforward_estimate, viscous_from_harmonics
    n, c, fs = 4096, 1, 2560.0
    w = 2 * np.pi * c * fs / n
    t = np.arange(n) / fs
    y = 0.5 * np.sin(w * t + 0.3) + 0.004 * np.sin(3 * w * t + 1.1)
    yd = 0.5 * w * np.cos(w * t + 0.3) + 0.012 * w * np.cos(3 * w * t + 1.1)
    ydd = -0.5 * w ** 2 * np.sin(w * t + 0.3) - 0.036 * w ** 2 * np.sin(3 * w * t + 1.1)
    J, b, fc = 2e-3, 0.04, 0.1157
    v1 = 0.5 * w * np.cos(w * t + 0.3)                 # the friction switches with the fundamental
    u = J * ydd + b * yd + fc * np.sign(v1)
    U = np.fft.fft(u)[c * np.arange(1, 8)]
    Y = np.fft.fft(y)[c * np.arange(1, 8)]
    kv, fc_fit = viscous_from_harmonics(U, Y, w, n, c)
    assert kv == pytest.approx(b, rel=1e-3) and fc_fit == pytest.approx(fc, rel=1e-3)
    # from the fundamentals (phasors of amplitude: V, rad) with the Coulomb level known
    U1, Y1 = 2 * U[0] / n, 2 * Y[0] / n
    assert viscous_feedforward_estimate(U1, Y1, w, fc) == pytest.approx(b, rel=2e-3)
    assert viscous_feedforward_estimate(U1, Y1, w, 10 * fc) == 0.0    # negative: none
    # no motion or no frequency: nothing to read, 0 (not a made-up K_v)
    assert viscous_feedforward_estimate(U1, 0.0, w, fc) == 0.0
    assert viscous_feedforward_estimate(U1, Y1, 0.0, fc) == 0.0
    assert np.isnan(viscous_from_harmonics(U, np.zeros(7), w, n, c)[0])
