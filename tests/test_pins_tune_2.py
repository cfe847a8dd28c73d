"""Pins of tune's numbers, second set (issue 33's hand-written bug audit, docs/testing.md):
the uncertainty budget's parts composed by the search tune after a converged search, the
raw capture's harmonic lines with several sine cycles per period, the repeated
experiment's verdict, the amplitude step and the grid limits. Expected values are
computed here (explicit DFT sums, scipy.stats' t quantile, the documented formulas) from
unequal, asymmetric inputs. The strategy's helpers are driven with a stand-in probe (no
drive, no simulation): their contracts, not a bench's numbers."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from fftune.analysis import tune_strategy as ts
from fftune.analysis import tuning
from fftune.analysis.errors import FftuneError

HARM = (3, 5, 7)


def _t95(dof):
    """t_{0.9772, dof} / 2 through the incomplete beta function (not stdtrit, which the
    code uses): P(T > t) = I_x(dof / 2, 1 / 2) / 2 with x = dof / (dof + t^2)."""
    from scipy.special import betaincinv
    x = float(betaincinv(dof / 2.0, 0.5, 2.0 * (1.0 - 0.9772)))
    return math.sqrt(dof * (1.0 / x - 1.0)) / 2.0


def _periods(h1, s_per_period, phases, even=0.013):
    """Per-period HOSIDFs (P, 7) whose signed objective is s_p in period p: every odd
    harmonic i projects on its reference phase phi_i as s_p |H_1|, plus an orthogonal part
    that differs per harmonic (it must not count)."""
    P = len(s_per_period)
    H = np.zeros((P, 7), dtype=complex)
    H[:, 0] = h1
    for j, (i, phi) in enumerate(zip(HARM, phases)):
        ortho = (0.004 * (j + 1)) * 1j
        H[:, i - 1] = (np.asarray(s_per_period) * abs(h1) + ortho) * np.exp(1j * phi)
    H[:, 1] = even
    H[:, 3] = -0.5 * even
    return H


class _Probe:
    """The search tune's probe without a drive: ``measure`` hands back prepared points."""

    def __init__(self, amplitude, points, frequency_hz=1.25):
        self.amplitude = amplitude
        self.harmonics = HARM
        self.c = {"frequency_hz": frequency_hz}
        self.kv_search = 0.0
        self.points = points            # tag -> point
        self.asked = []

    def measure(self, tag, kfc, kv=0.0, amplitude=None, repeat=False):
        self.asked.append((tag, kfc, kv, amplitude, repeat))
        return self.points[tag]
        yield   # (a generator, as the real probe)

    def search_point(self, p):
        return ts._TuneProbe.search_point(self, p)


def _point(kfc, Hp, amplitude, noise=2e-4, kv=0.0):
    Hp = np.asarray(Hp)
    return {"kfc": float(np.float32(kfc)), "kv": kv, "amplitude": amplitude, "H": Hp.mean(axis=0),
            "H_periods": Hp, "H_var": None, "n_periods": Hp.shape[0],
            "ratio": float(tuning.odd_ratio(Hp.mean(axis=0), HARM)), "check": {"cause": None},
            "lines": None, "u_over_y": None, "angle_noise_rad": noise, "fc_smooth": None,
            "rms_error": 1e-3, "record": None}


def _run(gen):
    try:
        while True:
            next(gen)
    except StopIteration as stop:
        return stop.value


