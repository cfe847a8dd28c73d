"""Pins of the search tune's messages and decisions, third set (issue 33, the mutation run's
survivors of fftune.analysis.tune_strategy): the figures of the unsettled, noise and
smoothed-sign diagnoses, the auto amplitude's end at its ceiling, the sweep's zero crossing,
the repeat the search's noise brings, the viscous minimiser's fallback to K_v = 0, and the
model tune's statistics path against the raw samples of the same signal.

No drive and no simulation: the tunes run on a synthetic plant (``_Plant``: a sine whose odd
harmonics are linear in Fc - K_fc, so the root is Fc exactly, plus a chosen period-to-period
spread kept off the harmonic lines), the helpers on test_pins_tune_2's stand-in probe. Every
expected figure is computed here from the inputs (the documented formula, or a reference)."""
import math
import os
import re
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from fftune.analysis import ffmodel
from fftune.analysis import stats as fstats
from fftune.analysis import tune_strategy as ts
from fftune.analysis import tuning

sys.path.insert(0, os.path.dirname(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "bench"))
import bench_tune  # noqa: E402
from test_pins_tune_2 import _Probe, _periods, _point, _rigid_lines, _run, _t95  # noqa: E402
from test_tune_honest import _sat_cos_coefficient  # noqa: E402

FS = 2560.0
ODD = ((3, 0.4), (5, -0.9), (7, 1.7))       # (order, phase) of the plant's odd harmonics


class _Plant:
    """A closed loop that follows the sine with gain ``gain(A)`` and lag ``lag_deg(request)``, plus
    odd harmonics of ``h_scale`` (Fc - K_fc) rad (the relay's 4 / (k pi) pattern) and, per
    experiment, a period-to-period deviation of rms ``spread(request)`` rad (white, or with
    ``ring`` the share of one non-harmonic line) with the harmonic lines cut out of it, so the
    HOSIDFs stay exact. ``records``: the record of each request key."""

    def __init__(self, fc=0.1157, gain=lambda a: 0.98, lag_deg=lambda req: 0.6, spread=lambda req: 0.0,
                 ring=0.0, h_scale=0.02, error_gain=lambda kv: 1.0):
        self.fc, self.gain, self.lag_deg, self.spread, self.ring = fc, gain, lag_deg, spread, ring
        self.h_scale, self.error_gain = h_scale, error_gain
        self.records = {}

    def __call__(self, req):
        n, P, c = req.period_samples, req.periods, req.cycles
        w = 2 * np.pi * req.frequency_hz
        t = np.arange(P * n) / FS
        a, kfc, kv = req.amplitude_rad, req.gains["kfc"], req.gains["kv"]
        ref = a * np.sin(w * t)
        lag = math.radians(self.lag_deg(req))
        y = a * self.gain(a) * np.sin(w * t - lag)
        for k, phi in ODD:
            y = y + self.h_scale * 4 / (k * math.pi) * (self.fc - kfc) * np.sin(k * (w * t - lag) + phi)
        rng = np.random.default_rng([7, int(round(kfc * 1e7)), int(round(a * 1e4))])     # (the same at any K_v)
        y = y + 1e-7 * rng.standard_normal(y.size)
        target = self.spread(req)
        if target:
            d = rng.standard_normal((P, n))
            d -= d.mean(axis=0)
            if self.ring:           # that share of the power at one line (bin 37)
                line = np.sin(2 * np.pi * 37 * np.arange(n) / n + rng.uniform(0, 2 * np.pi, (P, 1)))
                line -= line.mean(axis=0)
                d = math.sqrt(1 - self.ring) * d / np.std(d) + math.sqrt(self.ring) * line / np.std(line)
            D = np.fft.rfft(d, axis=1)
            D[:, c * np.arange(1, 8)] = 0.0
            d = np.fft.irfft(D, n, axis=1)
            d *= target / math.sqrt(np.sum(d ** 2) / ((P - 1) * n))
            y = y + d.reshape(-1)
        err = self.error_gain(kv) * (ref - y)
        rec = SimpleNamespace(stats=None, signals={"reference": ref, "motor_angle": y, "error": err},
                              parameters={})
        self.records[req.key] = rec
        return ts.Measurement(rec)


def _tune(plant, tune_over):
    """results['tune'] of a search tune (no frequency halving) on ``plant``."""
    cfg = bench_tune.tune_config(tune_over)
    cfg["detect"]["encoder_step_rad"] = 1e-9          # an ideal encoder: no encoder part
    strategy = ts.SearchTune(cfg, fs_hz=FS, k_fc_limit_v=2.0, capture="raw", max_halvings=0)
    results, _ = ts.replay(strategy, plant)
    return results


def _spread_rad(rec, n):
    """The angle's spread over the recorded periods: sum of squared deviations from the
    period mean over (P - 1) N."""
    yp = np.asarray(rec.signals["motor_angle"]).reshape(-1, n)
    return math.sqrt(np.sum((yp - yp.mean(axis=0)) ** 2) / ((yp.shape[0] - 1) * n))


