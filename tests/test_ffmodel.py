"""fftune.analysis.ffmodel: the model-based tune of several friction feed-forward terms
(issue 35) on synthetic lines (the plant's inverse dynamics along a known motion, so the
truth is exact), the ask/tell flow, and the offline replay of recorded lines with the
analysis object alone (no drive)."""
import math

import numpy as np
import pytest

from fftune.analysis import ffmodel as fm
from fftune.analysis.errors import InputError

N = 2048
W = 2 * math.pi * 0.625          # rad/s
TRUTH = {"kfc": 0.137, "kfa": -0.029, "kv": 0.052, "kps": 0.061, "kpc": -0.023, "inertia": 0.0071}


def plant_input(y0, y1, truth=TRUTH, n=N, periods=1, noise=0.0, rng=None):
    """u over ``periods`` periods of the rigid plant per volt with every friction term, along
    the motion y = y0 + Re(y1 exp(j w t)) (its inverse dynamics, written out here
    independently of the module), and y itself (+ noise)."""
    t = np.arange(n * periods) / n * 2 * np.pi        # w t
    e = np.exp(1j * t)
    y = y0 + (y1 * e).real
    v = (1j * W * y1 * e).real
    a = (-(W ** 2) * y1 * e).real
    sg = np.sign(v)
    u = (truth["inertia"] * a + truth["kv"] * v + sg * (truth["kfc"] + truth["kps"] * np.sin(y) + truth["kpc"] * np.cos(y))
         + truth["kfa"] * np.abs(sg))
    if noise:
        u = u + noise * rng.standard_normal(u.size)
        y = y + noise * 0.01 * rng.standard_normal(y.size)
    return u, y


def test_harmonic_lines_conventions():
    t = np.arange(3 * 64) / 64 * 2 * np.pi
    x = 0.4 + 1.5 * np.cos(t) - 0.7 * np.sin(3 * t) + 0.2 * np.cos(2 * t + 0.3)
    X = fm.harmonic_lines(x, 64, 1, 5)
    assert X.shape == (3, 6)
    np.testing.assert_allclose(X[0], [0.4, 1.5, 0.2 * np.exp(0.3j), 0.7j, 0, 0], atol=1e-12)
    # cycles 2: the lines at bins 2k
    x2 = np.cos(2 * np.arange(64) / 64 * 2 * np.pi)
    np.testing.assert_allclose(fm.harmonic_lines(x2, 64, 2, 3)[0], [0, 1, 0, 0], atol=1e-12)
    with pytest.raises(InputError, match="whole periods"):
        fm.harmonic_lines(x[:100], 64, 1, 5)
    with pytest.raises(InputError, match="N/2"):
        fm.harmonic_lines(x, 64, 8, 5)


def test_estimate_terms_exact_on_the_inverse_dynamics():
    y1 = 1.7 * np.exp(-0.4j)
    u, y = plant_input(0.35, y1)
    U, Y = fm.harmonic_lines(u, N, 1, 8), fm.harmonic_lines(y, N, 1, 8)
    est = fm.estimate_terms(U, Y, omega_rad_s=W, terms=fm.TERMS, n_fit=7)
    for k, v in TRUTH.items():
        assert est["values"][k] == pytest.approx(v, rel=2e-3, abs=2e-5), k
    assert est["residual_rel"] < 1e-3
    # a subset: the inertia and the viscous term are always in the model
    u2, y2 = plant_input(0.35, y1, truth=dict(TRUTH, kfa=0.0, kps=0.0, kpc=0.0))
    est2 = fm.estimate_terms(fm.harmonic_lines(u2, N, 1, 8), fm.harmonic_lines(y2, N, 1, 8),
                             omega_rad_s=W, terms=["coulomb"], n_fit=5)
    assert set(est2["values"]) == {"kfc", "inertia", "kv"}
    assert est2["values"]["kfc"] == pytest.approx(TRUTH["kfc"], rel=2e-3)
    assert est2["values"]["kv"] == pytest.approx(TRUTH["kv"], rel=2e-3)
    # leaving present terms out of the model leaves them in the residual (the fit is one)
    est3 = fm.estimate_terms(U, Y, omega_rad_s=W, terms=["coulomb"], n_fit=7)
    assert est3["residual_rel"] > 20 * est["residual_rel"]