def test_budget_parts_after_a_converged_search_with_the_smaller_second_amplitude():
    a1, a2 = 0.5, 0.25                     # the auto choice's alternative: the smaller amplitude
    q = 2 * math.pi / 4096                 # detect.encoder_step_rad
    k1, sig1, slope, sigma_fit = 0.1187, 1.0e-3, -8.0, 4.0e-4
    phases = np.array([0.3, -1.1, 2.0])
    h1_star = 0.97 * np.exp(-1j * 0.015)   # lag 0.86 deg: below LAG_MIN_DEG, no K_v step
    h1_two = 0.95 * np.exp(-1j * 0.021)
    s_two = np.array([0.0015, 0.0027, 0.0018, 0.0020])
    p_star = _point(k1, _periods(h1_star, [1e-4, -2e-4, 3e-4], phases), a1, noise=2.0e-4)
    p_two = _point(k1, _periods(h1_two, s_two, phases), a2)
    probe = _Probe(a1, {"amplitude2": p_two})
    cfg = {"tune": {"frequency_hz": 1.25, "amplitude_max_rad": 0.5}, "detect": {"encoder_step_rad": q},
           "limits": {}}
    ctx = ts._Context(cfg, 2560.0, "raw", 5.0, {})
    outcome = tuning.KfcSearchResult(k_fc=k1, sigma=sig1, converged=True, reason="", n_experiments=5,
                                     bracket=(0.1, 0.14), extended_to=None, regime="signed root",
                                     sigma_signed=1e-3, slope=slope, phases=phases, sigma_fit=sigma_fit)
    out = _run(ts._budget(ctx, probe, outcome, {k1: p_star}, {"alternative_rad": a2}))
    assert out["cause"] is None, out["cause"]
    assert [a[0] for a in probe.asked] == ["amplitude2"] and probe.asked[0][3] == a2
    # the second amplitude's root along the search's slope scaled by A1 |H_1| / (A2 |H_1(A2)|)
    s2 = s_two.mean()
    se2 = s_two.std(ddof=1) / math.sqrt(s_two.size)
    slope2 = slope * a1 * abs(h1_star) / (a2 * abs(h1_two))
    k_a = float(np.float32(k1))
    k2 = k_a - s2 / slope2
    sigma2 = se2 / abs(slope2) * _t95(s_two.size - 1)
    assert out["k_fc_at_amplitude"]["k_fc"] == [pytest.approx(k1), pytest.approx(k2, rel=1e-9)]
    assert out["k_fc_at_amplitude"]["sigma_noise"][1] == pytest.approx(sigma2, rel=1e-6)
    # they agree within twice their noise: the inverse-variance mean, the difference the part
    assert abs(k2 - k1) < 2 * math.hypot(sig1, sigma2)
    w1, w2 = 1 / sig1 ** 2, 1 / sigma2 ** 2
    k_est = (w1 * k1 + w2 * k2) / (w1 + w2)
    parts = out["parts"]
    assert out["k_fc"] == pytest.approx(k_est, rel=1e-9)
    assert parts["noise"] == pytest.approx(1 / math.sqrt(w1 + w2), rel=1e-6)
    assert parts["amplitude"] == pytest.approx(abs(k2 - k1), rel=1e-6)
    # the encoder floor at the smaller amplitude, through the slope there (A1 / A2 steeper)
    ds = (q / a2) ** 1.5 / math.pi * math.exp(-2 * math.pi ** 2 * (2.0e-4 / q) ** 2)
    assert parts["encoder"] == pytest.approx(ds / abs(slope * a1 / a2), rel=1e-9)
    assert parts["flatness"] == pytest.approx(sigma_fit)
    lag = math.degrees(0.015)
    assert parts["loop_lag"] == pytest.approx(1.2e-3 * lag ** 2 * k_est, rel=1e-6)
    assert parts["viscous"] == 0.0 and parts["smoothed_sign"] == 0.0
    assert out["sigma_total"] == pytest.approx(math.sqrt(sum(v ** 2 for v in parts.values())), rel=1e-12)


def test_repeated_first_experiment_changed_only_beyond_three_noises():
    # H(0) - H(top) is real at every odd harmonic: the reference phases are 0 and s is the
    # per-period projection built in
    p0 = _point(0.0, _periods(0.9, [0.030, 0.031, 0.029, 0.0305], [0.0, 0.0, 0.0]), 0.5)
    top_s = np.array([-0.0200, -0.0212, -0.0191, -0.0205])
    first = _point(0.3, _periods(0.92, top_s, [0.0, 0.0, 0.0]), 0.5)
    se = top_s.std(ddof=1) / 2
    noise = math.hypot(se, se)              # a constant shift keeps the spread
    floor = 0.01 * abs(top_s.mean())
    for shift, changed in ((0.0, False), (2.0 * noise, False), (3.0 * noise + 0.8 * floor, False),
                           (3.0 * noise + 1.2 * floor, True), (-(3.0 * noise + 1.2 * floor), True)):
        rep = _point(0.3, _periods(0.92, top_s + shift, [0.0, 0.0, 0.0]), 0.5)
        probe = _Probe(0.5, {"repeat": rep})
        out = _run(ts._repeat_first(probe, {0.0: p0, 0.3: first}))
        assert probe.asked == [("repeat", 0.3, 0.0, 0.5, True)]
        assert out["s_then"] == pytest.approx(top_s.mean(), rel=1e-9)
        assert out["s_now"] == pytest.approx(top_s.mean() + shift, rel=1e-9)
        assert out["noise"] == pytest.approx(noise, rel=1e-9)
        assert out["changed"] is changed, shift / noise