def _top_share(rec, n):
    """The share of the period deviation's power in its strongest 1 % of DFT bins (no DC)."""
    yp = np.asarray(rec.signals["motor_angle"]).reshape(-1, n)
    dev = yp - yp.mean(axis=0)
    pw = np.zeros(n // 2)
    for row in dev:
        X = np.fft.fft(row)
        pw += np.abs(X[1:n // 2 + 1]) ** 2
    top = np.sort(pw)[::-1][:max(1, int(round(0.01 * pw.size)))]
    return float(top.sum() / pw.sum())


def _zero_record(plant, amplitude):
    """The record of the K_fc = 0, K_v = 0 experiment at ``amplitude`` (its key carries the
    amplitude when it is not the configured one)."""
    found = []
    for key, rec in plant.records.items():
        m = re.fullmatch(r"tune-[a-z0-9]+-kfc0-kv0(?:-a([0-9.]+))?", key)
        if m and (m.group(1) is None or float(m.group(1)) == amplitude):
            found.append(rec)
    assert len(found) == 1, list(plant.records)
    return found[0]


# ---- the angle-noise check after a converged search: its figures, white against motion ----------

@pytest.mark.parametrize("share, shown", [(0.0494, "4.9"), (0.0496, "5")])
def test_white_spread_above_two_percent_is_named_noise_with_its_measured_share(share, shown):
    # 4.94 (4.96) % of 0.5 rad at K_fc = 0, more in the search's experiments (the lower is read)
    plant = _Plant(spread=lambda r: share * r.amplitude_rad * (1 + r.gains["kfc"]))
    t = _tune(plant, {"amplitude_rad": 0.5})
    s = t["search"]
    assert not s["converged"] and s["cause"] == "noise"
    noise = _spread_rad(_zero_record(plant, 0.5), 4096)
    assert noise == pytest.approx(share * 0.5, rel=1e-3)
    assert s["stop_reason"].startswith(
        f"the angle noise ({noise:.2g} rad, spread over the recorded periods) is {100 * noise / 0.5:.2g} % of "
        f"the sine amplitude 0.5 rad: it dithers the friction")
    assert f"{100 * noise / 0.5:.2g}" == shown
    assert f"raise tune.amplitude_rad to >= {noise / 0.02:.2g} rad or set it to auto" in s["stop_reason"]
    assert "settle_periods" not in s["stop_reason"]     # (the hint of the statistics' reading)


@pytest.mark.parametrize("ring, cause", [(0.0, "noise"), (0.45, "noise"), (0.55, "unsettled"), (0.6, "unsettled"),
                                         (0.9, "unsettled")])
def test_spread_concentrated_in_a_few_lines_is_motion_above_half_its_power(ring, cause):
    # the same 3 % spread, white or more and more at one line: the share of its power in 1 %
    # of the frequencies decides (SPREAD_MAX_SHARE 0.5), the share named is the measured one
    plant = _Plant(spread=lambda r: 0.03 * r.amplitude_rad * (1 + r.gains["kfc"]), ring=ring)
    s = _tune(plant, {"amplitude_rad": 0.5})["search"]
    rec = _zero_record(plant, 0.5)
    share = _top_share(rec, 4096)
    assert (share > 0.5) == (cause == "unsettled"), share
    assert not s["converged"] and s["cause"] == cause
    noise = _spread_rad(rec, 4096)
    if cause == "unsettled":
        assert s["stop_reason"].startswith(
            f"the motor angle differs between the recorded periods by {noise:.2g} rad at 0.5 rad: not "
            f"measurement noise (its spectrum is not flat: {100 * share:.0f} % of its power in 1 % of the "
            "frequencies) but a loop that has not settled or does not repeat (near its resonance?); raise "
            "tune.settle_periods or lower tune.frequency_hz (the angle noise (")
        assert s["stop_reason"].endswith("or set it to auto)")
    else:
        assert s["stop_reason"].startswith(f"the angle noise ({noise:.2g} rad, spread over")


@pytest.mark.parametrize("share, cause", [(0.5, "noise"), (math.nextafter(0.5, 1.0), "unsettled")])
def test_spread_share_of_exactly_one_half_is_still_white(monkeypatch, share, cause):
    # the limit itself is white: "above which it is motion at a few frequencies"
    monkeypatch.setattr(ts, "spread_concentration", lambda y, top=0.01: share)
    plant = _Plant(spread=lambda r: 0.03 * r.amplitude_rad * (1 + r.gains["kfc"]))
    assert _tune(plant, {"amplitude_rad": 0.5})["search"]["cause"] == cause


def _auto_plant(n_small):
    """Auto amplitude from 0.25 rad (|H_1| 0.45: raised 4x, capped at 0.5 rad, where the
    spread is 2.5 % of the amplitude); ``n_small`` rad of spread at 0.25 rad."""
    return _Plant(gain=lambda a: 0.45 if a < 0.3 else 0.98,
                  spread=lambda r: (n_small if r.amplitude_rad < 0.3 else 0.0125) * (1 + r.gains["kfc"]))


def test_spread_that_grew_with_the_amplitude_is_unsettled_naming_both():
    plant = _auto_plant(0.001)
    t = _tune(plant, {"amplitude_start_rad": 0.25, "amplitude_max_rad": 0.5})
    s = t["search"]
    assert [p["amplitude_rad"] for p in t["amplitude"]["probes"]] == [0.25, 0.5]
    n_lo, n_hi = _spread_rad(_zero_record(plant, 0.25), 4096), _spread_rad(_zero_record(plant, 0.5), 4096)
    assert n_hi > 2 * n_lo
    assert not s["converged"] and s["cause"] == "unsettled"
    assert s["stop_reason"].startswith(
        f"the motor angle differs between the recorded periods by {n_hi:.2g} rad at 0.5 rad and {n_lo:.2g} rad "
        "at 0.25 rad: not measurement noise (it grows with the amplitude) but a loop that has not settled")


@pytest.mark.parametrize("growth, cause", [(2.2, "unsettled"), (1.8, "noise")])
def test_spread_growth_over_the_auto_probes_both_sides_of_twice(growth, cause):
    # 12.5 mrad at 0.5 rad against 12.5 / growth mrad at 0.25 rad: UNSETTLED_SPREAD_GROWTH 2
    plant = _auto_plant(0.0125 / growth)
    t = _tune(plant, {"amplitude_start_rad": 0.25, "amplitude_max_rad": 0.5})
    n_lo, n_hi = _spread_rad(_zero_record(plant, 0.25), 4096), _spread_rad(_zero_record(plant, 0.5), 4096)
    assert n_hi / n_lo == pytest.approx(growth, rel=1e-3)
    assert t["search"]["cause"] == cause


def test_spread_the_same_in_rad_at_both_amplitudes_is_noise():
    # 8 mV .. 12.5 mrad: it did not double from 0.25 to 0.5 rad: measurement noise
    plant = _auto_plant(0.008)
    t = _tune(plant, {"amplitude_start_rad": 0.25, "amplitude_max_rad": 0.5})
    n_lo, n_hi = _spread_rad(_zero_record(plant, 0.25), 4096), _spread_rad(_zero_record(plant, 0.5), 4096)
    assert n_lo < n_hi <= 2 * n_lo
    assert t["search"]["cause"] == "noise" and t["search"]["stop_reason"].startswith(f"the angle noise ({n_hi:.2g}")


# ---- the auto amplitude: a spread that grows with it, stick-slip up to the ceiling -----------------

def _choose(plant, start, max_rad, h_scale, q=1e-9):
    cfg = bench_tune.tune_config({})
    cfg["detect"]["encoder_step_rad"] = q
    probe = ts._TuneProbe(ts._Context(cfg, FS, "raw", 2.0, {}))
    plant.h_scale = h_scale
    asked = []
    gen = ts.choose_amplitude(probe, start, max_rad)
    try:
        req = next(gen)
        while True:
            asked.append(req.amplitude_rad)
            req = gen.send(plant(req))
    except StopIteration as stop:
        return asked, stop.value


def _odd_ratio_at_zero(fc, h_scale, amplitude, gain):
    """rms of the relay's odd harmonics h_scale 4 fc / (k pi), k = 3, 5, 7, over the fundamental."""
    return h_scale * 4 * fc / math.pi * math.sqrt(np.mean([1 / k ** 2 for k, _ in ODD])) / (amplitude * gain)


@pytest.mark.parametrize("shares", [{0.05: 0.010, 0.2: 0.00244, 0.5: 0.0324},
                                    {0.05: 0.010, 0.2: 0.00246, 0.5: 0.0326}])
def test_auto_amplitude_stops_when_the_spread_grows_with_it_naming_both_shares(shares):
    # 0.05 rad: |H_1| 0.45 (4x); 0.2 rad: ratio 0.1 (2.5x); 0.5 rad: the spread 3.24 (3.26) % of
    # it, 16 mrad against 0.5 mrad at 0.2 rad: not noise (the shares on either side of rounding)
    plant = _Plant(gain=lambda a: 0.45 if a < 0.1 else 0.9,
                   spread=lambda r: shares[round(r.amplitude_rad, 6)] * r.amplitude_rad)
    h_scale = 0.1 * 0.2 * 0.9 / _odd_ratio_at_zero(0.1157, 1.0, 1.0, 1.0)
    asked, (a, block, p, stop) = _choose(plant, 0.05, 2.0, h_scale)
    assert asked == [0.05, pytest.approx(0.2), pytest.approx(0.5)]
    assert block["probes"][1]["ratio_at_zero"] == pytest.approx(0.1, rel=1e-3)
    measured = {}
    for key, rec in plant.records.items():
        amp = float(re.search(r"-a([\d.]+)$", key).group(1))
        measured[amp] = _spread_rad(rec, 4096) / amp
    assert measured == {k: pytest.approx(v, rel=1e-3) for k, v in shares.items()}
    assert stop["cause"] == "unsettled" and a == pytest.approx(0.5)
    assert stop["text"].startswith(
        f"the motor angle differs between the recorded periods by {100 * measured[0.5]:.2g} % of the amplitude "
        f"at 0.5 rad and {100 * measured[0.2]:.2g} % at 0.2 rad: not measurement noise (it grows with the "
        "amplitude)")
    assert block["reason"] == f"stopped: {stop['text']}"


def test_auto_amplitude_in_stick_slip_ends_at_its_ceiling_after_one_probe_there():
    # |H_1| 0.3, 0.38, 0.45 (below 0.5): 4x each time, 0.05 -> 0.2 -> 0.8 rad (the ceiling): the
    # probe there is the last, and the reason names its |H_1| and ratio
    plant = _Plant(gain=lambda a: 0.3 if a < 0.1 else 0.38 if a < 0.5 else 0.45,
                   spread=lambda r: 1e-3 * r.amplitude_rad)
    h_scale = 0.6
    asked, (a, block, p, stop) = _choose(plant, 0.05, 0.8, h_scale)
    assert asked == [0.05, pytest.approx(0.2), pytest.approx(0.8)]
    assert stop is None and a == pytest.approx(0.8) and len(block["probes"]) == 3
    ratios = [q["ratio_at_zero"] for q in block["probes"]]
    assert ratios == [pytest.approx(_odd_ratio_at_zero(0.1157, h_scale, x, g), rel=1e-3)
                      for x, g in ((0.05, 0.3), (0.2, 0.38), (0.8, 0.45))]
    assert min(ratios) > ts.AUTO_AMPLITUDE_MAX_RATIO
    assert block["reason"] == (
        f"stick-slip at every amplitude up to tune.amplitude_max_rad = 0.8 rad (|H_1| = "
        f"{block['probes'][2]['h1']:.3g}, ratio at K_fc = 0 {ratios[2]}); the search runs there and may rely on "
        "the ratio minimiser: raise tune.amplitude_max_rad if the set-up allows")
    assert f"{block['probes'][2]['h1']:.3g}" == "0.45"


# ---- the paper's sweep: the zero crossing next to the ratio minimum ------------------------------

def test_sweep_optimum_interpolates_the_crossing_next_to_the_minimum():
    k = np.array([0.0, 0.05, 0.1, 0.15, 0.2, 0.3])
    # the crossing after the minimum (between 0.1 and 0.15)
    s = np.array([0.5, 0.3, 0.07, -0.13, -0.3, -0.6])
    k_opt, note = ts.sweep_optimum(k, np.abs(s) + 0.01, s)
    assert k_opt == pytest.approx(0.1 + 0.05 * 0.07 / (0.07 + 0.13), rel=1e-12)
    assert note == "zero crossing of the signed objective next to the ratio minimum"
    # the crossing before it (between 0.05 and 0.1): 0.2 -> -0.05
    s = np.array([0.4, 0.2, -0.05, -0.21, -0.3, -0.6])
    assert ts.sweep_optimum(k, np.abs(s) + 0.01, s)[0] == pytest.approx(0.05 + 0.05 * 0.2 / 0.25, rel=1e-12)
    # the smallest ratio at K_fc = 0 itself: the crossing after it
    s = np.array([0.01, -0.3, -0.5, -0.6, -0.7, -0.8])
    assert ts.sweep_optimum(k, np.abs(s), s)[0] == pytest.approx(0.05 * 0.01 / 0.31, rel=1e-12)
    # no sign change there: the grid minimum
    s = np.array([0.5, 0.3, 0.07, 0.03, 0.2, 0.4])
    assert ts.sweep_optimum(k, np.abs(s), s) == (
        0.15, "grid minimum of the ratio (no sign change of the signed objective there)")


@pytest.mark.parametrize("where", ["last", "first above zero"])
def test_sweep_optimum_at_an_end_of_the_grid_is_unknown(where):
    if where == "last":
        k = np.array([0.0, 0.1, 0.2, 0.27])
        s = np.array([0.5, 0.3, 0.1, 0.02])
    else:
        k = np.array([0.06, 0.1, 0.2, 0.27])
        s = np.array([-0.02, -0.3, -0.5, -0.6])
    k_opt, note = ts.sweep_optimum(k, np.abs(s), s)
    at = k[-1] if where == "last" else k[0]
    assert math.isnan(k_opt)
    assert note == (f"the ratio is smallest at the end of the sweep (K_fc = {at:.4g}): the optimum may lie "
                    "outside; widen tune.sweep.k_fc_max")


# ---- the unconverged search's diagnosis --------------------------------------------------------

def test_a_search_without_a_moving_experiment_keeps_its_own_cause():
    pts = {0.0: dict(_point(0.0, _periods(0.9, [0.03, 0.031], [0.0, 0.0, 0.0]), 0.5), ratio=math.inf)}
    for cause, expected in (("noise", "noise"), ("no motion", "no motion"), (None, "not verified")):
        got = _run(ts._diagnose_search(_Probe(0.5, {}), SimpleNamespace(cause=cause), pts, 0.0))
        assert got == (expected, None)


@pytest.mark.parametrize("share, shown", [(0.443, "44"), (0.446, "45")])
def test_a_wide_smoothed_sign_is_named_with_its_share_of_the_peak_velocity(share, shown):
    f, a = 0.625, 0.5
    v_peak = 2 * math.pi * f * a
    width = share * v_peak                     # 44.3 (44.6) % of the sine's peak velocity
    phases = np.array([0.3, -1.1, 2.0])
    pts = {}
    for k, s_k in ((0.0, [0.03, 0.031, 0.029]), (0.11, [0.001, 0.0012, 0.0009]), (0.2, [-0.02, -0.021, -0.019])):
        pts[k] = _point(k, _periods(0.97 * np.exp(-1j * 0.03), s_k, phases), a)
        pts[k]["lag_deg"], pts[k]["fc_smooth"] = math.degrees(0.03), width
    probe = _Probe(a, {}, frequency_hz=f)
    cause, text = _run(ts._diagnose_search(probe, SimpleNamespace(cause="not verified"), pts, 0.0))
    # the offset bound: the relay's odd harmonics against those of the saturated sign (quadrature)
    rho = width / v_peak
    c = [_sat_cos_coefficient(rho, k) / (4 / (k * math.pi) * (-1) ** ((k - 1) // 2)) for k in (3, 5, 7)]
    bias = abs(sum(math.copysign(1, ck) / k for ck, k in zip(c, (3, 5, 7)))
               / sum(abs(ck) / k for ck, k in zip(c, (3, 5, 7))) - 1)
    assert bias > ts.MAX_SIGMA_RE_K_FC
    assert cause == "smoothed sign" and probe.asked == []
    assert text.startswith(f"the drive smooths the feed-forward's sign over fc_smooth = {width:g} rad/s, "
                           f"{100 * width / v_peak:.2g} % of the sine's peak velocity: its odd harmonics are not "
                           "the friction's relay (offset bound ")
    assert f"{100 * width / v_peak:.2g}" == shown
    bound = float(re.search(r"offset bound ([0-9.]+) %", text).group(1))
    assert bound == pytest.approx(100 * bias, rel=5e-3)     # (3 digits; the quadrature 1e-3)


# ---- the budget: the search's noise against one experiment's brings the repeat -------------------

@pytest.mark.parametrize("times, repeated", [(9.5, False), (10.5, True)])
def test_search_noise_ten_times_the_second_amplitudes_brings_the_repeat(times, repeated):
    # K_fc* at the second amplitude agrees (within twice the noise and 5 %), the search's noise
    # is above 1 % of K_fc*: the first experiment is repeated when that noise is more than
    # REPEAT_NOISE_RATIO = 10 times the second amplitude's (the search's points disagree)
    a1, a2 = 0.5, 0.25
    k1, slope = 0.1187, -8.0
    phases = np.array([0.3, -1.1, 2.0])
    h1_star, h1_two = 0.97 * np.exp(-1j * 0.015), 0.95 * np.exp(-1j * 0.021)
    s_two = np.array([0.002, 0.010, -0.004, 0.006])
    slope2 = slope * a1 * abs(h1_star) / (a2 * abs(h1_two))
    sigma2 = s_two.std(ddof=1) / 2 / abs(slope2) * _t95(3)
    sig1 = times * sigma2
    assert sig1 > 0.01 * k1
    p0 = _point(0.0, _periods(0.9, [0.030, 0.031, 0.029], phases), a1)
    p_star = _point(k1, _periods(h1_star, [1e-4, -2e-4, 3e-4], phases), a1, noise=2e-4)
    first = _point(0.3, _periods(0.93, [-0.020, -0.021, -0.019], phases), a1)
    probe = _Probe(a1, {"amplitude2": _point(k1, _periods(h1_two, s_two, phases), a2), "repeat": first})
    cfg = {"tune": {"frequency_hz": 1.25, "amplitude_max_rad": 0.5}, "detect": {"encoder_step_rad": 1e-9},
           "limits": {}}
    outcome = tuning.KfcSearchResult(k_fc=k1, sigma=sig1, converged=True, reason="", n_experiments=5,
                                     bracket=(0.1, 0.14), extended_to=None, regime="signed root",
                                     sigma_signed=1e-3, slope=slope, phases=phases, sigma_fit=0.0)
    out = _run(ts._budget(ts._Context(cfg, 2560.0, "raw", 5.0, {}), probe, outcome,
                          {0.0: p0, k1: p_star, 0.3: first}, {"alternative_rad": a2}))
    assert out["cause"] is None, out["cause"]
    assert out["k_fc_at_amplitude"]["sigma_noise"][1] == pytest.approx(sigma2, rel=1e-6)
    k2 = out["k_fc_at_amplitude"]["k_fc"][1]
    assert abs(k2 - k1) < min(2 * math.hypot(sig1, sigma2), 0.05 * k1)
    # the second amplitude is a new experiment (not a repeat: its capture is keyed as such)
    assert probe.asked[0] == ("amplitude2", k1, 0.0, a2, False)
    assert [x[0] for x in probe.asked] == ["amplitude2"] + (["repeat"] if repeated else [])
    assert (out["repeat"] is not None) is repeated
    if repeated:
        assert out["repeat"]["changed"] is False and out["repeat"]["k_fc"] == pytest.approx(0.3)


# ---- the protocol: the drive's facts by name ----------------------------------------------------

def test_search_tune_takes_the_drives_facts_by_name_only():
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5})
    # (fs_hz and k_fc_limit_v are both floats: by position they could be swapped unnoticed)
    with pytest.raises(TypeError):
        ts.SearchTune(cfg, 2560.0, 2.0)
    first = ts.SearchTune(cfg=cfg, fs_hz=2560.0, k_fc_limit_v=2.0).ask()
    assert first.gains == {"kfc": 0.0, "kv": 0.0} and first.amplitude_rad == 0.5


# ---- K_v at K_fc*: the minimiser's point only when it beats K_v = 0 -----------------------------

@pytest.mark.parametrize("slope, expected", [(2.0, "zero"), (0.0, "minimiser")])
def test_k_v_star_is_zero_when_every_k_v_raises_the_rms_error(slope, expected):
    # the rms error grows with K_v (slope 2 per V s/rad): Brent's interior point is worse than
    # the K_fc* run at K_v = 0, which is reported (K_v* = 0, its rms error); a K_v that leaves
    # the error unchanged (the same record at every K_v) keeps the minimiser's point: K_v = 0
    # replaces it only when strictly better
    plant = _Plant(spread=lambda r: 1e-4, error_gain=lambda kv: 1.0 + slope * kv)
    t = _tune(plant, {"amplitude_rad": 0.5, "viscous": {"enabled": True, "k_v_max": 1.0, "max_experiments": 6}})
    assert t["search"]["converged"], t["search"]["stop_reason"]
    v = t["viscous"]
    evals = v["evaluations"]
    assert len(evals) == v["experiments"] >= 3 and all(e["k_v"] > 0 for e in evals)
    k_star = t["k_fc_star"]
    ver = [r for key, r in plant.records.items() if key.startswith("tune-verify-") and "-kv0" in key
           and key.endswith("-kv0")]
    assert len(ver) == 1                       # K_fc* with K_v = 0, measured for the comparison
    rms0 = math.sqrt(np.mean(ver[0].signals["error"] ** 2))
    if expected == "zero":
        assert v["k_v_star"] == 0.0 and v["rms_error_rad"] == pytest.approx(rms0, rel=1e-12)
        assert min(e["rms_error_rad"] for e in evals) > rms0
    else:
        assert v["k_v_star"] > 0 and pytest.approx(v["k_v_star"], rel=1e-6) in [e["k_v"] for e in evals]
        assert v["rms_error_rad"] == rms0
    assert t["rms_error_rad"]["k_fc_star_k_v_star"] == v["rms_error_rad"]
    assert abs(k_star - 0.1157) < 1e-4


# ---- the model tune: the drive's statistics read as the lines of the raw samples ------------------

def test_model_tune_statistics_give_the_lines_and_noise_of_the_raw_samples():
    # one identification experiment recorded twice, as samples and as the drive's line
    # statistics (computed from the same samples): the lines k = 1 .. 8 are 2 / N of the DFT,
    # the mean the DC line; their period-to-period variances scale as (2 / N)^2, the DC line's
    # (unknown to the drive) is the fundamental's over 4. The deviation between the periods
    # is an impulse (equal at every DFT bin: the DC line's variance is exactly that stand-in)
    # plus a second-harmonic part (so the lines' variances differ)
    cfg = bench_tune.tune_config({"method": "model", "terms": ["coulomb", "asymmetry"], "periods": 4})
    n, P, u_max = 4096, 4, 4.0
    raw, stats = (ts.ModelTune(cfg, fs_hz=FS, capture=cap) for cap in ("raw", "stats"))
    req = stats.ask()
    assert req == raw.ask() and req.periods == P and req.period_samples == n and req.cycles == 1
    w = 2 * np.pi * req.frequency_hz
    t = np.arange(P * n) / FS
    a = req.amplitude_rad
    y = 0.03 + 0.97 * a * np.sin(w * t - 0.05) + 0.004 * np.sin(3 * w * t + 0.2) + 0.002 * np.sin(2 * w * t)
    u = (0.12 * np.sign(np.cos(w * t - 0.05)) + 0.02 + 0.31 * np.sin(w * t + 0.3)
         - 0.05 * np.sin(3 * w * t - 0.2))
    c_imp, e_two, e_eight = [0.3, -0.1, 0.25, -0.45], [0.002, -0.001, 0.0, 0.003], [0.0, 0.004, -0.002, 0.001]
    for p in range(P):
        u[p * n + 123] += c_imp[p]
        u[p * n:(p + 1) * n] += e_two[p] * np.cos(2 * w * t[:n]) + e_eight[p] * np.sin(8 * w * t[:n])
    ref = 0.02 + a * np.sin(w * t)
    err = ref - y
    sig = {"plant_input": u, "motor_angle": y, "error": err}
    rec_stats = SimpleNamespace(stats=fstats.harmonic_stats(sig, n=n, cycles=1, harmonics=8, power=list(sig)),
                                signals={}, parameters={})
    rec_raw = SimpleNamespace(stats=None, signals=dict(sig, reference=ref), parameters={})
    stats.tell(req, ts.Measurement(rec_stats, u_max_v=u_max))
    raw.tell(req, ts.Measurement(rec_raw, u_max_v=u_max))
    got, from_raw = stats.tuner.experiments[0].estimate, raw.tuner.experiments[0].estimate
    # the reference's mean (the set-point, for the Gauss-Newton check): the angle's plus the error's
    assert stats.tuner.experiments[0].lines[1] == pytest.approx(np.mean(ref), rel=1e-9)
    assert raw.tuner.experiments[0].lines[1] == pytest.approx(np.mean(ref), rel=1e-9)
    assert got is not None and from_raw is not None          # (no saturation: rms(u) / u_max 0.06)
    # the raw samples' lines: X_0 the period mean, X_k = 2 / N DFT at k, explicit sums
    nn = np.arange(n)

    def lines(x):
        return np.array([[np.mean(xp)] + [2 / n * np.sum(xp * np.exp(-2j * np.pi * k * nn / n)) for k in range(1, 9)]
                         for xp in x.reshape(P, n)])

    U, Y = lines(u), lines(y)
    var = np.sum(np.abs(U - U.mean(axis=0)) ** 2, axis=0) / (P - 1)
    assert var[0] == pytest.approx(var[1] / 4, rel=1e-9) and var[2] > 1.2 * var[1] and var[8] > 1.2 * var[1]
    expected = ffmodel.estimate_terms(U.mean(axis=0), Y.mean(axis=0), omega_rad_s=w, terms=["coulomb", "asymmetry"],
                                      n_fit=cfg["tune"]["model"]["n_fit"], line_var=var, n_periods=P)
    for name in ("kfc", "kfa", "inertia", "kv"):
        assert got["values"][name] == pytest.approx(expected["values"][name], rel=1e-7, abs=1e-12)
        assert got["values"][name] == pytest.approx(from_raw["values"][name], rel=1e-7, abs=1e-12)
        assert got["noise"][name] == pytest.approx(expected["noise"][name], rel=1e-7)
    assert got["values"]["kfc"] == pytest.approx(0.12, rel=0.05) and got["values"]["kfa"] == pytest.approx(
        0.02 + np.mean(c_imp) / n, rel=0.05)
    # the statistics' saturation check: rms(u) / u_max (0.95: at least (0.95^2 - 0.64) / 0.36 of
    # the samples within 20 % of u_max)
    near = ts.ModelTune(cfg, fs_hz=FS, capture="stats")
    rms_u = math.sqrt(np.mean(u ** 2))
    near.tell(near.ask(), ts.Measurement(rec_stats, u_max_v=rms_u / 0.95))
    assert near.ask() is None and near.tuner.experiments[0].estimate is None
    model = near.result()[0]["model"]
    assert model["cause"] == "saturation" and f"in {100 * (0.95 ** 2 - 0.64) / 0.36:.0f} % of the samples" in \
        model["stop_reason"]


def test_paper_sweep_runs_from_zero_and_finds_the_plants_level():
    # tune.sweep.points 5 up to 0.3 V: K_fc = 0, 0.075 .. 0.3 V; the plant's odd harmonics are
    # linear in Fc - K_fc, so the interpolated zero crossing is Fc itself
    plant = _Plant(fc=0.1157, spread=lambda r: 1e-4)
    t = _tune(plant, {"amplitude_rad": 0.5, "sweep": {"k_fc_max": 0.3, "points": 5}})
    sw = t["sweep"]
    assert sw["k_fc"] == [pytest.approx(x, rel=1e-7) for x in (0.0, 0.075, 0.15, 0.225, 0.3)]
    assert sw["experiments"] == 5 and sw["k_fc"][0] == 0.0
    assert sw["optimum_k_fc"] == pytest.approx(0.1157, rel=1e-4)
    assert sw["optimum_note"] == "zero crossing of the signed objective next to the ratio minimum"
    assert t["search"]["relative_to_sweep_optimum"] == pytest.approx(t["k_fc_star"] / sw["optimum_k_fc"] - 1)



# ---- the plan's key errors: harmonics above fs/2, more than the drive's statistics hold ----------

def test_tune_harmonics_above_half_the_sample_rate_and_beyond_the_statistics_are_named():
    fs, n = 2560.0, 4096
    # 292 cycles: harmonic 7 at bin 2044 < N/2; 293 cycles: bin 2051, above fs/2
    ts.check_plan(bench_tune.tune_config({"frequency_hz": 292 * fs / n}), fs, "raw")
    f = 293 * fs / n
    with pytest.raises(ts.FftuneError) as err:
        ts.check_plan(bench_tune.tune_config({"frequency_hz": f}), fs, "raw")
    assert str(err.value) == (f"bench_tune: key 'tune.harmonics': harmonic 7 of {f:g} Hz is above fs/2 = 1280 Hz")
    K = fstats.STAT_K_MAX
    for capture in ("raw", "stats", "both"):
        ts.check_plan(bench_tune.tune_config({"harmonics": K}), fs, capture)
    ts.check_plan(bench_tune.tune_config({"harmonics": K + 1}), fs, "raw")
    for capture in ("stats", "both"):
        with pytest.raises(ts.FftuneError) as err:
            ts.check_plan(bench_tune.tune_config({"harmonics": K + 1}), fs, capture)
        assert str(err.value) == (
            f"bench_tune: key 'tune.harmonics': {K + 1} harmonics with tune.capture {capture}: the drive's "
            f"statistics hold at most {K} (set tune.capture: raw or tune.harmonics <= {K})")


def test_model_tune_lines_up_to_eight_below_half_the_sample_rate():
    fs, n = 2560.0, 4096
    c = {"period_samples": n, "frequency_hz": 227 * fs / n}
    assert ts.check_model_lines(c, fs, "m.yaml") == 227          # line 8 at bin 1816, 9 x 227 < 2048
    c["frequency_hz"] = 228 * fs / n
    with pytest.raises(ts.FftuneError) as err:
        ts.check_model_lines(c, fs, "m.yaml")
    assert str(err.value) == (f"m.yaml: key 'tune.frequency_hz': harmonic 8 of {c['frequency_hz']:g} Hz is above "
                              "fs/2 (tune.method: model reads k = 0 .. 8)")


def test_model_plan_with_a_numeric_identification_amplitude():
    c = {"model": {"amplitude_rad": 0.7, "verify_amplitude_rad": None}, "terms": ["coulomb", "position"],
         "amplitude_rad": 0.2, "amplitude_max_rad": 3.0}
    plan = ts.model_plan(c)
    # 0.7 rad as set (not pi for the position term), doubled to 2.8 <= 3; the smaller 0.2 verifies
    assert plan["amplitude"] == 0.7 and plan["verify"] == 0.2
    assert plan["checked"] == [("tune.model.amplitude_rad", 0.7), ("tune.amplitude_max_rad", pytest.approx(2.8)),
                               ("tune.amplitude_rad", 0.2)]


# ---- the budget's refusals: each names what it could not tell ------------------------------------

PHASES = np.array([0.3, -1.1, 2.0])


class _ByAmplitude(_Probe):
    """The stand-in probe answering by the asked amplitude."""

    def measure(self, tag, kfc, kv=0.0, amplitude=None, repeat=False):
        self.asked.append((tag, kfc, kv, amplitude, repeat))
        return self.points[amplitude]
        yield


def _budget(probe, cfg_over=None, p_star_over=None, outcome_over=None):
    """``_budget`` after a converged search at 0.5 rad (K_fc* 0.1187 V, slope -8 / V), the auto
    choice's alternative 0.25 rad; (its dict, the point at K_fc*)."""
    a1, k1 = 0.5, 0.1187
    p_star = _point(k1, _periods(0.97 * np.exp(-1j * 0.015), [1e-4, -2e-4, 3e-4], PHASES), a1, noise=2e-4)
    p_star.update(p_star_over or {})
    cfg = {"tune": {"frequency_hz": 1.25, "amplitude_max_rad": 0.5}, "detect": {"encoder_step_rad": 1e-9},
           "limits": {}}
    for key, value in (cfg_over or {}).items():
        cfg[key].update(value)
    outcome = dict(k_fc=k1, sigma=1e-3, converged=True, reason="", n_experiments=5, bracket=(0.1, 0.14),
                   extended_to=None, regime="signed root", sigma_signed=1e-3, slope=-8.0, phases=PHASES,
                   sigma_fit=0.0)
    outcome.update(outcome_over or {})
    out = _run(ts._budget(ts._Context(cfg, 2560.0, "raw", 5.0, {}), probe, tuning.KfcSearchResult(**outcome),
                          {k1: p_star}, {"alternative_rad": 0.25}))
    return out, p_star


def _second(amplitude=0.25, h1=None):
    """An experiment at the second amplitude; with ``h1`` its check failed (saturation when it
    moves: 30 % of the samples at u_max, else no motion)."""
    p = _point(0.1187, _periods(0.95 * np.exp(-1j * 0.02), [0.0015, 0.0027, 0.0018], PHASES), amplitude)
    if h1 is not None:
        p["check"] = tuning.check_experiment(h1, saturated_fraction=0.3 if h1 > 0.2 else 0.0)
    return p


def test_budget_without_a_usable_second_amplitude_names_each_try():
    # the alternative 0.25 rad saturates, then 2 A = 1 rad (allowed up to 1 rad) does not move
    probe = _ByAmplitude(0.5, {0.25: _second(0.25, h1=0.95), 1.0: _second(1.0, h1=0.1)})
    out, _ = _budget(probe, cfg_over={"tune": {"amplitude_max_rad": 1.0}})
    assert [(x[0], x[3]) for x in probe.asked] == [("amplitude2", 0.25), ("amplitude2", 1.0)]
    assert out["cause_key"] == "saturation"
    assert out["cause"] == ("cannot tell the amplitude dependence of K_fc*: no second amplitude gave a usable "
                            "experiment (0.25 rad: saturation; 1 rad: no motion)")
    # (1 rad above tune.amplitude_max_rad: only the alternative is tried)
    probe = _ByAmplitude(0.5, {0.25: _second(0.25, h1=0.1)})
    out, _ = _budget(probe)
    assert [x[3] for x in probe.asked] == [0.25] and out["cause_key"] == "no motion"
    assert out["cause"].endswith("(0.25 rad: no motion)")


def test_budget_without_an_encoder_step_asks_for_it():
    # the drive's statistics (no samples) and no detect.encoder_step_rad: the encoder part is unknown
    probe = _ByAmplitude(0.5, {0.25: _second()})
    out, _ = _budget(probe, cfg_over={"detect": {"encoder_step_rad": None}},
                     p_star_over={"record": SimpleNamespace(signals={})})
    assert out["cause_key"] == "encoder" and "parts" not in out
    assert out["cause"] == (
        "cannot tell the encoder part of the uncertainty: the encoder step is unknown: no samples (tune.capture "
        "stats) and detect.encoder_step_rad unset; set detect.encoder_step_rad (2 pi / counts per revolution, "
        "from the encoder's data sheet) or use tune.capture: both")
    # with it set, the same budget completes with its encoder part
    out, _ = _budget(_ByAmplitude(0.5, {0.25: _second()}), p_star_over={"record": SimpleNamespace(signals={})})
    assert out["cause"] is None and out["encoder_step_source"] == "detect.encoder_step_rad"


def test_budget_in_stick_slip_cannot_read_a_second_amplitude():
    # the ratio minimiser's result, its bracket's ends with s of one sign: no slope to read along
    a, b = 0.08, 0.16
    pa = _point(a, _periods(0.9, [0.021, 0.019, 0.020], PHASES), 0.5)
    pb = _point(b, _periods(0.93, [0.012, 0.010, 0.0115], PHASES), 0.5)
    probe = _Probe(0.5, {})
    phases, slope = ts._phases_and_slope(probe, SimpleNamespace(phases=None, slope=math.nan, bracket=(a, b)),
                                         {a: pa, b: pb})
    assert phases is None and math.isnan(slope)
    cfg = {"tune": {"frequency_hz": 1.25, "amplitude_max_rad": 0.5}, "detect": {"encoder_step_rad": 1e-9},
           "limits": {}}
    outcome = tuning.KfcSearchResult(k_fc=0.1234, sigma=math.nan, converged=True, reason="", n_experiments=6,
                                     bracket=(a, b), extended_to=None, regime="ratio minimiser",
                                     sigma_signed=math.nan, slope=math.nan, phases=None)
    out = _run(ts._budget(ts._Context(cfg, 2560.0, "raw", 5.0, {}), probe, outcome, {a: pa, b: pb}, None))
    assert probe.asked == [] and out["cause_key"] == "stick-slip"
    assert out["cause"] == ("cannot tell the uncertainty: the signed objective has no sign change around K_fc = "
                            "0.1234 V (the odd phases rotate), so K_fc* at a second amplitude cannot be read; "
                            "raise the amplitude (out of stick-slip)")
    # a bracket end not measured: no phases either
    assert ts._phases_and_slope(probe, SimpleNamespace(phases=None, slope=math.nan, bracket=(a, 0.2)),
                                {a: pa, b: pb})[0] is None


def test_budget_lag_step_whose_experiment_fails_ends_with_its_check():
    # the motor lags 3 deg at K_fc*, K_v from the fundamentals: Im(U_1 / Y_1) / w - 4 K_fc / (pi |Y_1| w)
    a1, k1, w = 0.5, 0.1187, 2 * math.pi * 1.25
    h1 = 0.97 * np.exp(-1j * math.radians(3.0))
    u_over_y = 0.4 + 1.0j
    kv = 1.0 / w - 4 * k1 / (math.pi * abs(h1) * a1 * w)
    lag_point = _second(0.5, h1=0.95)                        # 30 % of the samples at u_max
    probe = _Probe(a1, {"lag": lag_point})
    out, _ = _budget(probe, p_star_over={"H": np.concatenate([[h1], np.zeros(6)]), "u_over_y": u_over_y})
    assert probe.asked == [("lag", k1, pytest.approx(kv, rel=1e-12), a1, False)]
    assert out["cause_key"] == "saturation"
    assert out["cause"] == f"saturation: {lag_point['check']['text']}"


# ---- the unconverged search: a plant that changed, named with its figures ------------------------

def _search_pts(h1=0.97 * np.exp(-1j * 0.03)):
    pts = {}
    for k, s_k in ((0.0, [0.03, 0.031, 0.029]), (0.11, [0.001, 0.0012, 0.0009]),
                   (0.2, [-0.020, -0.0212, -0.0191])):
        pts[k] = _point(k, _periods(h1, s_k, PHASES), 0.5)
        pts[k]["lag_deg"] = float(-np.degrees(np.angle(h1)))
    return pts


@pytest.mark.parametrize("shift, changed", [(0.004, True), (0.0012, False)])
def test_unconverged_search_repeats_its_first_experiment_and_names_the_change(shift, changed):
    pts = _search_pts()
    top_s = np.array([-0.020, -0.0212, -0.0191])
    rep = _point(0.2, _periods(0.97 * np.exp(-1j * 0.03), top_s + shift, PHASES), 0.5)
    probe = _Probe(0.5, {"repeat": rep})
    cause, text = _run(ts._diagnose_search(probe, SimpleNamespace(cause="noise"), pts, 0.0))
    assert probe.asked == [("repeat", 0.2, 0.0, 0.5, True)]
    se = top_s.std(ddof=1) / math.sqrt(3)
    noise = math.hypot(se, se)
    assert bool(shift > 3 * noise + 0.01 * abs(top_s.mean())) is changed
    if not changed:
        assert (cause, text) == ("noise", None)           # the search's own cause
        return
    assert cause == "non-stationary"
    assert text == (
        f"the plant changed during the tune: the search's first experiment (K_fc = 0.2 V) repeated at the end "
        f"reads s = {top_s.mean() + shift:.3g} instead of {top_s.mean():.3g} (noise {noise:.2g}): the friction "
        "drifts between the experiments (warming up, wear, a load change), which no search can follow; tune "
        "again in a steady state, or follow the drift with fftune track")


def test_repeat_of_the_first_experiment_needs_both_ends_and_a_usable_repeat():
    pts = _search_pts()
    # no K_fc = 0 experiment to take the phases from: nothing repeated
    probe = _Probe(0.5, {"repeat": pts[0.2]})
    no_zero = {k: p for k, p in pts.items() if k != 0.0}
    assert _run(ts._repeat_first(probe, no_zero)) is None and probe.asked == []
    # the repeat's check fails: no comparison
    probe = _Probe(0.5, {"repeat": _failed_copy(pts[0.2])})
    assert _run(ts._repeat_first(probe, pts)) is None and [x[0] for x in probe.asked] == ["repeat"]


def _failed_copy(p):
    return dict(p, check=tuning.check_experiment(0.1), ratio=math.inf)


# ---- the spread's and the loop gain's texts ------------------------------------------------------

def test_spread_text_from_samples_and_from_line_variances():
    n = 512
    probe = SimpleNamespace(n=n)
    rng = np.random.default_rng(11)
    white = rng.normal(0, 1e-3, (3, n))
    rec = SimpleNamespace(signals={"motor_angle": white.reshape(-1)}, stats=None)
    assert ts._spread_text(probe, {"record": rec, "kfc": 0.1}) is None
    ring = white + np.outer([1.0, -0.4, -0.6], 0.01 * np.sin(2 * np.pi * 21 * np.arange(n) / n))
    rec = SimpleNamespace(signals={"motor_angle": ring.reshape(-1)}, stats=None)
    share = _top_share(rec, n)
    assert share > 0.5
    text = ts._spread_text(probe, {"record": rec, "kfc": 0.1234})
    assert text == (f"the motor angle differs between the recorded periods at K_fc = 0.1234 V by motion, not "
                    f"measurement noise (its spectrum is not flat: {100 * share:.0f} % of its power in 1 % of the "
                    "frequencies): a loop that has not settled or does not repeat (near its resonance?); raise "
                    "tune.settle_periods or lower tune.frequency_hz")
    # the drive's statistics: the lines' variances, flat or one line 14.7 times their median
    flat = np.array([1.0, 1.3, 0.8, 1.1, 0.9, 1.2, 1.0]) * 1e-6
    st = SimpleNamespace(var={"motor_angle": flat})
    rec = SimpleNamespace(signals={}, stats=st)
    assert ts._spread_text(probe, {"record": rec, "kfc": 0.1}) is None
    st.var["motor_angle"] = np.array([1.0, 1.3, 0.8, 1.1, 0.9, 14.7, 1.0]) * 1e-6     # median 1.0e-6
    text = ts._spread_text(probe, {"record": rec, "kfc": 0.1})
    assert "(the period-to-period variance of the harmonic lines is not flat: its largest 14.7 times its " \
           "median)" in text
    # neither samples nor statistics of the angle: nothing to tell
    assert ts._spread_text(probe, {"record": SimpleNamespace(signals={}, stats=None), "kfc": 0.1}) is None


def test_line_variances_and_spread_need_enough_of_them():
    assert ts.line_variance_is_white([1.0, 50.0]) is True                  # two lines: no median to judge
    assert ts.line_variance_is_white([1.0, np.nan, 50.0, np.inf]) is True  # (the finite ones)
    assert ts.line_variance_is_white([1.0, 1.0, 50.0]) is False
    assert ts.line_variance_is_white([1.0, 1.0, 50.0], ratio=60.0) is True
    assert math.isnan(ts.spread_concentration(np.ones((1, 64))))           # one period: no spread


def test_loop_gain_text_outside_the_band_at_the_point_nearest_k():
    pts = _search_pts(0.7 * np.exp(-1j * 0.1))
    pts[0.11] = dict(pts[0.11], H=np.concatenate([[0.9 * np.exp(-1j * 0.1)], pts[0.11]["H"][1:]]))
    probe = _Probe(0.5, {}, frequency_hz=1.875)
    # nearest 0.118: 0.11, |H_1| 0.9 inside 0.8 .. 1.25; nearest 0.19: 0.2, 0.7 outside
    assert ts._loop_gain_text(probe, pts, 0.118) is None
    text = ts._loop_gain_text(probe, pts, 0.19)
    assert text.startswith(f"the loop cannot follow the 1.875 Hz sine: the motor moves 0.7 times the reference at "
                           f"K_fc = 0.2 V (outside 0.8 .. 1.25; lag {math.degrees(0.1):.3g} deg)")
    assert ts._loop_gain_text(probe, pts, math.nan) is None
    assert ts._loop_gain_text(probe, {k: dict(p, ratio=math.inf) for k, p in pts.items()}, 0.19) is None


# ---- the protocol after the tune ------------------------------------------------------------------

def test_a_finished_tune_refuses_more_measurements_and_counts_its_experiments():
    plant = _Plant(spread=lambda r: 1e-4)
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5})
    cfg["detect"]["encoder_step_rad"] = 1e-9
    strategy = ts.SearchTune(cfg, fs_hz=FS, k_fc_limit_v=2.0, max_halvings=0)
    assert not strategy.done and strategy.experiments == 0
    results, _ = ts.replay(strategy, plant)
    assert strategy.done and strategy.ask() is None
    assert strategy.experiments == len(strategy.requests) == len(plant.records) == results["search"]["experiments"]
    with pytest.raises(ValueError, match=r"^tune strategy: finished, nothing was asked; read result\(\)$"):
        strategy.tell(strategy.requests[-1], None)
    model = ts.ModelTune(bench_tune.tune_config({"method": "model"}), fs_hz=FS)
    with pytest.raises(ValueError, match=r"^tune strategy: finished, nothing was asked; read result\(\)$"):
        model.tell(None, None)


# ---- the auto amplitude's verdicts and the loop's own stops, with their figures ------------------

def test_auto_amplitude_reason_names_its_figures_the_encoder_step_and_a_near_alternative():
    # 0.5 rad: |H_1| 0.98, the ratio 0.03 (clear of 0.05), the spread 0.3 %, the step 0.4 %: taken
    plant = _Plant(spread=lambda r: 0.003 * r.amplitude_rad)
    h_scale = 0.03 * 0.5 * 0.98 / _odd_ratio_at_zero(0.1157, 1.0, 1.0, 1.0)
    asked, (a, block, p, stop) = _choose(plant, 0.5, 4.0, h_scale, q=0.002)
    assert asked == [0.5] and stop is None and block["alternative_rad"] is None
    noise = _spread_rad(_zero_record(plant, 0.5), 4096) / 0.5
    ratio = block["probes"][0]["ratio_at_zero"]
    assert ratio == pytest.approx(0.03, rel=1e-3)
    assert block["reason"] == (
        f"at K_fc = 0 the motor follows the sine (|H_1| = 0.98 >= 0.5), the odd-harmonic ratio {ratio:.3g} is <= "
        f"0.05 (out of stick-slip) and the angle noise is {100 * noise:.2g} % of the amplitude (<= 2 %); the "
        "encoder step is 0.4 % of it (<= 1 %, else the amplitude is raised: the quantisation offset falls with it)")
    assert block["probes"][0]["encoder_step_re_amplitude"] == pytest.approx(0.004)
    # the ratio 0.045: within 25 % of its limit, taken with the alternative the next step
    # gives, max(2, 0.045 / 0.04) x 0.5 rad = 1 rad
    plant = _Plant(spread=lambda r: 0.003 * r.amplitude_rad)
    asked, (a, block, p, stop) = _choose(plant, 0.5, 4.0, 0.045 / 0.03 * h_scale, q=0.002)
    assert asked == [0.5] and block["probes"][0]["verdict"] == "near" and block["alternative_rad"] == 1.0
    assert block["reason"].endswith("; near a limit (within 25 % or 2 standard errors): another noise seed may "
                                    "choose 1 rad, measured as the second amplitude")
    # the step 1.2 % of the amplitude at tune.amplitude_max_rad: taken there, named as above 1 %
    plant = _Plant(spread=lambda r: 0.003 * r.amplitude_rad)
    asked, (a, block, p, stop) = _choose(plant, 0.5, 0.5, h_scale, q=0.006)
    assert asked == [0.5] and stop is None
    assert block["reason"].endswith("; the encoder step is 1.2 % of it, above 1 %, at tune.amplitude_max_rad")


@pytest.mark.parametrize("h1_top, linear", [(0.37, True), (0.38, False)])
def test_a_motor_that_follows_the_same_share_at_two_amplitudes_is_the_loops_lag(h1_top, linear):
    # |H_1| 0.25 at 0.5 rad, then 0.37 at 2 rad (x 1.48) with small odd harmonics and no sample
    # at u_max: no friction holds it (a held motor breaks free), the loop's own dynamics; x 1.52
    # is more than LINEAR_H1_FACTOR 1.5: the motor is breaking free, the probes go on
    plant = _Plant(gain=lambda a: 0.25 if a < 1.0 else h1_top if a < 4.0 else 0.98,
                   spread=lambda r: 0.001 * r.amplitude_rad)
    h_scale = 0.02 * 2.0 * h1_top / _odd_ratio_at_zero(0.1157, 1.0, 1.0, 1.0)      # ratio 0.02 at 2 rad
    asked, (a, block, p, stop) = _choose(plant, 0.5, 8.0, h_scale)
    assert asked[:2] == [0.5, 2.0]
    if not linear:
        assert asked == [0.5, 2.0, 8.0] and stop is None and a == 8.0          # (free at 8 rad)
        return
    assert asked == [0.5, 2.0] and stop["cause"] == "loop lag" and block["probes"][-1]["cause"] == "loop lag"
    assert stop["text"] == (
        f"the loop cannot follow the 0.625 Hz sine: the motor moves {h1_top:.3g} times the reference at 2 rad and "
        "0.25 times at 0.5 rad, with no sample at u_max: the same share at both, so no friction holds it (a held "
        "motor breaks free as the amplitude grows) but the loop's own dynamics at this frequency (a load "
        "anti-resonance near it); lower tune.frequency_hz or change the loop gains")


def test_resonance_without_feed_forward_names_the_motion_and_the_samples_at_u_max():
    probe = _Probe(0.5, {}, frequency_hz=3.75)

    def zero(h1, sat, kfc=0.0, kv=0.0):
        p = _point(kfc, _periods(h1, [0.01, 0.011, 0.009], PHASES), 0.5, kv=kv)
        p["check"] = tuning.check_experiment(abs(h1), saturated_fraction=sat)
        return p

    ck = ts._resonance_check(probe, zero(5.8 * np.exp(-1j * 0.4), 0.57))
    assert ck["cause"] == "loop lag" and ck["saturated_fraction"] == 0.57
    assert ck["text"] == (
        "the loop cannot follow the 3.75 Hz sine: without feed-forward the motor moves 5.8 times the reference "
        "at 0.5 rad (more than 1.4; the friction only holds it back): the loop is near its resonance at this "
        "frequency, its output at u_max in 57 % of the samples; lower tune.frequency_hz or change the loop gains")
    # the samples at u_max named only above SATURATION_MAX_FRACTION (2 %)
    assert "u_max" not in ts._resonance_check(probe, zero(1.5, 0.02))["text"]
    assert "its output at u_max in 2 % of" in ts._resonance_check(probe, zero(1.5, 0.0201))["text"]
    # 1.4 times itself, or any feed-forward in the loop: no resonance verdict
    assert ts._resonance_check(probe, zero(1.4, 0.0)) is None
    assert ts._resonance_check(probe, zero(1.5, 0.0, kfc=0.05)) is None
    assert ts._resonance_check(probe, zero(1.5, 0.0, kv=0.01)) is None


def test_a_loop_that_lags_is_tuned_at_a_frequency_where_the_scaled_lag_is_within_the_limit():
    # the loop lags 30 deg at 2.5 Hz, in proportion to the frequency: refused there (no K_v
    # removes it), 1.25 and 0.625 Hz skipped (15 and 7.5 deg expected), tuned at 0.3125 Hz
    plant = _Plant(lag_deg=lambda r: 30.0 * r.frequency_hz / 2.5, spread=lambda r: 1e-4)
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5, "frequency_hz": 2.5})
    cfg["detect"]["encoder_step_rad"] = 1e-9
    logged = []
    strategy = ts.SearchTune(cfg, fs_hz=FS, k_fc_limit_v=2.0, max_halvings=3, log=logged.append)
    t, _ = ts.replay(strategy, plant)
    ch = t["frequency_changes"]
    assert [(c["from_hz"], c["to_hz"], c["period_samples"]) for c in ch] == [
        (2.5, 1.25, 4096), (1.25, 0.625, 4096), (0.625, 0.3125, 8192)]
    assert ch[0]["reason"].startswith("the loop cannot follow the 2.5 Hz sine closely enough: the motor lags the "
                                      "reference by 30 deg at K_fc*")
    assert ch[1]["reason"] == ("skipped: the lag at 1.25 Hz would still be about 15 deg (the lag scaled with the "
                               "frequency from 2.5 Hz; more than 7 deg)")
    assert ch[2]["reason"].startswith("skipped: the lag at 0.625 Hz would still be about 7.5 deg")
    assert logged == ["tune: the loop cannot follow 2.5 Hz; again at 0.3125 Hz"]
    s = t["search"]
    assert t["frequency_hz"] == 0.3125 and s["converged"] and s["loop_lag_deg"] == pytest.approx(3.75, rel=1e-3)
    at_first = sum(1 for key in plant.records if "-f" not in key)
    assert s["experiments_at_other_frequencies"] == at_first
    assert s["experiments"] == len(plant.records) == len(strategy.requests)
    # without halvings: refused at 2.5 Hz with the loop's lag, no estimate
    strategy = ts.SearchTune(cfg, fs_hz=FS, k_fc_limit_v=2.0, max_halvings=0)
    t0, _ = ts.replay(strategy, _Plant(lag_deg=lambda r: 30.0 * r.frequency_hz / 2.5, spread=lambda r: 1e-4))
    assert t0["search"]["cause"] == "loop lag" and "frequency_changes" not in t0 and t0["k_fc_best_measured"] is None