def test_estimate_terms_noise_from_the_periods():
    rng = np.random.default_rng(7)
    y1 = 1.2 * np.exp(0.3j)
    u, y = plant_input(-0.8, y1, periods=8, noise=0.02, rng=rng)
    U, Y = fm.harmonic_lines(u, N, 1, 8), fm.harmonic_lines(y, N, 1, 8)
    est = fm.estimate_terms(U, Y, omega_rad_s=W, terms=["coulomb", "asymmetry"], n_fit=5)
    for k in ("kfc", "kfa"):
        s = est["noise"][k]
        assert 0 < s < 0.01
    # the mean lines alone: the residual's standard error, also > 0
    est1 = fm.estimate_terms(U.mean(axis=0), Y.mean(axis=0), omega_rad_s=W, terms=["coulomb"], n_fit=5)
    assert est1["noise"]["kfc"] > 0


def test_estimate_terms_refuses_bad_input():
    U = np.ones(9, complex)
    with pytest.raises(InputError, match="unknown term"):
        fm.estimate_terms(U, U, omega_rad_s=W, terms=["stiction"])
    with pytest.raises(InputError, match="same shape"):
        fm.estimate_terms(U, U[:5], omega_rad_s=W, terms=["coulomb"])
    with pytest.raises(InputError, match="finite"):
        fm.estimate_terms(np.where(np.arange(9) == 2, np.nan, U), U, omega_rad_s=W, terms=["coulomb"])
    Y = U.copy()
    Y[1] = 0
    with pytest.raises(InputError, match="did not move"):
        fm.estimate_terms(U, Y, omega_rad_s=W, terms=["coulomb"])


def test_odd_even_ratios():
    Y = np.zeros(8, complex)
    Y[1], Y[3], Y[5], Y[7], Y[2], Y[4] = 2.0, 0.06j, -0.03, 0.0, 0.01, 0.02j
    odd, even = fm.odd_even_ratios(Y)
    assert odd == pytest.approx(math.sqrt((0.06 ** 2 + 0.03 ** 2) / 3) / 2.0)
    assert even == pytest.approx(math.sqrt((0.01 ** 2 + 0.02 ** 2) / 3) / 2.0)
    with pytest.raises(InputError, match="harmonic 7"):
        fm.odd_even_ratios(Y[:6])


class SyntheticLoop:
    """Stands in for the drive: the motion's amplitude and lag depend on how far the gains
    are from the truth (stick-slip without feed-forward), the lines are the plant's."""

    def __init__(self, truth=TRUTH, periods=2, noise=0.0, seed=3):
        self.truth, self.periods, self.noise = truth, periods, noise
        self.rng = np.random.default_rng(seed)
        self.runs = []

    def measure(self, exp):
        miss = sum(abs(exp.gains[k] - self.truth[k]) for k in fm.GAINS)
        y1 = exp.amplitude_rad * (0.97 - 0.5 * miss) * np.exp(-1j * (0.05 + 0.4 * miss))
        u, y = plant_input(0.2, y1, truth=self.truth, periods=self.periods, noise=self.noise, rng=self.rng)
        U, Y = fm.harmonic_lines(u, N, 1, 8), fm.harmonic_lines(y, N, 1, 8)
        self.runs.append((exp.amplitude_rad, dict(exp.gains), U, Y))
        return U, Y


def run_tune(loop, **kw):
    tuner = fm.FeedForwardModelTune(omega_rad_s=W, **kw)
    asked = []
    while not tuner.done:
        exp = tuner.ask()
        asked.append(exp)
        tuner.tell(exp, *loop.measure(exp))
    return tuner, asked