def test_raw_capture_lines_at_k_times_the_cycles_and_the_per_period_checks():
    n, P, cyc, K = 512, 3, 4, 7
    fs = 512.0
    f = cyc * fs / n
    cfg = {"tune": {"period_samples": n, "frequency_hz": f, "harmonics": K, "amplitude_rad": 0.4,
                    "settle_periods": 1, "periods": P}, "_source": "t.yaml"}
    probe = ts._TuneProbe(ts._Context(cfg, fs, "raw", 5.0, {}))
    t = np.arange(P * n) / fs
    w = 2 * np.pi * f
    rng = np.random.default_rng(3)
    ref = 0.4 * np.sin(w * t)
    y = 0.37 * np.sin(w * t - 0.08) + 0.006 * np.sin(3 * w * t + 0.4) + 0.002 * np.sin(2 * w * t) \
        + 3e-4 * rng.standard_normal(t.size)
    u = 0.9 * np.sin(w * t + 0.3) + 0.2 * np.sign(np.cos(w * t - 0.08)) + 0.05 * np.sin(5 * w * t)
    u[17] = u[900] = 1.5                                   # two samples at u_max
    rec = SimpleNamespace(stats=None, signals={"reference": ref, "motor_angle": y, "plant_input": u,
                                               "error": ref - y})
    gen = probe.measure("search", 0.1, 0.0)
    req = next(gen)
    assert req.cycles == cyc and req.period_samples == n
    try:
        gen.send(ts.Measurement(rec, u_max_v=1.5))
    except StopIteration as stop:
        p = stop.value
    # the lines k = 1 .. K of the period mean, explicit DFT sums at k x cycles
    tt = np.arange(n)
    U_mean, Y_mean = u.reshape(P, n).mean(axis=0), y.reshape(P, n).mean(axis=0)
    for k in range(1, K + 1):
        e = np.exp(-2j * np.pi * k * cyc * tt / n)
        assert p["lines"][0][k - 1] == pytest.approx(np.sum(U_mean * e), rel=1e-9, abs=1e-9)
        assert p["lines"][1][k - 1] == pytest.approx(np.sum(Y_mean * e), rel=1e-9, abs=1e-9)
    assert p["check"]["saturated_fraction"] == pytest.approx(2 / (P * n))
    # the angle's spread over the periods: sum of squared deviations over (P - 1) N
    yp = y.reshape(P, n)
    assert p["angle_noise_rad"] == pytest.approx(
        math.sqrt(np.sum((yp - yp.mean(axis=0)) ** 2) / ((P - 1) * n)), rel=1e-12)
    assert p["rms_error"] == pytest.approx(math.sqrt(np.mean((ref - y) ** 2)), rel=1e-12)
    assert p["lag_deg"] == pytest.approx(math.degrees(0.08), rel=2e-2)


def test_std_over_periods_is_the_sample_standard_deviation():
    Hp = np.array([[1.0 + 0.1j, 0.02, 0.010j], [0.97 - 0.05j, 0.025, -0.004j],
                   [1.02 + 0.0j, 0.018, 0.007j], [0.99 + 0.02j, 0.021, 0.001j]])
    out = ts._std_over_periods([{"H": Hp.mean(axis=0), "H_periods": Hp},
                                {"H": Hp[0], "H_periods": None, "H_var": np.array([4e-4, 1e-6, 9e-6])}])
    d = Hp - Hp.mean(axis=0)
    expected = np.sqrt(np.sum(np.abs(d) ** 2, axis=0) / (len(Hp) - 1))
    assert out[0] == pytest.approx(expected, rel=1e-12)
    assert out[1] == pytest.approx([2e-2, 1e-3, 3e-3], rel=1e-12)