# ---- a budget too large, a plant that drifts inside the experiments ------------------------------

def test_an_amplitude_dependent_level_is_refused_with_its_budget_and_largest_part():
    # Fc(A) = 0.1 + 0.02 / A: 0.14 V at 0.5 rad, 0.12 V at 2 A = 1 rad; extrapolated to 1/A -> 0:
    # 0.14 + 2 (0.12 - 0.14) = 0.10 V, the step from the nearer amplitude (1 rad) 0.02 V the part:
    # 20 % of K_fc*, more than MAX_SIGMA_RE_K_FC 10 %
    class ByAmplitude(_Plant):
        def __call__(self, req):
            self.fc = 0.1 + 0.02 / req.amplitude_rad
            return _Plant.__call__(self, req)

    t = _tune(ByAmplitude(spread=lambda r: 1e-4), {"amplitude_rad": 0.5})
    s = t["search"]
    assert not s["converged"] and s["cause"] == "amplitude dependence"
    assert s["budget"]["k_fc_at_amplitude"]["amplitude_rad"] == [0.5, 1.0]
    assert s["budget"]["k_fc_at_amplitude"]["k_fc"] == [pytest.approx(0.14, rel=1e-4), pytest.approx(0.12, rel=1e-4)]
    parts, total, k = s["sigma_parts_v"], s["sigma_total_v"], s["k_fc_star"]
    assert k == pytest.approx(0.10, rel=1e-3) and parts["amplitude"] == pytest.approx(0.02, rel=1e-3)
    assert total == pytest.approx(math.sqrt(sum(v ** 2 for v in parts.values())), rel=1e-12)
    assert max(parts, key=parts.get) == "amplitude"
    assert s["stop_reason"].startswith(
        f"cannot tell K_fc* better than +-{100 * total / k:.3g} % (sigma_total {total:.3g} V at K_fc = {k:.4g} V, "
        f"more than 10 %); the largest part is 'amplitude' ({parts['amplitude']:.3g} V): K_fc* depends on the sine "
        "amplitude (stick-slip, Stribeck, a loop that does not repeat): raise tune.amplitude_rad")
    assert f"{100 * total / k:.3g}" == "20"
    # an estimate, but not K_fc*
    assert t["k_fc_star"] is None and t["k_fc_best_measured"] == k
    assert t["k_fc_best_measured_note"] == "an estimate whose uncertainty is too large (tune.search.sigma_total_v)"