def test_ask_tell_all_terms_and_the_flow():
    loop = SyntheticLoop()
    tuner, asked = run_tune(loop, terms=["position", "coulomb", "asymmetry", "viscous"], amplitude_rad=3.0,
                            verify_amplitude_rad=0.4, n_fit=7)
    r = tuner.result
    assert r["converged"], r["reason"]
    # first without feed-forward at the identification amplitude, then at the estimate,
    # then half the amplitude at the final gains, then the verification amplitude
    assert asked[0].gains == {k: 0.0 for k in fm.GAINS} and asked[0].amplitude_rad == 3.0
    assert [e.tag for e in asked] == ["identify", "identify", "amplitude", "verify"]
    assert asked[2].amplitude_rad == 1.5 and asked[3].amplitude_rad == 0.4
    assert asked[3].gains == asked[2].gains == r["gains"]
    t = r["terms"]
    assert t["coulomb"]["value"] == pytest.approx(TRUTH["kfc"], rel=3e-3)
    assert t["asymmetry"]["value"] == pytest.approx(TRUTH["kfa"], rel=1e-2)
    assert t["viscous"]["value"] == pytest.approx(TRUTH["kv"], rel=3e-3)
    assert t["position"]["value"] == pytest.approx(math.hypot(TRUTH["kps"], TRUTH["kpc"]), rel=1e-2)
    assert t["position"]["sine_v"] == pytest.approx(TRUTH["kps"], rel=1e-2)
    assert t["position"]["cosine_v"] == pytest.approx(TRUTH["kpc"], rel=3e-2)
    assert t["coulomb"]["fc_plus_v"] == pytest.approx(TRUTH["kfc"] + TRUTH["kfa"], rel=5e-3)
    assert t["coulomb"]["fc_minus_v"] == pytest.approx(TRUTH["kfc"] - TRUTH["kfa"], rel=5e-3)
    assert t["viscous"]["unit"] == "V s/rad" and t["asymmetry"]["object"] == "0x2000:9"
    assert r["experiments"] == 4
    assert r["verification"]["amplitude_rad"] == 0.4


def test_ask_tell_coulomb_alone_three_experiments_and_refusals():
    truth = dict(TRUTH, kfa=0.0, kps=0.0, kpc=0.0)
    tuner, asked = run_tune(SyntheticLoop(truth=truth), terms=["coulomb"], amplitude_rad=1.0)
    r = tuner.result
    assert r["converged"] and r["experiments"] == 3
    assert r["terms"]["coulomb"]["value"] == pytest.approx(truth["kfc"], rel=2e-3)
    assert set(r["terms"]) == {"coulomb"}
    # the viscous feed-forward is applied while identifying (the motion follows the reference)
    assert asked[1].gains["kv"] == pytest.approx(truth["kv"], rel=1e-2)
    assert tuner.ask() is None
    with pytest.raises(InputError, match="not the experiment"):
        tuner.tell(asked[0], np.ones(9), np.ones(9))
    for bad in ([], ["coulomb", "coulomb"], ["stribeck"]):
        with pytest.raises(InputError, match="subset"):
            fm.FeedForwardModelTune(bad, omega_rad_s=W, amplitude_rad=1.0)


def test_a_failed_experiment_ends_unconverged_with_the_cause():
    tuner = fm.FeedForwardModelTune(["coulomb"], omega_rad_s=W, amplitude_rad=1.0)
    exp = tuner.ask()
    tuner.fail(exp, "saturation", "the drive output is at its limit")
    r = tuner.result
    assert tuner.done and not r["converged"] and r["cause"] == "saturation"
    assert "limit" in r["reason"] and r["experiments"] == 1 and r["terms"] == {}