def test_next_auto_amplitude_steps():
    # out of stick-slip the ratio at K_fc = 0 falls as 1/A: the step aims at 0.8 of the limit
    r = ts.AUTO_AMPLITUDE_MAX_RATIO
    assert ts._next_amplitude(0.5, 0.9, 5.0 * 0.8 * r, 1e-4, 10.0) == pytest.approx(2.5)
    assert ts._next_amplitude(0.5, 0.9, 1.1 * r, 1e-4, 10.0) == pytest.approx(1.0)      # at least 2x
    assert ts._next_amplitude(0.5, 0.9, 100 * r, 1e-4, 10.0) == pytest.approx(4.0)      # at most 8x
    assert ts._next_amplitude(0.5, 0.3, 0.01, 1e-4, 10.0) == pytest.approx(2.0)         # stuck: 4x
    assert ts._next_amplitude(0.5, 0.9, 0.01, 0.05, 10.0) == pytest.approx(0.5 * 1.2 * 0.05 / 0.02)
    assert ts._next_amplitude(0.5, 0.9, 5.0 * 0.8 * r, 1e-4, 1.7) == pytest.approx(1.7)


def test_sine_on_the_grid_below_half_the_sample_rate():
    assert ts.cycles_on_grid(1000.0, 16, 437.5, "k") == 7
    with pytest.raises(FftuneError, match="above fs/2"):
        ts.cycles_on_grid(1000.0, 16, 500.0, "k")         # 8 cycles in 16 samples: fs/2 itself
    with pytest.raises(FftuneError, match="not on the DFT grid"):
        ts.cycles_on_grid(1000.0, 16, 440.0, "k")


def test_loop_lag_part_at_its_limit_and_drift_floor():
    assert tuning.loop_lag_part(7.0, 0.2) == pytest.approx(1.2e-3 * 49 * 0.2)
    assert math.isinf(tuning.loop_lag_part(math.nextafter(7.0, 8.0), 0.2))
    # a difference under the floor is no drift even beyond 3 sigma; over both, a drift
    assert tuning.drift_between(0.100, 0.108, 0.001, 0.002, floor=0.010) == (False, pytest.approx(0.008))
    assert tuning.drift_between(0.100, 0.1115, 0.001, 0.002, floor=0.010)[0] is True
    assert tuning.drift_between(0.100, 0.1070, 0.001, 0.002, floor=0.001)[0] is True   # 7 > 3 x 2.24 mV


# ---- second round: the limits of a larger sine, the model plan, the verdicts, the truth ----------

def test_a_larger_amplitude_within_the_velocity_limit():
    cfg = {"tune": {"frequency_hz": 1.25, "amplitude_max_rad": 2.0}, "limits": {"max_velocity_rad_s": 6.0}}
    ctx = ts._Context(cfg, 2560.0, "raw", 5.0, {})
    a_top = 6.0 / (2 * math.pi * 1.25)                    # 0.764 rad: the peak velocity 2 pi f A
    assert ts._amplitude_allowed(ctx, 0.999 * a_top)
    assert not ts._amplitude_allowed(ctx, 1.001 * a_top)
    cfg["limits"] = {"max_amplitude_rad": 1.5}
    assert ts._amplitude_allowed(ctx, 1.5) and not ts._amplitude_allowed(ctx, 1.51)
    cfg["limits"] = {}
    assert ts._amplitude_allowed(ctx, 2.0) and not ts._amplitude_allowed(ctx, 2.01)


def test_model_plan_doubles_up_to_the_largest_amplitude_reached():
    c = {"model": {"amplitude_rad": "auto", "verify_amplitude_rad": None}, "terms": ["coulomb"],
         "amplitude_rad": "auto", "amplitude_max_rad": 4.0}
    plan = ts.model_plan(c)
    assert plan["amplitude"] == 1.0 and plan["verify"] is None
    assert plan["checked"] == [("tune.model.amplitude_rad", 1.0), ("tune.amplitude_max_rad", 4.0)]
    c["amplitude_max_rad"] = 3.9
    assert ts.model_plan(c)["checked"][1] == ("tune.amplitude_max_rad", 2.0)
    c = dict(c, amplitude_rad=0.3, amplitude_max_rad=1.0)
    plan = ts.model_plan(c)
    assert plan["verify"] == 0.3 and plan["checked"] == [("tune.model.amplitude_rad", 1.0),
                                                        ("tune.amplitude_rad", 0.3)]