class _Drifting(_Plant):
    """Fc falls by ``rate`` of its start value per recorded (and settling) period of the tune."""

    def __init__(self, rate, **kw):
        super().__init__(**kw)
        self.rate, self.clock, self.fc0 = rate, 0, self.fc

    def __call__(self, req):
        n, P = req.period_samples, req.periods
        t0 = self.clock + req.settle_periods
        self.clock += req.settle_periods + P
        y = []
        for p in range(P):
            self.fc = self.fc0 * (1 + self.rate * (t0 + p))
            m = _Plant.__call__(self, req)
            y.append(m.record.signals["motor_angle"].reshape(P, n)[p])
        m.record.signals["motor_angle"] = np.concatenate(y)
        m.record.signals["error"] = m.record.signals["reference"] - m.record.signals["motor_angle"]
        return m


def test_a_level_that_drifts_inside_every_experiment_brings_the_repeat_and_is_named():
    # -0.3 % of Fc per period: within each experiment s moves the same way, through the
    # search's slope about -0.3 % Fc / K_fc* per period; the first experiment repeated reads
    # another s: non-stationary, not a K_fc*
    plant = _Drifting(-0.003, spread=lambda r: 1e-4)
    t = _tune(plant, {"amplitude_rad": 0.5})
    s = t["search"]
    drift = s["period_drift"]
    rate = drift["rate_re_k_fc_per_period"]
    assert drift["repeated"] and drift["repeat"]["changed"]
    # the change of s per period is the stationary plant's slope times the change of Fc; read
    # through the (drift-flattened) slope of this search, relative to its K_fc*
    true_slope = _tune(_Plant(spread=lambda r: 1e-4), {"amplitude_rad": 0.5})["search"]["signed_objective_slope_per_v"]
    expected = -0.003 * plant.fc0 * true_slope / s["signed_objective_slope_per_v"] / s["k_fc_star"]
    assert rate == pytest.approx(expected, rel=0.15) and rate < -ts.DRIFT_MIN_REL
    assert not s["converged"] and s["cause"] == "non-stationary" and t["k_fc_best_measured"] is None
    rep = drift["repeat"]
    assert s["stop_reason"] == (
        f"the plant changed during the tune: the search's first experiment (K_fc = {rep['k_fc']:.4g} V) repeated "
        f"at the end reads s = {rep['s_now']:.3g} instead of {rep['s_then']:.3g} (noise {rep['noise']:.2g}): the "
        "friction drifts between the experiments (warming up, wear, a load change), which no search can follow; "
        "tune again in a steady state, or follow the drift with fftune track; within every experiment the "
        f"objective moved the same way ({100 * rate:+.2g} % of K_fc* per recorded period)")
    assert f"{100 * rate:+.2g}".startswith("-0.")