def test_noise_sigma_covers_the_truth():
    truth = dict(TRUTH, kps=0.0, kpc=0.0)
    hits = 0
    for seed in range(6):
        loop = SyntheticLoop(truth=truth, noise=0.05, seed=seed, periods=4)
        tuner, _ = run_tune(loop, terms=["coulomb", "asymmetry", "viscous"], amplitude_rad=1.0)
        t = tuner.result["terms"]
        for name, key in (("coulomb", "kfc"), ("asymmetry", "kfa"), ("viscous", "kv")):
            assert t[name]["sigma"] > 0
            hits += abs(t[name]["value"] - truth[key]) <= 2 * t[name]["sigma"]
    assert hits >= 15          # of 18: a 2-sigma interval


def test_replay_from_recorded_lines_gives_the_same_result():
    """The offline replay (issue 35): the recorded lines of a tune, fed to a new object,
    give the same decisions and the same result, without a drive."""
    loop = SyntheticLoop(noise=0.01, periods=3)
    kw = dict(terms=["coulomb", "asymmetry", "viscous", "position"], omega_rad_s=W, amplitude_rad=3.0,
              verify_amplitude_rad=0.5)
    tuner, _ = run_tune(loop, **{k: v for k, v in kw.items() if k != "omega_rad_s"})
    again = fm.FeedForwardModelTune.replay(loop.runs, **kw)
    assert again.result == tuner.result
    # captures that are not what the tune asks for are refused, naming the capture
    bad = [(a, dict(g, kfc=g["kfc"] + 0.01) if i == 1 else g, U, Y) for i, (a, g, U, Y) in enumerate(loop.runs)]
    with pytest.raises(InputError, match="capture 1"):
        fm.FeedForwardModelTune.replay(bad, **kw)
    with pytest.raises(InputError, match="asks for more"):
        fm.FeedForwardModelTune.replay(loop.runs[:2], **kw)


def test_gauss_newton_step_recovers_a_known_mismatch():
    """Y_k = PS(k w) sum_i d_i Phi_i(k) for harmonics >= 2 and the mean (PS(0) = 1 / Kp),
    built from an independent PS (the loop's transfer written out) and the regressors'
    lines computed here by direct summation."""
    ctl = {"kp": 2.5, "kd": 0.07, "tau_d": 0.003}
    J, b = 0.0063, 0.041
    y0, y1 = 0.9, 2.2 * np.exp(0.7j)
    n = 4096
    t = np.arange(n) / n * 2 * np.pi
    y = y0 + (y1 * np.exp(1j * t)).real
    sg = np.sign((1j * y1 * np.exp(1j * t)).real)
    d = {"kfc": 0.013, "kfa": -0.004, "kps": 0.006, "kpc": -0.009}
    mis = d["kfc"] * sg + d["kfa"] * np.abs(sg) + sg * (d["kps"] * np.sin(y) + d["kpc"] * np.cos(y))
    M = np.fft.rfft(mis) / n
    Y = np.zeros(8, complex)
    for k in range(2, 8):
        s = 1j * W * k
        ps = 1.0 / (J * s * s + b * s + ctl["kp"] + ctl["kd"] * s / (ctl["tau_d"] * s + 1))
        Y[k] = ps * 2 * M[k]
    Y[1] = y1
    Y[0] = y0
    r0 = y0 - M[0].real / ctl["kp"]      # the mean: Y_0 - r0 = PS(0) M_0 = M_0 / Kp
    step = fm.gauss_newton_step(Y, r0, ["kfc", "kfa", "kps", "kpc", "kv"], J, b, ctl, W)
    assert set(step) == {"kfc", "kfa", "kps", "kpc"}
    for k, v in d.items():
        assert step[k] == pytest.approx(v, rel=0.05, abs=3e-4), k
    # without the reference's mean the asymmetry (a mean only) is not in the step's data
    step2 = fm.gauss_newton_step(Y, None, ["kfc"], J, b, ctl, W)
    assert step2["kfc"] == pytest.approx(d["kfc"], rel=0.1)