def test_amplitude_verdict_cases():
    v = ts.amplitude_verdict
    assert v(0.9, 0.02, 0.001, 0.001) == "pass"
    assert v(0.9, 0.048, 0.001, 0.001) == "near"           # the ratio within 25 % of its limit
    assert v(0.9, 0.07, 0.001, 0.001) == "fail"
    assert v(0.52, 0.02, 0.001, 0.001) == "near"           # |H_1| within 5 % of 0.5
    assert v(0.9, 0.02, 0.001, 0.016) == "fail"            # noise: the full margin below 2 %
    assert v(0.9, 0.02, 0.001, 0.0149) == "pass"
    # the ratio's band: 2 standard errors when wider than the margin
    assert v(0.9, 0.03, 0.011, 0.001) == "near"            # -40 % vs 2 x 0.011 / 0.05 = 44 %
    assert v(0.9, 0.03, 0.009, 0.001) == "pass"            # vs 36 %


def test_with_truth_is_the_error_against_the_end_value():
    r = ts.with_truth({"k_fc_star": 0.1207, "true_coulomb_v_at_start": None}, 0.100, 0.115)
    assert r["true_coulomb_v"] == 0.115 and r["true_coulomb_v_at_start"] == 0.100
    assert r["k_fc_star_error_re_truth"] == pytest.approx(0.1207 / 0.115 - 1)


def _search_point(k, s, ortho=0.0, phases=(0.4, -1.2, 2.2)):
    rng = np.random.default_rng(int(k * 1e6) % 997)
    H = np.zeros(7, dtype=complex)
    H[0] = 1.0
    for i, phi in zip(HARM, phases):
        H[i - 1] = (s + 1j * ortho) * np.exp(1j * phi)
    Hp = H[None, :] + 1e-8 * (rng.standard_normal((3, 7)) + 1j * rng.standard_normal((3, 7)))
    return tuning.make_point(k, H_periods=Hp)


def test_verified_by_a_sign_change_bracketed_within_four_tolerances():
    # s at the measured point nearest the root is beyond its noise (the secant through the
    # over-compensated points puts the root 0.2 mV from it), but the sign change is
    # bracketed within 4 tolerances (1.5 mV < 4 x 0.5 mV): verified, the bracket's width
    # over sqrt(12) a part of sigma
    k1, k2, k3 = 0.1000, 0.1015, 0.1030
    s1, s2 = 0.002, -0.001
    s3 = s2 - abs(s2) * (k3 - k2) / (k2 - (k1 + 0.0002))       # the secant's root at k1 + 0.2 mV
    search = tuning.KfcSearch(0.0, 0.2)
    search.points = {0.0: _search_point(0.0, 0.3), k1: _search_point(k1, s1),
                     k2: _search_point(k2, s2, ortho=0.003), k3: _search_point(k3, s3, ortho=0.003),
                     0.2: _search_point(0.2, -0.05)}
    out = search._estimate(0.0, 0.2)
    assert out["stop"], out
    res = out["result"]
    root = k2 - s2 * (k3 - k2) / (s3 - s2)
    assert res.converged and res.k_fc == pytest.approx(root, rel=1e-6)
    assert abs(s1) > abs((s2 - s1) / (k2 - k1)) * search._tol(root)      # s not zero within the noise
    assert res.sigma == pytest.approx(math.hypot(abs(k1 - root), (k2 - k1) / math.sqrt(12)), rel=1e-3)
    assert "bracketed" in res.reason


def test_motion_limit_itself_is_motion():
    assert tuning.check_experiment(tuning.MOTION_MIN_H1)["cause"] is None
    assert tuning.check_experiment(math.nextafter(tuning.MOTION_MIN_H1, 0.0))["cause"] == "no motion"
    ck = tuning.check_experiment(0.9, u_rms_re_max=0.9)                  # (0.81 - 0.64) / 0.36
    assert ck["saturated_fraction"] == pytest.approx(0.17 / 0.36) and ck["cause"] == "saturation"