# ---- the results of a converged tune: each figure against the plant ------------------------------

def test_converged_tune_results_against_the_synthetic_plant():
    plant = _Plant(spread=lambda r: 2e-4 * (1 + r.gains["kfc"]), h_scale=0.05)
    t = _tune(plant, {"amplitude_rad": 0.5})
    s = t["search"]
    assert s["converged"] and t["k_fc_star"] == pytest.approx(0.1157, rel=1e-4)
    assert s["amplitude_probes"] == 0 and t["amplitude"] == {"chosen_rad": 0.5, "reason": "tune.amplitude_rad"}
    # every experiment of the search: its K_fc, |H_1| 0.98, lag 0.6 deg, the ratio of its odd harmonics
    ev = s["evaluations"]
    assert [e["k_fc"] for e in ev] == sorted(e["k_fc"] for e in ev) and ev[0]["k_fc"] == 0.0
    for e in ev:
        assert e["h1"] == pytest.approx(0.98, rel=1e-5) and e["lag_deg"] == pytest.approx(0.6, abs=1e-4)
        r = _odd_ratio_at_zero(0.1157 - e["k_fc"], 0.05, 0.5, 0.98)
        assert e["ratio"] == pytest.approx(abs(r), rel=1e-3, abs=1e-6) and e["cause"] is None
    r0 = _odd_ratio_at_zero(0.1157, 0.05, 0.5, 0.98)
    assert t["ratio_at_zero"] == pytest.approx(r0, rel=1e-4)
    # the verification experiment: the measured point nearest K_fc*, its ratio and the improvement
    k_ver = min((e["k_fc"] for e in ev), key=lambda k: abs(k - t["k_fc_star"]))
    assert s["verification_k_fc"] == pytest.approx(k_ver, rel=1e-7)          # (the K_fc asked; float32 run)
    r_ver = next(e["ratio"] for e in ev if e["k_fc"] == k_ver)
    assert t["ratio_at_k_fc_star"] == r_ver and t["ratio_improvement"] == pytest.approx(t["ratio_at_zero"] / r_ver)
    # the rms tracking errors: at K_fc = 0, at the verification, the smallest over the search
    rms = {float(re.search(r"-kfc([0-9.e-]+)-kv", key).group(1)): math.sqrt(np.mean(rec.signals["error"] ** 2))
           for key, rec in plant.records.items()}
    assert t["rms_error_rad"]["k_fc_0"] == pytest.approx(rms[0.0], rel=1e-12)
    assert t["rms_error_rad"]["k_fc_star"] == pytest.approx(rms[min(rms, key=lambda k: abs(k - k_ver))], rel=1e-12)
    k_min = min(rms, key=rms.get)
    assert t["rms_error_rad"]["sweep_min"] == pytest.approx(rms[k_min], rel=1e-12)
    assert t["rms_error_rad"]["sweep_min_at_k_fc"] == pytest.approx(k_min, rel=1e-6)
    assert s["experiments"] == len(plant.records) and s["k_fc_search_v"] == pytest.approx(0.1157, rel=1e-4)


@pytest.mark.parametrize("lag_deg, lag_after_deg, kv_search", [(3.0, 0.5, 0.0), (-3.0, 0.5, 0.01), (3.0, 4.0, 0.0),
                                                               (1.2, None, 0.0), (3.0, None, "0.95 kv"),
                                                               (3.0, None, "no estimate")])
