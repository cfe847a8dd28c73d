"""Feed-forward objective and K_fc searches on closed-form and simulated HOSIDFs."""
import numpy as np
import pytest

from fftune.analysis.errors import InputError
from fftune.analysis.hosidf import hosidf
from fftune.analysis.tuning import (RatioMinimizer, SignedRootSearch, odd_ratio, reference_phases,
                             signed_odd_ratio, signed_odd_ratio_std)

FC, A, GAIN = 0.1157, 1.0, 2.0      # plant Coulomb friction, sine amplitude, linear gain


def relay_with_offset_hosidf(k_fc, fc=FC, amplitude=A, gain=GAIN, k_max=7):
    """Closed form: y = gain u + (fc - k_fc) sign(u): residual relay of (fc - k_fc)."""
    h = np.zeros(k_max, dtype=complex)
    h[0] = gain + 4 * (fc - k_fc) / (np.pi * amplitude)
    for k in range(3, k_max + 1, 2):
        h[k - 1] = (-1) ** ((k - 1) // 2) * 4 * (fc - k_fc) / (k * np.pi * amplitude)
    return h


def test_objectives_on_closed_form():
    h0 = relay_with_offset_hosidf(0.0)
    phases = reference_phases(h0)
    np.testing.assert_allclose(np.degrees(phases), [180, 0, 180], atol=1e-9)
    ks = np.array([0.0, 0.05, FC, 0.2])
    r = np.array([odd_ratio(relay_with_offset_hosidf(k)) for k in ks])
    s = np.array([signed_odd_ratio(relay_with_offset_hosidf(k), phases) for k in ks])
    rms = np.sqrt(np.mean([(1 / 3) ** 2, (1 / 5) ** 2, (1 / 7) ** 2]))
    expected = rms * 4 * np.abs(FC - ks) / np.pi / np.abs(GAIN + 4 * (FC - ks) / np.pi)
    np.testing.assert_allclose(r, expected, rtol=1e-12)
    assert r[2] == pytest.approx(0.0, abs=1e-15)
    assert s[0] > 0 and s[1] > 0 and s[3] < 0 and abs(s[2]) < 1e-15
    np.testing.assert_allclose(np.abs(s), r * np.mean([1 / 3, 1 / 5, 1 / 7]) / rms, rtol=1e-12)
    # configurable harmonic set
    assert odd_ratio(h0, harmonics=(3,)) == pytest.approx(4 * FC / (3 * np.pi) / abs(h0[0]))
    with pytest.raises(InputError, match="harmonic 9"):
        odd_ratio(h0, harmonics=(3, 9))


@pytest.mark.parametrize("k_max", [0.2, 0.3, 0.5])
def test_ratio_minimizer_reaches_optimum(k_max):
    search = RatioMinimizer(0.0, k_max, xtol=1e-4)
    evaluations = 0
    best_after_8 = None
    while not search.done:
        k = search.ask()
        search.tell(k, odd_ratio(relay_with_offset_hosidf(k)))
        evaluations += 1
        if evaluations == 8:
            best_after_8 = search.result.k_fc
    res = search.result
    assert best_after_8 is not None or res.n_evaluations < 8
    best = best_after_8 if best_after_8 is not None else res.k_fc
    assert best == pytest.approx(FC, rel=0.01)          # within 1 % in <= 8 experiments
    assert res.converged and res.k_fc == pytest.approx(FC, rel=1e-3)
    assert res.uncertainty < 1e-3 and abs(res.k_fc - FC) <= res.uncertainty + 1e-12
    assert res.n_evaluations == len(res.history) <= 20


@pytest.mark.parametrize("k_max", [0.2, 0.3, 0.5])
def test_signed_root_search_reaches_optimum(k_max):
    phases = reference_phases(relay_with_offset_hosidf(0.0))
    res = SignedRootSearch(0.0, k_max, xtol=1e-6).run(
        lambda k: signed_odd_ratio(relay_with_offset_hosidf(k), phases))
    assert res.converged and res.n_evaluations <= 8
    assert res.k_fc == pytest.approx(FC, rel=0.01)
    assert res.uncertainty <= 1e-6 + 1e-12


def test_signed_search_on_nonlinear_objective_and_noise():
    # a signed objective that is not linear (cubic-ish around the root) still converges
    res = SignedRootSearch(0.0, 1.0, xtol=1e-5).run(lambda k: np.tanh(5 * (0.37 - k)) + 0.3 * (0.37 - k) ** 3)
    assert res.converged and res.k_fc == pytest.approx(0.37, rel=1e-3) and res.n_evaluations <= 10
    # noisy measurements: ftol = noise level stops early, estimate within a few noise widths
    rng = np.random.default_rng(0)
    noise = 0.002
    res = SignedRootSearch(0.0, 0.3, xtol=1e-6, ftol=2 * noise).run(
        lambda k: 2 * (FC - k) + noise * rng.standard_normal())
    assert res.k_fc == pytest.approx(FC, abs=0.01) and res.n_evaluations <= 8


def test_search_from_simulated_hosidf_measurements():
    """The whole chain: time-domain records -> hosidf -> objective -> search."""
    n, p = 1024, 2
    theta = 2 * np.pi * (np.arange(p * n) + 0.5) / n * 4          # bin 4
    u = A * np.sin(theta)
    rng = np.random.default_rng(1)

    def measure(k_fc):
        y = GAIN * u + (FC - k_fc) * np.sign(u) + 1e-5 * rng.standard_normal(u.size)
        return hosidf(u.reshape(1, 1, p, n), y.reshape(1, 1, p, n), fs=1000.0, n_harmonics=7).H[0]

    phases = reference_phases(measure(0.0))
    res = SignedRootSearch(0.0, 0.3, xtol=1e-5).run(lambda k: signed_odd_ratio(measure(k), phases))
    assert res.k_fc == pytest.approx(FC, rel=0.01) and res.n_evaluations <= 8
    res = RatioMinimizer(0.0, 0.3, xtol=1e-4, max_evaluations=12).run(lambda k: odd_ratio(measure(k)))
    assert res.k_fc == pytest.approx(FC, rel=0.02)


def test_no_sign_change_and_misuse():
    res = SignedRootSearch(0.0, 0.05).run(lambda k: FC - k)      # optimum beyond K_max
    assert not res.converged and "outside" in res.reason and res.k_fc == 0.05
    search = SignedRootSearch(0.0, 1.0)
    with pytest.raises(InputError, match="asked"):
        search.tell(0.5, 1.0)
    with pytest.raises(InputError, match="not finite"):
        search.tell(search.ask(), float("nan"))
    with pytest.raises(InputError, match="lower < upper"):
        RatioMinimizer(1.0, 0.0)
    capped = RatioMinimizer(0.0, 1.0, xtol=1e-9, max_evaluations=4).run(lambda k: abs(k - 0.3))
    assert capped.n_evaluations == 4 and not capped.converged and "max_evaluations" in capped.reason


def test_signed_ratio_std_matches_scatter():
    rng = np.random.default_rng(3)
    h_true = relay_with_offset_hosidf(0.08)
    phases = reference_phases(relay_with_offset_hosidf(0.0))
    sigma, repeats = 0.004, 5
    values, predicted = [], []
    for _ in range(400):
        noise = sigma * (rng.standard_normal((repeats, 7)) + 1j * rng.standard_normal((repeats, 7)))
        reps = h_true + noise
        H, H_std = reps.mean(0), np.sqrt(np.sum(np.abs(reps - reps.mean(0)) ** 2, 0) / (repeats - 1))
        values.append(signed_odd_ratio(H, phases))
        predicted.append(signed_odd_ratio_std(H, H_std, repeats))
    assert np.std(values) == pytest.approx(np.mean(predicted), rel=0.15)


# ---- KfcSearch: measured-data search (bracket, stick-slip fallback, sigma) -------------
from fftune.analysis.tuning import KfcSearch, harmonic_orders  # noqa: E402


def periods_of(h, noise=0.0, periods=4, rng=None):
    """(P, K) per-period HOSIDFs: ``h`` plus complex Gaussian noise of std ``noise``."""
    rng = rng or np.random.default_rng(0)
    w = noise * (rng.standard_normal((periods, h.size)) + 1j * rng.standard_normal((periods, h.size)))
    return h[None, :] + w / np.sqrt(2)


def test_harmonic_orders_is_the_one_level_definition():
    assert harmonic_orders(7) == (3, 5, 7)
    assert harmonic_orders(8, "even") == (2, 4, 6, 8)
    h = relay_with_offset_hosidf(0.0)
    assert odd_ratio(h, harmonic_orders(7)) == odd_ratio(h)
    with pytest.raises(InputError, match="no odd harmonic"):
        harmonic_orders(2)


def test_kfc_search_brackets_verifies_and_reports_sigma():
    rng = np.random.default_rng(5)
    res = KfcSearch(0.0, 0.3, max_experiments=8).run(
        lambda k: periods_of(relay_with_offset_hosidf(k), 1e-4, rng=rng))
    assert res.converged and res.regime == "signed root" and res.extended_to is None
    assert res.k_fc == pytest.approx(FC, rel=0.01)
    assert abs(res.k_fc - FC) <= 2 * res.sigma and 0 < res.sigma < 0.01 * FC
    assert res.n_experiments <= 6
    # the verification experiment is within the tolerance of K_fc*, and no measured point
    # has a smaller ratio by more than the noise
    k_ver = min((p.k_fc for p in res.points), key=lambda k: abs(k - res.k_fc))
    assert abs(k_ver - res.k_fc) <= max(3 * res.sigma, 0.005 * res.k_fc)
    r_ver = next(p.ratio for p in res.points if p.k_fc == k_ver)
    assert all(r_ver <= p.ratio + 1e-3 for p in res.points if abs(p.k_fc - res.k_fc) > 0.01 * FC)


def test_kfc_search_extends_a_too_small_bracket_and_says_so():
    res = KfcSearch(0.0, 0.05, k_limit=10.0).run(lambda k: periods_of(relay_with_offset_hosidf(k), 1e-5))
    assert res.converged and res.extended_to is not None and res.extended_to > FC
    assert res.k_fc == pytest.approx(FC, rel=0.01)


def test_kfc_search_at_the_drive_limit_says_why_instead_of_guessing():
    # the old root search returned the bracket end with its confident label
    res = KfcSearch(0.0, 0.05, k_limit=0.08).run(lambda k: periods_of(relay_with_offset_hosidf(k), 1e-5))
    assert not res.converged and np.isnan(res.sigma)
    assert "drive's limit" in res.reason and "amplitude" in res.reason


def rotating_hosidf(k_fc, fc=FC, turn_deg=270.0):
    """Stick-slip-like HOSIDFs: under-compensated the odd phases rotate with K_fc (by
    ``turn_deg`` between 0 and fc), over-compensated they are fixed; |H_k| ~ |fc - k_fc|."""
    h = relay_with_offset_hosidf(k_fc, fc=fc)
    if k_fc < fc:
        turn = np.radians(turn_deg) * (1 - k_fc / fc) ** 2
        for k in range(3, 8, 2):
            h[k - 1] = h[k - 1] * np.exp(1j * turn * k / 3)
    return h


def test_kfc_search_survives_phase_rotation_where_the_old_root_search_fails():
    # the old search: reference phases from H(0) - H(k_max), root assumed between
    phases = reference_phases(rotating_hosidf(0.0) - rotating_hosidf(0.3))
    s = [float(signed_odd_ratio(rotating_hosidf(k), phases)) for k in np.linspace(0, 0.3, 61)]
    assert np.sum(np.diff(np.sign(s)) != 0) >= 2          # s changes sign more than once
    rng = np.random.default_rng(2)
    res = KfcSearch(0.0, 0.3, max_experiments=10).run(
        lambda k: periods_of(rotating_hosidf(k), 1e-5, rng=rng))
    assert res.converged and res.k_fc == pytest.approx(FC, rel=0.02)


def test_kfc_search_ratio_minimiser_when_s_has_no_sign_change():
    # odd harmonics whose phase does not turn at the optimum (|H_k| ~ |fc - k_fc| at a fixed
    # phase): s never changes sign, only the ratio r shows the optimum
    def h(k):
        out = relay_with_offset_hosidf(k)
        for j in range(3, 8, 2):
            out[j - 1] = abs(out[j - 1]) * np.exp(0.7j * j)
        return periods_of(out, 1e-6)

    res = KfcSearch(0.0, 0.3, max_experiments=20).run(h)
    assert res.regime == "ratio minimiser" and "phases rotate" in res.reason
    assert res.converged and res.k_fc == pytest.approx(FC, rel=0.02)
    assert abs(res.k_fc - FC) <= max(2 * res.sigma, 0.02 * FC)


@pytest.mark.parametrize("turn_deg", [90, 180, 270, 360, 540])
@pytest.mark.parametrize("fc", [0.03, 0.1157, 0.25])
def test_kfc_search_over_a_family_of_rotating_phases_is_right_or_says_why(turn_deg, fc):
    rng = np.random.default_rng(int(turn_deg))
    res = KfcSearch(0.0, 0.3, max_experiments=12).run(
        lambda k: periods_of(rotating_hosidf(k, fc=fc, turn_deg=turn_deg), 1e-5, rng=rng))
    if res.converged:
        assert abs(res.k_fc - fc) <= max(0.02 * fc, 2 * res.sigma)
    else:
        assert "raise" in res.reason


def test_kfc_search_refuses_bad_input():
    with pytest.raises(InputError, match="0 <= lower < upper"):
        KfcSearch(0.0, 0.0)
    with pytest.raises(InputError, match="0 <= lower < upper"):
        KfcSearch(-0.1, 0.3)
    with pytest.raises(InputError, match="k_limit"):
        KfcSearch(0.0, 0.3, k_limit=0.2)
    search = KfcSearch(0.0, 0.3)
    with pytest.raises(InputError, match=">= 2 recorded periods"):
        search.tell(search.ask(), relay_with_offset_hosidf(0.3)[None, :])
    with pytest.raises(InputError, match="asked"):
        search.tell(0.123, periods_of(relay_with_offset_hosidf(0.3)))


def test_moment_standard_errors_match_monte_carlo():
    """tell_moments propagates one period's line variances to the standard errors of the
    ratio and of the signed objective; against the scatter of both over 4000 simulated
    experiments of P = 4 periods with circular Gaussian line noise."""
    from fftune.analysis.tuning import KfcSearch, reference_phases, signed_odd_ratio
    rng = np.random.default_rng(3)
    H = np.array([0.95 * np.exp(-0.3j), 0.02j, 0.04 * np.exp(1j), 0.01, 0.03 * np.exp(-2j),
                  0.005, 0.02 * np.exp(0.5j)])
    H_var = np.array([3e-3, 1e-6, 2e-5, 1e-6, 1e-5, 1e-6, 3e-5])   # |H_1| noise matters too
    P, n_mc = 4, 4000
    noise = (rng.standard_normal((n_mc, P, 7)) + 1j * rng.standard_normal((n_mc, P, 7))) * np.sqrt(H_var / 2)
    Hm = (H + noise).mean(axis=1)
    phases = reference_phases(H * np.exp(0.2j))
    search = KfcSearch(0.0, 1.0)
    k = search.ask()
    search.tell_moments(k, H, H_var, P)
    pt = search.points[k]
    r_mc = np.std(odd_ratio(Hm))
    s_mc = np.std(signed_odd_ratio(Hm, phases))
    _, s_se = search._signed([pt], phases)
    assert pt.ratio_std == pytest.approx(r_mc, rel=0.1)
    assert s_se[0] == pytest.approx(s_mc, rel=0.1)
    # and the per-period path on one such experiment gives a spread of the same size
    search2 = KfcSearch(0.0, 1.0)
    search2.tell(search2.ask(), H + noise[0])
    assert 0.2 < search2.points[k].ratio_std / pt.ratio_std < 5


def test_tell_moments_reaches_the_optimum_and_checks_its_input():
    from fftune.analysis.tuning import KfcSearch
    rng = np.random.default_rng(1)
    P, sd = 4, 2e-4
    search = KfcSearch(0.0, 1.0, max_experiments=12)
    while not search.done:
        k = search.ask()
        Hp = relay_with_offset_hosidf(k) + sd * (rng.standard_normal((P, 7)) + 1j * rng.standard_normal((P, 7)))
        d = Hp - Hp.mean(axis=0)
        search.tell_moments(k, Hp.mean(axis=0), np.sum(np.abs(d) ** 2, axis=0) / (P - 1), P)
    res = search.result
    assert res.converged, res.reason
    assert abs(res.k_fc - FC) <= max(3 * res.sigma, 0.01 * FC)
    s = KfcSearch(0.0, 1.0)
    k = s.ask()
    with pytest.raises(InputError, match="one shape"):
        s.tell_moments(k, np.ones(7), np.ones(6), 4)
    with pytest.raises(InputError, match=">= 2 recorded periods"):
        s.tell_moments(k, np.ones(7), np.ones(7), 1)
    with pytest.raises(InputError, match="not finite"):
        s.tell_moments(k, np.ones(7), -np.ones(7), 4)