def test_signed_ratio_std_of_unequal_harmonic_noises():
    # the mean of n projections, each of variance H_std_i^2 / (2 R): sqrt(sum H_std_i^2 / (2 R n^2))
    H = np.array([0.8 + 0.3j, 0.01, 0.05, 0.0, 0.02, 0.0, 0.007])
    H_std = np.array([0.01, 0.0, 0.004, 0.0, 0.011, 0.0, 0.0005])
    R = 5
    expected = math.sqrt((0.004 ** 2 + 0.011 ** 2 + 0.0005 ** 2) / (2 * R * 9)) / abs(H[0])
    assert tuning.signed_odd_ratio_std(H, H_std, R) == pytest.approx(expected, rel=1e-12)


def test_phases_and_slope_from_the_bracket_ends_in_the_ratio_minimiser_regime():
    phases = np.array([0.7, -0.2, 1.9])
    a, b = 0.08, 0.16
    pa = _point(a, _periods(0.9, [0.021, 0.019, 0.020], phases), 0.5)
    pb = _point(b, _periods(0.93, [-0.012, -0.010, -0.0115], phases), 0.5)
    outcome = tuning.KfcSearchResult(k_fc=0.12, sigma=np.nan, converged=True, reason="", n_experiments=5,
                                     bracket=(a, b), extended_to=None, regime="ratio minimiser",
                                     sigma_signed=np.nan, slope=np.nan, phases=None)
    got_phases, slope = ts._phases_and_slope(_Probe(0.5, {}), outcome, {a: pa, b: pb})
    assert np.angle(np.exp(1j * (got_phases - phases))) == pytest.approx(np.zeros(3), abs=1e-9)
    assert slope == pytest.approx((-0.0335 / 3 - 0.060 / 3) / (b - a), rel=1e-9)
    assert slope < 0


def test_auto_amplitude_raised_past_the_encoder_limit_with_a_margin():
    q = 0.002
    cfg = {"tune": {"frequency_hz": 1.25}, "detect": {"encoder_step_rad": q}, "limits": {}}
    ctx = ts._Context(cfg, 2560.0, "raw", 5.0, {})

    class Probe(_Probe):
        def measure(self, tag, kfc, kv=0.0, amplitude=None, repeat=False):
            self.asked.append(amplitude)
            H = _periods(0.9, [0.010, 0.0101, 0.0099], [0.0, 0.0, 0.0])
            p = _point(0.0, H, amplitude, noise=1e-5 * amplitude)
            p["check"] = tuning.check_experiment(0.9)
            p["record"] = SimpleNamespace(signals={})
            return p
            yield

    probe = Probe(None, {})
    probe.s = ctx
    a, block, _, stop = _run(ts.choose_amplitude(probe, 0.05, 10.0))
    # 0.05 rad: the step is 4 % of it (> 1 %): raised to 1.05 q / 1 % = 0.21 rad (more than
    # the ratio's 2x), where it is 0.95 %
    assert stop is None and probe.asked == [0.05, pytest.approx(0.21)]
    assert a == pytest.approx(0.21) and block["chosen_rad"] == pytest.approx(0.21)
    assert block["probes"][0]["verdict"] == "fail" and "encoder step" in block["probes"][0]["encoder_note"]


def _rigid_lines(b, n=4096, c=2, fs=2560.0):
    """A rigid motor (1.7e-3 V s^2/rad) with viscous ``b`` V s/rad and the relay 0.1157 V on a
    sine with a third harmonic: (f, w, U, Y) at the lines c, 2c, .. 7c of one period."""
    f = c * fs / n
    w = 2 * np.pi * f
    t = np.arange(n) / fs
    y = 0.45 * np.sin(w * t + 0.3) + 0.004 * np.sin(3 * w * t - 0.6)
    yd = 0.45 * w * np.cos(w * t + 0.3) + 0.012 * w * np.cos(3 * w * t - 0.6)
    ydd = -0.45 * w ** 2 * np.sin(w * t + 0.3) - 0.036 * w ** 2 * np.sin(3 * w * t - 0.6)
    u = 1.7e-3 * ydd + b * yd + 0.1157 * np.sign(0.45 * w * np.cos(w * t + 0.3))
    at = c * np.arange(1, 8)
    return f, w, np.fft.fft(u)[at], np.fft.fft(y)[at]