def test_budget_viscous_step_notes(lag_deg, lag_after_deg, kv_search):
    # the motor lags (or leads) |lag| deg at K_fc*; K_v from the fundamentals; one experiment with
    # it in the loop (its root 1.1 % away: no second): corrected when its lag is smaller, else
    # not applied and the shift is the part; within 1.5 deg (or with the search's K_v within 10 %
    # of the estimate) no step at all
    a1, k1, w, slope = 0.5, 0.1187, 2 * math.pi * 1.25, -8.0
    h1 = 0.97 * np.exp(-1j * math.radians(lag_deg))
    u_over_y = 0.4 + 1.0j
    kv = 1.0 / w - 4 * k1 / (math.pi * 0.97 * a1 * w)
    s_lag = np.array([0.0010, 0.0012, 0.0009])
    if kv_search == "0.95 kv":                  # the search's K_v within 10 % of the estimate: no step
        kv_search = 0.95 * kv
    if kv_search == "no estimate":              # no K_v read at K_fc*: no step (the search's is kept)
        kv_search, u_over_y = 0.01, None
    points = {"amplitude2": _second()}
    if lag_after_deg is not None:
        points["lag"] = _point(k1, _periods(0.98 * np.exp(-1j * math.radians(lag_after_deg)), s_lag, PHASES), a1,
                               kv=kv)
    probe = _Probe(a1, points)
    probe.kv_search = kv_search
    out, _ = _budget(probe, p_star_over={"H": np.concatenate([[h1], np.zeros(6)]), "u_over_y": u_over_y})
    assert out["cause"] is None, out["cause"]
    visc = out["viscous"]
    prefix = (f"the viscous feed-forward K_v = {kv_search:.4g} V s/rad (read from the K_fc = 0 experiment) was in "
              "the loop during the search; " if kv_search else "")
    if lag_after_deg is None:
        assert [x[0] for x in probe.asked] == ["amplitude2"] and out["parts"]["viscous"] == 0.0
        assert visc["note"] == prefix + (f"lag {lag_deg:.3g} deg at K_fc* (|lag| <= 1.5 deg, or no better K_v "
                                         "estimate): no further correction")
        assert out["k_v_in_search"] == kv_search
        return
    k_new = float(np.float32(k1)) - s_lag.mean() / slope
    assert probe.asked[0] == ("lag", k1, pytest.approx(kv, rel=1e-12), a1, False)
    assert abs(k_new - k1) < 0.02 * k1 and len(visc["steps"]) == 1
    if abs(lag_after_deg) < abs(lag_deg):
        assert visc["applied"] and out["parts"]["viscous"] == pytest.approx(abs(k_new - k1) / 2, rel=1e-9)
        assert out["k_fc_at_amplitude"]["k_fc"][0] == pytest.approx(k_new, rel=1e-12)
        assert visc["note"] == prefix + (
            f"the motor {'lagged' if lag_deg > 0 else 'led'} the reference by {abs(lag_deg):.3g} deg at K_fc*: K_fc* "
            f"read again with K_v = {kv:.4g} V s/rad in the loop (corrected)")
        assert out["k_v_in_search"] == pytest.approx(kv)
    else:
        assert not visc["applied"] and out["parts"]["viscous"] == pytest.approx(abs(k_new - k1), rel=1e-9)
        assert out["k_fc_at_amplitude"]["k_fc"][0] == k1 and out["k_v_in_search"] == kv_search
        assert visc["note"] == prefix + ("the new K_v estimate did not reduce the lag: not applied; the shift it "
                                         "gave is a part of the budget")


# ---- the measurement of one experiment, the auto amplitude's rules, K_v into the search ------------

def test_measurement_reads_the_runs_parameters_before_the_configuration():
    ctl = {"u_max": 2.0, "fc_smooth": 0.3, "kp": 1.0}
    m = ts.measurement_from_record(SimpleNamespace(parameters={"u_max": 1.5, "fc_smooth": None}), ctl)
    assert (m.u_max_v, m.fc_smooth) == (1.5, 0.3)
    m = ts.measurement_from_record(SimpleNamespace(), ctl)            # (a record without parameters)
    assert (m.u_max_v, m.fc_smooth) == (2.0, 0.3)
    m = ts.measurement_from_record(SimpleNamespace(parameters={"fc_smooth": 0.0}))
    assert (m.u_max_v, m.fc_smooth) == (None, 0.0)


def test_saturation_fraction_at_an_output_limit_below_one_volt():
    u = np.array([0.1, -0.8, 0.79, 0.8 * (1 - 1e-7), -0.3, 0.81, 0.0, -0.2])
    assert ts.saturation_fraction(u, 0.8) == 3 / 8                   # |u| >= u_max (float32 tolerance)
    assert ts.saturation_fraction(u, 0.0) is None and ts.saturation_fraction(u, None) is None


def _probe(capture, periods=3, harmonics=7):
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5, "periods": periods, "harmonics": harmonics,
                                  "capture": capture})
    return ts._TuneProbe(ts._Context(cfg, FS, capture, 2.0, {}))


def test_statistics_capture_measures_what_the_raw_samples_give():
    # one record, told as samples and as the drive's line statistics of the same samples: the
    # HOSIDFs, the plant input's and the angle's lines, U_1 / Y_1 and the rms error agree; the
    # saturation is the samples' share, or from the statistics the bound (rho^2 - 0.64) / 0.36
    n, P, u_max = 4096, 3, 1.0
    w = 2 * np.pi * 0.625
    t = np.arange(P * n) / FS
    rng = np.random.default_rng(4)
    ref = 0.5 * np.sin(w * t)
    y = 0.48 * np.sin(w * t - 0.05) + 0.003 * np.sin(3 * w * t + 0.7) + 1e-4 * rng.standard_normal(t.size)
    u = np.clip(1.6 * np.sin(w * t + 0.4) + 0.1 * np.sign(np.cos(w * t - 0.05)), -u_max, u_max)
    sig = {"reference": ref, "motor_angle": y, "plant_input": u, "error": ref - y}
    got = {}
    for capture in ("raw", "stats"):
        probe = _probe(capture)
        if capture == "raw":
            rec = SimpleNamespace(stats=None, signals=sig, parameters={})
        else:
            st = fstats.harmonic_stats({k: sig[k] for k in ("reference", "motor_angle", "plant_input")}, n=n,
                                       cycles=1, harmonics=7)
            st.power_mean.update({k: float(np.mean(sig[k])) for k in ("error", "plant_input")})
            st.power_msq.update({k: float(np.mean(sig[k] ** 2)) for k in ("error", "plant_input")})
            rec = SimpleNamespace(stats=st, signals={}, parameters={})
        gen = probe.measure("search", 0.0)
        next(gen)
        try:
            gen.send(ts.Measurement(rec, u_max_v=u_max))
        except StopIteration as stop:
            got[capture] = stop.value
    raw, st = got["raw"], got["stats"]
    mean_u, mean_y = u.reshape(P, n).mean(axis=0), y.reshape(P, n).mean(axis=0)
    U1 = np.sum(mean_u * np.exp(-2j * np.pi * np.arange(n) / n))
    Y1 = np.sum(mean_y * np.exp(-2j * np.pi * np.arange(n) / n))
    for p in (raw, st):
        assert p["H"] == pytest.approx(raw["H"], rel=1e-9, abs=1e-12)
        assert p["lines"][0][0] == pytest.approx(U1, rel=1e-9) and p["lines"][1][0] == pytest.approx(Y1, rel=1e-9)
        assert p["u_over_y"] == pytest.approx(U1 / Y1, rel=1e-9)
        assert p["rms_error"] == pytest.approx(math.sqrt(np.mean((ref - y) ** 2)), rel=1e-12)
    assert raw["check"]["saturated_fraction"] == pytest.approx(np.mean(np.abs(u) >= u_max * (1 - 1e-6)))
    rho = math.sqrt(np.mean(u ** 2)) / u_max
    assert rho ** 2 > 0.64
    assert st["check"]["saturated_fraction"] == pytest.approx((rho ** 2 - 0.64) / 0.36, rel=1e-12)
    assert st["check"]["saturation_basis"].startswith("lower bound from rms(u) / u_max")


def test_viscous_estimate_and_its_share_of_the_fundamental():
    f, w, U, Y = _rigid_lines(0.04)
    probe = _Probe(0.5, {}, frequency_hz=f)
    probe.n, probe.cycles = 4096, 2
    p = _point(0.0, _periods(0.9, [0.03, 0.031], PHASES), 0.5)
    p.update(lines=(U, Y), check=tuning.check_experiment(0.9))
    kv, share = ts._viscous_estimate(probe, p)
    assert kv == pytest.approx(0.04, rel=2e-3)
    assert share == pytest.approx(kv * w * abs(Y[0]) / abs(U[0]), rel=1e-12) and 0 < share < 1
    # no viscous friction to read (negative), a failed check, no motion, no lines: (0, 0)
    _, _, Un, Yn = _rigid_lines(-0.02)
    assert ts._viscous_estimate(probe, dict(p, lines=(Un, Yn))) == (0.0, 0.0)
    failed = tuning.check_experiment(0.9, saturated_fraction=0.3)
    assert ts._viscous_estimate(probe, dict(p, check=failed)) == (0.0, 0.0)
    assert ts._viscous_estimate(probe, dict(p, ratio=math.inf)) == (0.0, 0.0)
    assert ts._viscous_estimate(probe, dict(p, lines=None)) == (0.0, 0.0)


def test_amplitude_verdict_h1_band_is_a_fifth_of_the_margin():
    v = ts.amplitude_verdict
    # |H_1| 0.53: 6 % above 0.5, outside the 5 % band: pass; 0.52 inside: near; 0.47 below it: fail
    assert v(0.53, 0.02, 0.001, 0.001) == "pass"
    assert v(0.52, 0.02, 0.001, 0.001) == "near"
    assert v(0.47, 0.02, 0.001, 0.001) == "fail"
    assert v(0.53, 0.02, 0.001, 0.001, margin=0.4) == "near"     # (a fifth of 0.4: 8 %)


def test_auto_amplitude_probes_four_times_by_default():
    # stuck at every amplitude (|H_1| 0.3, ratio > 0.05): 4x each time; after the fourth probe the
    # next amplitude is taken unprobed (the search runs there)
    plant = _Plant(gain=lambda a: 0.3, spread=lambda r: 1e-3 * r.amplitude_rad)
    asked, (a, block, p, stop) = _choose(plant, 0.01, 100.0, 0.5)
    assert asked == [0.01, pytest.approx(0.04), pytest.approx(0.16), pytest.approx(0.64)]
    assert stop is None and a == pytest.approx(2.56) and block["chosen_rad"] == pytest.approx(2.56)
    assert len(block["probes"]) == 4 and all(q["verdict"] == "fail" for q in block["probes"])
    # the reason says the ceiling was not reached and the chosen amplitude was not probed
    # (it said "stick-slip at every amplitude up to tune.amplitude_max_rad = 100 rad")
    assert p["H"] is not None and block["reason"] == (
        f"stick-slip at all 4 probed amplitudes up to 0.64 rad (|H_1| = {block['probes'][3]['h1']:.3g}, "
        f"ratio at K_fc = 0 {block['probes'][3]['ratio_at_zero']}), below tune.amplitude_max_rad = 100 rad: "
        "the search runs at the next step, 2.56 rad, not probed, and may rely on the ratio minimiser")


def test_auto_amplitude_resonance_marks_the_probe_that_found_it():
    plant = _Plant(gain=lambda a: 0.45 if a < 0.1 else 1.6, spread=lambda r: 1e-3 * r.amplitude_rad)
    asked, (a, block, p, stop) = _choose(plant, 0.05, 2.0, 0.5)
    assert asked == [0.05, pytest.approx(0.2)] and stop["cause"] == "loop lag"
    assert [q["cause"] for q in block["probes"]] == [None, "loop lag"]
    assert stop["text"].startswith("the loop cannot follow the 0.625 Hz sine: without feed-forward the motor "
                                   "moves 1.6 times the reference at 0.2 rad")


@pytest.mark.parametrize("growth, unsettled", [(2.1, True), (1.9, False)])
def test_auto_amplitude_spread_that_doubles_is_unsettled_already_at_the_second_probe(growth, unsettled):
    # 0.1 rad: ratio 0.1 (x 2.5), spread 4 mrad; 0.25 rad: the spread `growth` times that, above 2 %
    # of the amplitude at both sizes: unsettled when it more than doubled (in rad)
    spreads = {0.1: 0.004, 0.25: 0.004 * growth, 0.5: 0.001}
    plant = _Plant(gain=lambda a: 0.9, spread=lambda r: spreads[round(r.amplitude_rad, 6)])
    h_scale = 0.1 * 0.1 * 0.9 / _odd_ratio_at_zero(0.1157, 1.0, 1.0, 1.0)
    asked, (a, block, p, stop) = _choose(plant, 0.1, 2.0, h_scale)
    assert asked[:2] == [0.1, pytest.approx(0.25)]
    n1 = _spread_rad(_zero_record(plant, 0.1), 4096)
    n2 = _spread_rad(_zero_record(plant, 0.25), 4096)
    assert n2 / n1 == pytest.approx(growth, rel=1e-3) and n2 / 0.25 > 0.02
    if unsettled:
        assert len(asked) == 2 and stop["cause"] == "unsettled"
        assert stop["text"].startswith(f"the motor angle differs between the recorded periods by "
                                       f"{100 * n2 / 0.25:.2g} % of the amplitude at 0.25 rad and "
                                       f"{100 * n1 / 0.1:.2g} % at 0.1 rad")
    else:
        assert asked == [0.1, pytest.approx(0.25), pytest.approx(0.5)] and stop is None


@pytest.mark.parametrize("h1_top, linear", [(0.26, True), (0.25, False)])
def test_a_motor_that_moves_less_at_the_larger_amplitude_within_the_factor_is_the_loops(h1_top, linear):
    # |H_1| 0.38 at 0.5 rad, h1_top at 2 rad: 0.26 / 0.38 = 0.684 >= 1 / 1.5, the same share
    # within LINEAR_H1_FACTOR (the loop's); 0.25 / 0.38 = 0.658 below it: the probes go on
    plant = _Plant(gain=lambda a: 0.38 if a < 1.0 else h1_top if a < 4.0 else 0.98,
                   spread=lambda r: 0.001 * r.amplitude_rad)
    h_scale = 0.02 * 2.0 * h1_top / _odd_ratio_at_zero(0.1157, 1.0, 1.0, 1.0)
    asked, (a, block, p, stop) = _choose(plant, 0.5, 8.0, h_scale)
    if linear:
        assert asked == [0.5, 2.0] and stop["cause"] == "loop lag" and "0.26 times the reference at 2 rad and " \
            "0.38 times at 0.5 rad" in stop["text"]
    else:
        assert asked == [0.5, 2.0, 8.0] and stop is None


