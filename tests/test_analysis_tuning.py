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