def test_budget_with_the_lag_correction_step():
    # the motor lags 2.9 deg at K_fc* and the plant's harmonics read K_v = 0.04 V s/rad:
    # one experiment with K_v in the loop (its root along the slope moves K_fc* by less
    # than 2 %: no second), half that step the viscous part, its noise added
    fs, n, c = 2560.0, 4096, 2
    f, w, U, Y = _rigid_lines(0.04, n, c, fs)
    kv = tuning.viscous_from_harmonics(U, Y, w, n, c)[0]
    assert kv == pytest.approx(0.04, rel=2e-3)
    a1, a2 = 0.5, 0.25
    k1, sig1, slope = 0.1187, 1.0e-3, -8.0
    phases = np.array([0.3, -1.1, 2.0])
    h1_star = 0.97 * np.exp(-1j * 0.05)
    p_star = _point(k1, _periods(h1_star, [1e-4, -2e-4, 3e-4], phases), a1, noise=1e-5)
    p_star["lines"] = (U, Y)
    s_lag = np.array([0.0010, 0.0012, 0.0009])
    p_lag = _point(k1, _periods(0.98 * np.exp(-1j * 0.01), s_lag, phases), a1, kv=kv)
    s_two = np.array([0.0015, 0.0027, 0.0018, 0.0020])
    h1_two = 0.95 * np.exp(-1j * 0.012)
    p_two = _point(k1, _periods(h1_two, s_two, phases), a2, kv=kv)
    probe = _Probe(a1, {"lag": p_lag, "amplitude2": p_two}, frequency_hz=f)
    probe.n, probe.cycles = n, c
    cfg = {"tune": {"frequency_hz": f, "amplitude_max_rad": 0.5}, "detect": {"encoder_step_rad": None},
           "limits": {}}
    cfg["detect"]["encoder_step_rad"] = 1e-9          # (an ideal encoder: a negligible part)
    ctx = ts._Context(cfg, fs, "raw", 5.0, {})
    outcome = tuning.KfcSearchResult(k_fc=k1, sigma=sig1, converged=True, reason="", n_experiments=5,
                                     bracket=(0.1, 0.14), extended_to=None, regime="signed root",
                                     sigma_signed=1e-3, slope=slope, phases=phases, sigma_fit=0.0)
    out = _run(ts._budget(ctx, probe, outcome, {k1: p_star}, {"alternative_rad": a2}))
    assert out["cause"] is None, out["cause"]
    k_new = float(np.float32(k1)) - s_lag.mean() / slope
    assert [(x[0], x[2]) for x in probe.asked] == [("lag", pytest.approx(kv)), ("amplitude2", pytest.approx(kv))]
    assert probe.asked[1][1] == pytest.approx(k_new, rel=1e-12)
    visc = out["viscous"]
    assert visc["applied"] and visc["lag_after_deg"] == pytest.approx(math.degrees(0.01))
    assert out["parts"]["viscous"] == pytest.approx(abs(k_new - k1) / 2, rel=1e-9)
    se_lag = s_lag.std(ddof=1) / math.sqrt(3)
    sig_noise = math.hypot(sig1, se_lag / abs(slope))
    assert out["k_fc_at_amplitude"]["sigma_noise"][0] == pytest.approx(sig_noise, rel=1e-9)
    assert out["k_fc_at_amplitude"]["k_fc"][0] == pytest.approx(k_new, rel=1e-12)
    assert out["parts"]["loop_lag"] == pytest.approx(1.2e-3 * math.degrees(0.01) ** 2 * out["k_fc"], rel=1e-6)
    assert out["k_v_in_search"] == pytest.approx(kv)