@pytest.mark.parametrize("q, shown", [(0.0122, "2.4"), (0.0123, "2.5")])
def test_encoder_step_raises_a_passing_probe_and_names_it(q, shown):
    # 0.1 rad fails by its ratio (x 5); 0.5 rad would pass but the step (12.2, 12.3 mrad) is 2.44
    # (2.46) % of it: failed there, raised to 1.05 q / 1 % (more than the ratio's 2x), where it passes
    plant = _Plant(gain=lambda a: 0.9, spread=lambda r: 1e-3 * r.amplitude_rad)
    h_scale = 0.2 * 0.1 * 0.9 / _odd_ratio_at_zero(0.1157, 1.0, 1.0, 1.0)
    asked, (a, block, p, stop) = _choose(plant, 0.1, 4.0, h_scale, q=q)
    raised = 1.05 * q / 0.01
    assert asked == [0.1, pytest.approx(0.5), pytest.approx(raised)] and a == pytest.approx(raised) and stop is None
    first, second, third = block["probes"]
    assert first["verdict"] == "fail" and "encoder_note" not in first
    assert f"{100 * q / 0.5:.2g}" == shown
    assert second["verdict"] == "fail" and second["encoder_note"] == (
        f"encoder step {q:.3g} rad (detect.encoder_step_rad) is {shown} % of the amplitude (> 1 %)")
    assert third["verdict"] == "pass" and third["encoder_step_re_amplitude"] == pytest.approx(q / raised)


def test_near_probe_at_the_ceiling_has_no_alternative_and_names_its_noise():
    # the ratio 0.045 is near its limit, but 0.5 rad is tune.amplitude_max_rad: nothing larger
    plant = _Plant(spread=lambda r: 0.01 * r.amplitude_rad)
    h_scale = 0.045 * 0.5 * 0.98 / _odd_ratio_at_zero(0.1157, 1.0, 1.0, 1.0)
    asked, (a, block, p, stop) = _choose(plant, 0.5, 0.5, h_scale)
    assert asked == [0.5] and block["probes"][0]["verdict"] == "near" and block["alternative_rad"] is None
    assert "near a limit" not in block["reason"]
    assert "the angle noise is 1 % of the amplitude (<= 2 %)" in block["reason"]        # 1.00 %


def test_sweep_zero_exactly_at_a_grid_point_is_the_crossing():
    k = np.array([0.0, 0.05, 0.1, 0.15])
    s = np.array([0.5, 0.2, 0.0, -0.3])
    assert ts.sweep_optimum(k, np.abs(s) + 0.01, s) == (
        0.1, "zero crossing of the signed objective next to the ratio minimum")


def test_sine_on_the_grid_within_a_relative_tolerance_of_its_cycles():
    # 293 cycles in 4096 samples at 2560 Hz: the frequency typed with 10 digits (relative 1e-10)
    # is that sine; 1e-8 off is not
    f = 293 * 2560.0 / 4096
    assert ts.cycles_on_grid(2560.0, 4096, f * (1 + 1e-10), "k") == 293
    with pytest.raises(ts.FftuneError, match="not on the DFT grid"):
        ts.cycles_on_grid(2560.0, 4096, f * (1 + 1e-8), "k")


class _WithInput(_Plant):
    """The synthetic loop with its plant input: a rigid body J y'' + b y' plus the sliding
    relay F sgn(velocity's fundamental), in V."""

    def __init__(self, b, J=1e-3, F=0.1, **kw):
        super().__init__(**kw)
        self.b, self.J, self.F = b, J, F

    def __call__(self, req):
        self.requests = getattr(self, "requests", []) + [req]
        m = _Plant.__call__(self, req)
        n, P = req.period_samples, req.periods
        w = 2 * np.pi * req.frequency_hz
        t = np.arange(P * n) / FS
        a, kfc = req.amplitude_rad, req.gains["kfc"]
        lag = math.radians(self.lag_deg(req))
        comps = [(1, a * self.gain(a), 0.0)] + [(k, self.h_scale * 4 / (k * math.pi) * (self.fc - kfc), phi)
                                               for k, phi in ((3, 0.4), (5, -0.9), (7, 1.7))]
        yd = sum(c * k * w * np.cos(k * (w * t - lag) + phi) for k, c, phi in comps)
        ydd = sum(-c * (k * w) ** 2 * np.sin(k * (w * t - lag) + phi) for k, c, phi in comps)
        m.record.signals["plant_input"] = self.J * ydd + self.b * yd + self.F * np.sign(np.cos(w * t - lag))
        return m


@pytest.mark.parametrize("b, in_search", [(0.015, False), (0.03, True)])
def test_viscous_feed_forward_enters_the_search_from_a_quarter_of_the_fundamental(b, in_search):
    # K_v read at K_fc = 0 goes into the search's experiments when its share of the plant input's
    # fundamental, K_v w |Y_1| / |U_1|, is at least KV_MIN_SHARE 0.25
    plant = _WithInput(b, spread=lambda r: 1e-4)
    t = _tune(plant, {"amplitude_rad": 0.5})
    rec = _zero_record(plant, 0.5)
    n = 4096
    e = np.exp(-2j * np.pi * np.arange(n) / n)
    U1 = np.sum(rec.signals["plant_input"].reshape(-1, n).mean(axis=0) * e)
    Y1 = np.sum(rec.signals["motor_angle"].reshape(-1, n).mean(axis=0) * e)
    share = b * 2 * np.pi * 0.625 * abs(Y1) / abs(U1)
    assert bool(share >= 0.25) is in_search and abs(share - 0.25) > 0.03, share
    s = t["search"]
    assert s["converged"] and t["k_fc_star"] == pytest.approx(0.1157, rel=1e-3)
    kv_asked = [r.gains["kv"] for r in plant.requests if r.tag == "search" and r.gains["kfc"] > 0]
    assert len(kv_asked) >= 2 and kv_asked == [pytest.approx(b, rel=1e-3) if in_search else 0.0] * len(kv_asked)
    assert s["k_v_in_search"] == (pytest.approx(b, rel=1e-3) if in_search else 0.0)


def test_the_default_two_halvings_reach_a_quarter_of_the_frequency():
    # 20 deg at 2.5 Hz: 10 deg expected at 1.25 Hz (skipped), 5 deg at 0.625 Hz: tuned there
    plant = _Plant(lag_deg=lambda r: 20.0 * r.frequency_hz / 2.5, spread=lambda r: 1e-4)
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5, "frequency_hz": 2.5})
    cfg["detect"]["encoder_step_rad"] = 1e-9
    t, _ = ts.replay(ts.SearchTune(cfg, fs_hz=FS, k_fc_limit_v=2.0), plant)
    assert [(c["from_hz"], c["to_hz"]) for c in t["frequency_changes"]] == [(2.5, 1.25), (1.25, 0.625)]
    assert t["frequency_hz"] == 0.625 and t["search"]["converged"]


# ---- the budget's second lag step, the 5 % repeat rule, the |H_1| range of an unconverged search ----

class _Sequence(_Probe):
    """The stand-in probe answering each tag from a list, in order."""

    def measure(self, tag, kfc, kv=0.0, amplitude=None, repeat=False):
        self.asked.append((tag, kfc, kv, amplitude, repeat))
        return self.points[tag].pop(0)
        yield


@pytest.mark.parametrize("s_second, expected", [(0.024, "series"), (-0.032, "step"), (0.05, "inf")])
def test_budget_second_lag_step_bounds_what_is_left(s_second, expected):
    # the first K_v step moves K_fc* by 4.2 % (s 0.04 along the slope -8 / V): a second one at the
    # new root; the same way with the ratio q of the steps: the series' rest q / (1 - q) bounds what
    # is left (at least the step); the other way: the step; q >= 1: no bound (inf)
    a1, k1, w, slope = 0.5, 0.1187, 2 * math.pi * 1.25, -8.0
    h1 = 0.97 * np.exp(-1j * math.radians(3.0))
    kv = 1.0 / w - 4 * k1 / (math.pi * 0.97 * a1 * w)
    lag = [_point(k1, _periods(0.98 * np.exp(-1j * 0.01), [0.0400, 0.0401, 0.0399], PHASES), a1, kv=kv),
           _point(k1, _periods(0.98 * np.exp(-1j * 0.01), [s_second, s_second + 1e-4, s_second - 1e-4], PHASES),
                  a1, kv=kv)]
    probe = _Sequence(a1, {"lag": lag, "amplitude2": [_second()]})
    out, _ = _budget(probe, p_star_over={"H": np.concatenate([[h1], np.zeros(6)]), "u_over_y": 0.4 + 1.0j})
    k_a = float(np.float32(k1))
    k_b = k_a - 0.04 / slope
    k_c = float(np.float32(k_b)) - s_second / slope
    assert [x[0] for x in probe.asked] == ["lag", "lag", "amplitude2"]
    assert probe.asked[1][1] == pytest.approx(k_b, rel=1e-12)
    step1, step2 = k_b - k1, k_c - k_b
    q = abs(step2) / abs(step1)
    part = out["parts"]["viscous"]
    if expected == "series":
        assert 0 < q < 1 and part == pytest.approx(abs(step2) * q / (1 - q), rel=1e-6)
    elif expected == "step":
        assert step1 * step2 < 0 and part == pytest.approx(abs(step2), rel=1e-6)
    else:
        # (the budget used to skip the infinite part: a diverging correction passed as converged)
        assert q >= 1 and math.isinf(part) and math.isinf(out["sigma_total"])
        assert not out["sigma_total"] <= ts.MAX_SIGMA_RE_K_FC * abs(out["k_fc"])       # refused
    roots = [st["root"] for st in out["viscous"]["steps"]]
    assert roots == [pytest.approx(k_b, rel=1e-9), pytest.approx(k_c, rel=1e-9)]


@pytest.mark.parametrize("away, repeated", [(0.055, True), (0.045, False)])
def test_budget_repeats_the_first_experiment_when_the_second_amplitude_is_5_percent_away(away, repeated):
    # K_fc* at 0.3 rad `away` of K_fc* from the first amplitude's, within twice their noise: the
    # repeat comes from the 5 % rule alone (the search's noise below 10 times the second's and 1 %)
    a1, a2, k1, slope, q_enc = 0.5, 0.3, 0.1187, -8.0, 2 * math.pi / 4096
    h1_star, h1_two = 0.97 * np.exp(-1j * 0.015), 0.95 * np.exp(-1j * 0.021)
    k_a = float(np.float32(k1))
    slope2 = slope * a1 * abs(h1_star) / (a2 * abs(h1_two))
    s2 = (k_a - k1 * (1 + away)) * slope2
    spread = np.array([-0.09, 0.06, -0.03, 0.06])            # its se: sigma2 about 3.7 mV
    s_two = s2 + spread
    sigma2 = s_two.std(ddof=1) / 2 / abs(slope2) * _t95(3)
    sig1 = 1e-3
    assert 2 * math.hypot(sig1, sigma2) > away * k1 and sig1 < min(10 * sigma2, 0.01 * k1)
    phases = PHASES
    p0 = _point(0.0, _periods(0.9, [0.030, 0.031, 0.029], phases), a1)
    first = _point(0.3, _periods(0.93, [-0.020, -0.021, -0.019], phases), a1)
    p_star = _point(k1, _periods(h1_star, [1e-4, -2e-4, 3e-4], phases), a1, noise=2e-4)
    two = _point(k1, _periods(h1_two, s_two, phases), a2)
    probe = _Probe(a1, {"amplitude2": two, "repeat": first})
    cfg = {"tune": {"frequency_hz": 1.25, "amplitude_max_rad": 0.5}, "detect": {"encoder_step_rad": q_enc},
           "limits": {}}
    outcome = tuning.KfcSearchResult(k_fc=k1, sigma=sig1, converged=True, reason="", n_experiments=5,
                                     bracket=(0.1, 0.14), extended_to=None, regime="signed root",
                                     sigma_signed=1e-3, slope=slope, phases=phases, sigma_fit=0.0)
    out = _run(ts._budget(ts._Context(cfg, 2560.0, "raw", 5.0, {}), probe, outcome,
                          {0.0: p0, k1: p_star, 0.3: first}, {"alternative_rad": a2}))
    assert out["cause"] is None, out["cause"]
    assert out["k_fc_at_amplitude"]["k_fc"][1] == pytest.approx(k1 * (1 + away), rel=1e-9)
    assert ("repeat" in [x[0] for x in probe.asked]) is repeated and (out["repeat"] is not None) is repeated
    # the encoder floor at the smaller amplitude 0.3 rad, through the slope there (A1 / A2 steeper)
    ds = (q_enc / a2) ** 1.5 / math.pi * math.exp(-2 * math.pi ** 2 * (2e-4 / q_enc) ** 2)
    assert out["parts"]["encoder"] == pytest.approx(ds / abs(slope * a1 / a2), rel=1e-9)
    # a pure sign: no smoothing part, and said so
    assert out["parts"]["smoothed_sign"] == 0.0 and out["fc_smooth"]["note"] == "pure sign (fc_smooth 0)"
    assert out["fc_smooth"]["velocity_peak_rad_s"] == pytest.approx(2 * math.pi * 1.25 * a2)


