"""Pins of the BLA's numbers, third set (issue 33's complete mutation run of analysis/bla.py,
docs/testing.md): expected values computed here from the documented definitions, with
unequal inputs, for what the earlier tests left free (defaults, float32 records, more than
256 excited lines, the input-drift note's figures)."""
import math
import sys

import numpy as np
import pytest

from fftune.analysis import bla
from fftune.analysis.bla import _drift_test, _false_alarm_count, _g_extrapolated2, robust_bla


def _odd_multisine_records(m=2, p=4, n=256, dtype=float, lines=None, seed=3, ramp=0.0):
    """Random-phase odd multisines (M realizations, P periods) through a short FIR filter,
    output noise; ``ramp`` per sample added to u (a slow input drift)."""
    rng = np.random.default_rng(seed)
    bins = np.arange(1, 60, 2) if lines is None else lines
    u = np.empty((m, p, n))
    for i in range(m):
        X = np.zeros(n // 2 + 1, complex)
        X[bins] = np.exp(2j * np.pi * rng.random(bins.size))
        u[i] = np.fft.irfft(X, n) * math.sqrt(n)
    flat = u.reshape(m, -1) + ramp * np.arange(p * n)
    y = 0.6 * flat + 0.3 * np.roll(flat, 1, axis=1) - 0.1 * np.roll(flat, 2, axis=1)
    y = y + 1e-3 * rng.standard_normal(y.shape)
    return flat.reshape(m, p, n).astype(dtype), y.reshape(m, p, n).astype(dtype), bins


def test_to_frd_without_python_control_says_how_to_install_it(monkeypatch):
    u, y, _ = _odd_multisine_records()
    res = robust_bla(u, y)
    monkeypatch.setitem(sys.modules, "control", None)         # import control fails
    with pytest.raises(ImportError, match=r"needs python-control.*pip install control"):
        res.to_frd()


def test_float32_records_find_the_same_excited_lines():
    # the float32 path of the excitation's power (as recorded by the drive) must index the
    # same lines as the float64 one: bin k at position k - 1 (the DC line left out)
    u, y, bins = _odd_multisine_records()
    r64 = robust_bla(u, y)
    r32 = robust_bla(u.astype(np.float32), y.astype(np.float32))
    assert np.array_equal(r64.bins, bins)
    assert np.array_equal(r32.bins, r64.bins) and np.array_equal(r32.freq, r64.freq)
    assert r32.G == pytest.approx(r64.G, rel=1e-4)


def test_transient_check_reads_256_lines_spread_over_a_wide_band():
    # "At most 256 lines spread over the band are used": with 300 excited lines the check's
    # level per period is that of lines linspace(0, 299, 256), computed here by hand
    rng = np.random.default_rng(11)
    m, periods, lines = 2, 6, 300
    Y = rng.standard_normal((m, periods, lines)) + 1j * rng.standard_normal((m, periods, lines))
    Y += 5.0                                                   # the steady state
    Y[:, 0, -1] += 40.0                                        # the first period differs at the top line
    check = bla._transient(Y, 0, periods)
    pick = np.linspace(0, lines - 1, 256).astype(np.int64)
    assert pick[0] == 0 and pick[-1] == lines - 1
    Z = Y[..., pick]
    centre = Z[:, periods - periods // 2:, :].mean(axis=1, keepdims=True)
    d = np.mean(np.sum(np.abs(Z - centre) ** 2, axis=2), axis=0) / 256
    ref = np.mean(np.abs(centre) ** 2)
    assert np.asarray(check.level_db) == pytest.approx(10 * np.log10(d / ref), rel=1e-9)


def _binomial_tails(n, p):
    """[P(Binomial(n, p) >= k) for k = 0 .. n]: each term in log space (lgamma), summed
    from the top (the small terms first)."""
    pmf = [math.exp(math.lgamma(n + 1) - math.lgamma(j + 1) - math.lgamma(n - j + 1)
                    + j * math.log(p) + (n - j) * math.log1p(-p)) for j in range(n + 1)]
    tails, acc = [0.0] * (n + 1), 0.0
    for k in range(n, -1, -1):
        acc += pmf[k]
        tails[k] = acc
    return tails


@pytest.mark.parametrize("n, p", [(5, 0.3), (40, 0.02), (200, 0.01), (1000, 0.2)])
def test_false_alarm_count_is_the_smallest_count_whose_tail_is_within_alpha(n, p):
    # "smallest count k >= 1 with P(Binomial(n, p) >= k) <= alpha", n + 1 where even all n
    # lines are more likely than alpha; against the exact sum, alpha down to 1e-30 (below
    # 1e-16, 1 - alpha is 1 in float64: the term-by-term cdf cannot tell it)
    tails = _binomial_tails(n, p)
    for alpha in (1e-3, 1e-8, 1e-12, 1e-20, 1e-30):
        k = next((k for k in range(1, n + 1) if tails[k] <= alpha), n + 1)
        assert _false_alarm_count(n, p, alpha=alpha) == k, alpha


def test_drift_test_default_limit_is_a_t_of_six():
    # a trend whose t is 5.5 is not reported with the default limit; one of 6.5 is
    base = np.array([0.3, -0.2, 0.25, -0.35, 0.1, -0.1, 0.05, -0.05])
    t_idx = np.arange(base.size) - (base.size - 1) / 2
    base = base - base.mean() - (base @ t_idx) / (t_idx @ t_idx) * t_idx   # no trend of its own
    se = math.sqrt(np.sum(base ** 2) / (base.size - 2) / np.sum(t_idx ** 2))
    for t_wanted, found in ((5.5, False), (6.5, True)):
        dc = (base + t_wanted * se * t_idx)[None, :]
        got = _drift_test(dc)
        assert (got is not None) is found
        if found:
            assert got[2] == pytest.approx(t_wanted, rel=1e-9)


def test_extrapolation_from_one_line_is_flat():
    # a single excited line: no slope to fit, |G|^2 above the band is that line's
    assert _g_extrapolated2(np.array([10.0]), np.array([2.0 + 1.0j]), np.array([20.0, 40.0])) \
        == pytest.approx([5.0, 5.0], rel=1e-12)


def test_input_drift_note_gives_the_mean_change_per_period_and_its_share_of_the_rms():
    # u drifts by a ramp of 2e-5 per sample: its mean moves 2e-5 x 256 per period, and over
    # the P kept periods by that times P, as a % of u's rms
    ramp, n, p = 2e-5, 256, 8
    u, y, _ = _odd_multisine_records(m=2, p=p, n=n, ramp=ramp, seed=5)
    res = robust_bla(u, y)
    per_period = ramp * n
    assert res.summary["input_drift_per_period"] == pytest.approx(per_period, rel=1e-3)
    note = next(s for s in res.notes if s.startswith("input u drifts"))
    assert f"{per_period:+.3g} per period" in note
    share = 100 * per_period * p / float(np.sqrt(np.mean(np.square(u))))
    assert f"{share:.2g} % of its rms" in note
    distorted = bool(res.summary.get("excitation_distorted"))
    assert ("the 'distorted' figures of u above count it" in note) is distorted


def test_mimo_frequencies_default_to_cycles_per_sample():
    # fs defaults to 1: the frequency axis is k / N
    rng = np.random.default_rng(2)
    n, p, nu, blocks = 128, 3, 2, 2
    bins = np.arange(1, 40, 2)
    u = np.empty((blocks * nu, p, n, nu))
    for e in range(blocks * nu):
        for i in range(nu):
            X = np.zeros(n // 2 + 1, complex)
            X[bins] = np.exp(2j * np.pi * rng.random(bins.size))
            u[e, :, :, i] = np.fft.irfft(X, n)
    y = np.stack([u[..., 0] + 0.5 * u[..., 1], 0.2 * u[..., 0] - u[..., 1]], axis=-1)
    y = y + 1e-6 * rng.standard_normal(y.shape)
    res = bla.robust_bla_mimo(u, y)
    assert np.asarray(res.freq) == pytest.approx(bins / n, rel=1e-12)
    # fs and the rest are keyword-only (as in robust_bla): a positional 2.0 is refused, not
    # taken silently as the sampling frequency
    with pytest.raises(TypeError):
        bla.robust_bla_mimo(u, y, 2.0)
    # a late start (the first period empty) is refused, the check's own finding named
    late_u = np.concatenate([np.zeros((blocks * nu, 1, n, nu)), u], axis=1)
    late_y = np.concatenate([np.zeros((blocks * nu, 1, n, 2)), y], axis=1)
    from fftune.analysis.checks import check_blocks
    first = check_blocks(late_u[..., 0], name="input 0", fs=1.0, infer=False, mixed_levels="note").notes[0]
    with pytest.raises(bla.InputError) as info:
        bla.robust_bla_mimo(late_u, late_y)
    assert str(info.value) == (f"MIMO BLA: {first}: every experiment must hold the same periods; "
                               f"cut the records to the excited periods")


@pytest.mark.parametrize("top, detected", [(7.5, False), (8.5, True)])
def test_a_line_counts_alone_only_beyond_eight_times_the_known_quantisation_part(top, detected):
    # the reference holds a known (model) part, the quantisation error: the strongest line's
    # probability is that of its excess over known_margin (8) times it, relative to the
    # noise part; one line at 8.5 x known (noise 1 % of known) is a detection by itself,
    # one at 7.5 x known is not tested (its count alone, 1 of 5, is not enough either)
    known = np.full(5, 1.0)
    reference = known + 0.01
    level = np.array([0.5, 0.6, 0.4, 0.5, top])
    out = bla._class_stats(level, reference, 10, "x_", known=known)
    assert out["x_lines_over_noise_6db"] == 1 and out["x_lines_needed"] >= 2
    assert out["x_detected"] is detected


def test_a_late_start_is_cut_from_the_reference_too():
    # the closed loop of tests/test_analysis_bla.py with a late start (the first period of
    # every record empty): the layout drops it from u, y and r alike, and the estimate still
    # uses the known reference (the plant, not the closed loop)
    from scipy import signal

    from test_analysis_bla import A, B, closed_loop_records
    m, n = 6, 512
    u, y, r, _ = closed_loop_records(m, n=n)
    late = [np.concatenate([np.zeros((m, 1, n)), x], axis=1) for x in (u, y, r)]
    res = robust_bla(*late, fs=1.0)
    assert any("start" in note for note in res.notes), res.notes
    assert res.known_reference
    _, g_plant = signal.freqz(B, A, worN=2 * np.pi * res.bins / n)
    assert np.median(np.abs(res.G - g_plant) / np.abs(g_plant)) < 0.02