def test_budget_second_amplitude_secant_and_the_1_over_a_extrapolation():
    # at A2 = A1 / 2 the root along the scaled slope is 6.8 % away: one more experiment
    # there, the secant through both (its noise from both), then K_fc* differs at the two
    # amplitudes by more than twice the noise: extrapolated in 1/A
    a1, a2 = 0.5, 0.25
    k1, sig1, slope = 0.1187, 1.0e-3, -8.0
    phases = np.array([0.3, -1.1, 2.0])
    h1_star, h1_two = 0.97 * np.exp(-1j * 0.015), 0.95 * np.exp(-1j * 0.021)
    p_star = _point(k1, _periods(h1_star, [1e-4, -2e-4, 3e-4], phases), a1, noise=1e-5)
    s2 = np.array([0.128, 0.131, 0.1305, 0.1295])
    s3 = np.array([0.0102, 0.0097, 0.0105])
    p_two = _point(k1, _periods(h1_two, s2, phases), a2)
    slope2 = slope * a1 * abs(h1_star) / (a2 * abs(h1_two))
    k_a = float(np.float32(k1))
    k2_first = k_a - s2.mean() / slope2
    p_three = _point(k2_first, _periods(h1_two, s3, phases), a2)

    class Probe(_Probe):
        def measure(self, tag, kfc, kv=0.0, amplitude=None, repeat=False):
            self.asked.append((tag, kfc, kv, amplitude, repeat))
            return self.points[tag].pop(0)
            yield

    probe = Probe(a1, {"amplitude2": [p_two, p_three]})
    cfg = {"tune": {"frequency_hz": 1.25, "amplitude_max_rad": 0.5}, "detect": {"encoder_step_rad": 1e-9},
           "limits": {}}
    ctx = ts._Context(cfg, 2560.0, "raw", 5.0, {})
    outcome = tuning.KfcSearchResult(k_fc=k1, sigma=sig1, converged=True, reason="", n_experiments=5,
                                     bracket=(0.1, 0.14), extended_to=None, regime="signed root",
                                     sigma_signed=1e-3, slope=slope, phases=phases, sigma_fit=0.0)
    out = _run(ts._budget(ctx, probe, outcome, {k1: p_star}, {"alternative_rad": a2}))
    assert out["cause"] is None, out["cause"]
    assert abs(k2_first - k_a) > 0.05 * k_a
    assert probe.asked[1][1] == pytest.approx(k2_first, rel=1e-12)
    k_b = float(np.float32(k2_first))
    slope_m = (s3.mean() - s2.mean()) / (k_b - k_a)
    k2 = k_b - s3.mean() / slope_m
    se2, se3 = s2.std(ddof=1) / 2, s3.std(ddof=1) / math.sqrt(3)
    sigma2 = math.hypot(se3, se2) / abs(slope_m) * _t95(2)
    at = out["k_fc_at_amplitude"]
    assert at["secant_at_second"]["slope_measured"] == pytest.approx(slope_m, rel=1e-9)
    assert at["k_fc"][1] == pytest.approx(k2, rel=1e-9)
    assert at["sigma_noise"][1] == pytest.approx(sigma2, rel=1e-9)
    g = (1 / a1) / (1 / a1 - 1 / a2)
    k_inf = k1 + g * (k2 - k1)
    assert out["k_fc"] == pytest.approx(k_inf, rel=1e-9)
    assert out["parts"]["noise"] == pytest.approx(math.hypot((1 - g) * sig1, g * sigma2), rel=1e-9)
    assert out["parts"]["amplitude"] == pytest.approx(abs(k_inf - k1), rel=1e-9)
    assert out["repeat"] is None          # (no K_fc = 0 point to repeat against)


def test_unconverged_search_with_a_motor_that_moves_too_little_is_the_loops_lag():
    phases = np.array([0.3, -1.1, 2.0])
    outcome = SimpleNamespace(cause="not verified")
    for gain, cause in ((0.70, "loop lag"), (1.45, "loop lag"), (0.72, "not verified"), (1.38, "not verified")):
        h1 = gain * np.exp(-1j * np.radians(3.0))              # 3 deg: within the lag limit
        pts = {0.0: _point(0.0, _periods(h1, [0.03, 0.031, 0.029], phases), 0.5),
               0.2: _point(0.2, _periods(h1, [-0.02, -0.021, -0.019], phases), 0.5),
               0.11: _point(0.11, _periods(h1, [0.001, 0.0012, 0.0009], phases), 0.5)}
        for k, p in pts.items():
            p["lag_deg"] = 3.0
        probe = _Probe(0.5, {"repeat": pts[0.2]})
        got, text = _run(ts._diagnose_search(probe, outcome, pts, 0.0))
        assert got == cause, (gain, got)
        if cause == "loop lag":
            assert f"{gain:.3g} times the reference" in text