def test_unconverged_search_far_from_the_sine_names_its_h1_range():
    pts = {}
    for k, s_k, g in ((0.0, [0.03, 0.031, 0.029], 0.70), (0.11, [0.001, 0.0012, 0.0009], 0.65),
                      (0.2, [-0.02, -0.021, -0.019], 0.60)):
        pts[k] = _point(k, _periods(g * np.exp(-1j * 0.05), s_k, PHASES), 0.5)
        pts[k]["lag_deg"] = math.degrees(0.05)
    cause, text = _run(ts._diagnose_search(_Probe(0.5, {}), SimpleNamespace(cause="not verified"), pts, 0.0))
    assert cause == "loop lag"
    assert text.startswith("the loop cannot follow the 1.25 Hz sine: the motor moves 0.65 times the reference at "
                           "K_fc = 0.11 V (the smallest ratio; |H_1| 0.7 .. 0.6 over the search)")


@pytest.mark.parametrize("s_first, steps", [(0.0288, 2), (0.021, 1)])
def test_budget_lag_step_is_repeated_only_beyond_twice_its_noise(s_first, steps):
    # the first K_v step 3.6 mV (s 0.0288 along -8 / V; 3 % of K_fc*) with its s noisy (se 11.5e-3):
    # above 2 se / |slope| = 2.9 mV, a second experiment; 2.6 mV (s 0.021), within it, not
    a1, k1, w, slope = 0.5, 0.1187, 2 * math.pi * 1.25, -8.0
    h1 = 0.97 * np.exp(-1j * math.radians(3.0))
    kv = 1.0 / w - 4 * k1 / (math.pi * 0.97 * a1 * w)
    s_lag = np.array([s_first - 0.02, s_first, s_first + 0.02])
    se = s_lag.std(ddof=1) / math.sqrt(3)
    step = s_first / abs(slope)
    assert (step > 2 * se / abs(slope)) == (steps == 2) and step > 0.02 * k1
    lag = [_point(k1, _periods(0.98 * np.exp(-1j * 0.01), s_lag, PHASES), a1, kv=kv) for _ in range(2)]
    probe = _Sequence(a1, {"lag": lag, "amplitude2": [_second()]})
    out, _ = _budget(probe, p_star_over={"H": np.concatenate([[h1], np.zeros(6)]), "u_over_y": 0.4 + 1.0j})
    assert [x[0] for x in probe.asked] == ["lag"] * steps + ["amplitude2"]


def test_phases_from_the_bracket_when_the_search_gave_no_falling_slope():
    # phases given, but the slope not finite or not negative: the bracket's ends decide
    a, b = 0.08, 0.16
    pa = _point(a, _periods(0.9, [0.021, 0.019, 0.020], PHASES), 0.5)
    pb = _point(b, _periods(0.93, [-0.012, -0.010, -0.0115], PHASES), 0.5)
    for slope in (math.nan, 0.3):
        outcome = SimpleNamespace(phases=np.array([1.0, 1.0, 1.0]), slope=slope, bracket=(a, b))
        phases, got = ts._phases_and_slope(_Probe(0.5, {}), outcome, {a: pa, b: pb})
        assert np.angle(np.exp(1j * (phases - PHASES))) == pytest.approx(np.zeros(3), abs=1e-9)
        assert got == pytest.approx((-0.0335 / 3 - 0.060 / 3) / (b - a), rel=1e-9)
    outcome = SimpleNamespace(phases=np.array([1.0, 1.0, 1.0]), slope=-2.0, bracket=(a, b))
    phases, got = ts._phases_and_slope(_Probe(0.5, {}), outcome, {a: pa, b: pb})
    assert list(phases) == [1.0, 1.0, 1.0] and got == -2.0


@pytest.mark.parametrize("share, motion", [(0.5, False), (math.nextafter(0.5, 1.0), True)])
def test_spread_text_from_samples_at_half_the_power_in_a_few_lines(monkeypatch, share, motion):
    monkeypatch.setattr(ts, "spread_concentration", lambda y, top=0.01: share)
    rec = SimpleNamespace(signals={"motor_angle": np.zeros(3 * 64)}, stats=None)
    text = ts._spread_text(SimpleNamespace(n=64), {"record": rec, "kfc": 0.1})
    assert (text is not None) is motion
    if motion:
        assert "(its spectrum is not flat: 50 % of its power in 1 % of the frequencies)" in text


def test_period_drift_reads_every_usable_experiment_either_way():
    slope, k = -2.0, 0.1
    up = [[0.01, 0.0106], [-0.002, -0.0014, -0.0008], [0.003, 0.0036], [-0.05, -0.0494]]
    drifting, rate = ts.period_drift(up, slope, k)
    assert drifting and rate == pytest.approx(3e-3)                       # upward: +0.3 % per period
    # one experiment the other way: no drift, even with the mean rate (+0.23 %) above DRIFT_MIN_REL
    mixed, rate = ts.period_drift(up + [[0.04, 0.0399]], slope, k)
    assert mixed is False and rate == pytest.approx((4 * 6e-4 - 1e-4) / 5 / 2 / 0.1)
    # an experiment of one period or with a NaN period says nothing: left out (3 left: too few)
    assert ts.period_drift(up[:3] + [[0.02], [0.01, np.nan]], slope, k) == (False, pytest.approx(np.nan, nan_ok=True))
    assert ts.period_drift(up + [[0.02], [0.01, np.nan]], slope, k) == (True, pytest.approx(3e-3))
    # no slope or no K_fc*: no rate
    for sl, kk in ((0.0, k), (math.nan, k), (slope, 0.0)):
        drifting, rate = ts.period_drift(up, sl, kk)
        assert drifting is False and math.isnan(rate)


def test_lag_sides_take_the_points_clear_of_their_noise_without_k_v():
    # s at K_fc = 0 positive (under-compensated): below the root the points with s > 0, above
    # those with s < 0, each beyond 2 standard errors; a point within them, or with another
    # K_v, sides with neither
    def pt(k, s_mean, lag, kv=0.0, spread=1e-4):
        p = _point(k, _periods(0.95, [s_mean - spread, s_mean, s_mean + spread], PHASES), 0.5, kv=kv)
        p["lag_deg"] = lag
        return p

    by_k = {0.0: pt(0.0, 0.03, 20.0), 0.05: pt(0.05, 0.012, 15.0), 0.1: pt(0.1, 0.0002, 12.0, spread=3e-4),
            0.15: pt(0.15, -0.01, 9.0), 0.2: pt(0.2, -0.02, 7.0), 0.12: pt(0.12, 0.004, 11.0, kv=0.05)}
    assert ts._lag_sides(_Probe(0.5, {}), by_k) == ([20.0, 15.0], [9.0, 7.0])
    # K_fc = 0 not clear of its noise: no sides
    by_k[0.0] = pt(0.0, 0.0003, 20.0, spread=5e-4)
    assert ts._lag_sides(_Probe(0.5, {}), by_k) == ([], [])


# ---- the mutation run's last survivors: edges of the sweep, the halvings, the protocol ------------

def test_sweep_optimum_crossing_between_the_last_two_points_and_no_wrap_at_the_first():
    k = np.array([0.0, 0.1, 0.2, 0.3])
    s = np.array([0.5, 0.3, 0.02, -0.1])                   # the smallest ratio one before the end
    assert ts.sweep_optimum(k, np.abs(s), s)[0] == pytest.approx(0.2 + 0.1 * 0.02 / 0.12, rel=1e-12)
    # the smallest ratio at K_fc = 0 with s <= 0 there: the grid minimum, never a crossing to the
    # other end of the sweep
    s = np.array([-0.01, -0.3, -0.5, 0.05])
    assert ts.sweep_optimum(k, np.abs(s), s) == (
        0.0, "grid minimum of the ratio (no sign change of the signed objective there)")


def test_repeat_for_the_search_noise_needs_one_percent_of_k_fc_too():
    # the search's noise 20 times the second amplitude's but below 1 % of K_fc*: no repeat
    a1, a2, k1, slope = 0.5, 0.25, 0.1187, -8.0
    h1_star, h1_two = 0.97 * np.exp(-1j * 0.015), 0.95 * np.exp(-1j * 0.021)
    s_two = np.array([0.0015, 0.0017, 0.0014, 0.0016])
    slope2 = slope * a1 * abs(h1_star) / (a2 * abs(h1_two))
    sigma2 = s_two.std(ddof=1) / 2 / abs(slope2) * _t95(3)
    sig1 = 20 * sigma2
    assert sig1 < 0.01 * k1
    p0 = _point(0.0, _periods(0.9, [0.030, 0.031, 0.029], PHASES), a1)
    first = _point(0.3, _periods(0.93, [-0.020, -0.021, -0.019], PHASES), a1)
    probe = _Probe(a1, {"amplitude2": _point(k1, _periods(h1_two, s_two, PHASES), a2), "repeat": first})
    cfg = {"tune": {"frequency_hz": 1.25, "amplitude_max_rad": 0.5}, "detect": {"encoder_step_rad": 1e-9},
           "limits": {}}
    outcome = tuning.KfcSearchResult(k_fc=k1, sigma=sig1, converged=True, reason="", n_experiments=5,
                                     bracket=(0.1, 0.14), extended_to=None, regime="signed root",
                                     sigma_signed=1e-3, slope=slope, phases=PHASES, sigma_fit=0.0)
    p_star = _point(k1, _periods(h1_star, [1e-4, -2e-4, 3e-4], PHASES), a1, noise=2e-4)
    out = _run(ts._budget(ts._Context(cfg, 2560.0, "raw", 5.0, {}), probe, outcome,
                          {0.0: p0, k1: p_star, 0.3: first}, {"alternative_rad": a2}))
    assert out["cause"] is None and out["repeat"] is None and [x[0] for x in probe.asked] == ["amplitude2"]


def test_two_halvings_by_default_then_refused_where_the_loop_still_lags():
    # 40 deg at 2.5 Hz: 20 deg expected at 1.25 Hz (skipped), 0.625 Hz is the second and last
    # halving: 10 deg there, refused (a third halving is not made)
    plant = _Plant(lag_deg=lambda r: 40.0 * r.frequency_hz / 2.5, spread=lambda r: 1e-4)
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5, "frequency_hz": 2.5})
    cfg["detect"]["encoder_step_rad"] = 1e-9
    t, _ = ts.replay(ts.SearchTune(cfg, fs_hz=FS, k_fc_limit_v=2.0), plant)
    assert [(c["from_hz"], c["to_hz"]) for c in t["frequency_changes"]] == [(2.5, 1.25), (1.25, 0.625)]
    assert t["frequency_hz"] == 0.625 and t["search"]["cause"] == "loop lag"
    assert t["search"]["loop_lag_deg"] == pytest.approx(10.0, rel=1e-3)


def test_halvings_end_at_one_cycle_in_the_longest_period():
    # 0.625 Hz is 1 cycle in 4096 samples: 0.3125 Hz (8192 samples) is the lowest; the lag
    # scaled there (20 deg) is still too large, but no lower frequency exists: tuned (refused) there
    plant = _Plant(lag_deg=lambda r: 40.0 * r.frequency_hz / 0.625, spread=lambda r: 1e-4)
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5})
    cfg["detect"]["encoder_step_rad"] = 1e-9
    t, _ = ts.replay(ts.SearchTune(cfg, fs_hz=FS, k_fc_limit_v=2.0, max_halvings=2), plant)
    assert [(c["from_hz"], c["to_hz"]) for c in t["frequency_changes"]] == [(0.625, 0.3125)]
    assert t["frequency_hz"] == 0.3125 and t["search"]["cause"] == "loop lag"


def test_a_smoothing_wider_than_the_peak_velocity_is_bounded_at_999_percent():
    f, a = 0.625, 0.5
    v_peak = 2 * math.pi * f * a
    pts = {}
    for k, s_k in ((0.0, [0.03, 0.031, 0.029]), (0.11, [0.001, 0.0012, 0.0009]), (0.2, [-0.02, -0.021, -0.019])):
        pts[k] = _point(k, _periods(0.97 * np.exp(-1j * 0.03), s_k, PHASES), a)
        pts[k]["lag_deg"], pts[k]["fc_smooth"] = math.degrees(0.03), 1.2 * v_peak
    cause, text = _run(ts._diagnose_search(_Probe(a, {}, frequency_hz=f), SimpleNamespace(cause="x"), pts, 0.0))
    assert cause == "smoothed sign" and math.isinf(tuning.smoothed_sign_bias(1.2 * v_peak, v_peak))
    # (a person reads "120 %", not "1.2e+02 %")
    assert "sign over fc_smooth = 2.35619 rad/s, 120 % of the sine's peak velocity" in text
    assert "(offset bound 999 %)" in text


def test_period_drift_of_a_search_without_phases_is_none():
    outcome = SimpleNamespace(phases=None, slope=math.nan, bracket=(math.nan, math.nan), k_fc=0.1)
    drifting, rate = ts._period_drift(_Probe(0.5, {}), outcome, {})
    assert drifting is False and math.isnan(rate)


def test_requests_number_from_zero_and_the_model_tune_takes_its_facts_by_name():
    req = ts.ExperimentRequest(key="k", tag="search", amplitude_rad=0.5, gains={}, frequency_hz=0.625,
                               period_samples=4096, cycles=1, settle_periods=2, periods=2, stats={})
    assert req.index == 0
    cfg = bench_tune.tune_config({"method": "model"})
    with pytest.raises(TypeError):
        ts.ModelTune(cfg, 2560.0)
    assert ts.ModelTune(cfg=cfg, fs_hz=2560.0).ask().tag == "identify"


@pytest.mark.parametrize("share, text", [(0.00532, "0.53 %"), (0.443, "44 %"), (0.994, "99 %"),
                                         (0.996, "100 %"), (1.2, "120 %"), (12.34, "1234 %")])
def test_a_percentage_for_a_person_has_no_exponent(share, text):
    assert ts._percent(share) == text