def test_linearisation_part_with_the_controller():
    loop = SyntheticLoop(truth=dict(TRUTH, kps=0.0, kpc=0.0))
    tuner, _ = run_tune(loop, terms=["coulomb", "asymmetry"], amplitude_rad=1.0,
                        controller={"kp": 2.0, "kd": 0.05, "tau_d": 0.002})
    parts = tuner.result["terms"]["coulomb"]["parts"]
    assert math.isfinite(parts["linearisation"]) and tuner.result["gauss_newton_step"] is not None
    with pytest.raises(InputError, match="kp"):
        fm.FeedForwardModelTune(["coulomb"], omega_rad_s=W, amplitude_rad=1.0, controller={"kp": 0.0})


class StickyLoop(SyntheticLoop):
    """Below 1.5 rad the motion carries a 3rd harmonic of 4 % (stick-slip the model lacks)."""

    def measure(self, exp):
        U, Y = super().measure(exp)
        if exp.amplitude_rad < 1.5:
            Y = Y.copy()
            Y[:, 3] += 0.04 * abs(Y[0, 1])
        return U, Y


def test_odd_harmonics_at_the_estimate_double_the_amplitude():
    truth = dict(TRUTH, kfa=0.0, kps=0.0, kpc=0.0)
    tuner, asked = run_tune(StickyLoop(truth=truth), terms=["coulomb"], amplitude_rad=1.0)
    amps = [e.amplitude_rad for e in asked]
    assert amps[:3] == [1.0, 1.0, 2.0] and asked[-1].tag == "amplitude" and amps[-1] == 1.0
    assert tuner.result["experiments"] == len(asked) <= 6
    # the half-amplitude experiment (1 rad) still shows them: its estimate moves, and that
    # part of sigma refuses the result
    assert not tuner.result["converged"] and tuner.result["cause"] == "uncertain"
    assert tuner.result["terms"]["coulomb"]["parts"]["amplitude"] > 0.1 * truth["kfc"]
    # no room to double: refused for the odd harmonics at the estimate, named
    tuner2, asked2 = run_tune(StickyLoop(truth=truth), terms=["coulomb"], amplitude_rad=1.0, amplitude_max_rad=1.0)
    assert {e.amplitude_rad for e in asked2} == {1.0, 0.5}
    r2 = tuner2.result
    assert not r2["converged"] and r2["cause"] == "model" and "raise tune.model.amplitude_rad" in r2["reason"]


def test_noise_from_line_variances_matches_the_per_period_spread():
    """Mean lines with their period-to-period variance (a drive's statistics) give about the
    noise the per-period estimates show on the same data."""
    rng = np.random.default_rng(11)
    u, y = plant_input(0.1, 1.1 * np.exp(0.2j), periods=40, noise=0.03, rng=rng)
    U, Y = fm.harmonic_lines(u, N, 1, 8), fm.harmonic_lines(y, N, 1, 8)
    per = fm.estimate_terms(U, Y, omega_rad_s=W, terms=["coulomb", "asymmetry"])
    var = np.sum(np.abs(U - U.mean(axis=0)) ** 2, axis=0) / (U.shape[0] - 1)
    var[0] = np.var(U[:, 0].real, ddof=1)
    prop = fm.estimate_terms(U.mean(axis=0), Y.mean(axis=0), omega_rad_s=W, terms=["coulomb", "asymmetry"],
                             line_var=var, n_periods=U.shape[0])
    for k in ("kfc", "kfa", "kv"):
        assert prop["noise"][k] == pytest.approx(per["noise"][k], rel=0.5), k
    # the residual's standard error (no variances told) is another number
    res = fm.estimate_terms(U.mean(axis=0), Y.mean(axis=0), omega_rad_s=W, terms=["coulomb", "asymmetry"])
    assert res["noise"]["kfc"] != prop["noise"]["kfc"]
