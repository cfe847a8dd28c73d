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
from test_pins_tune_2 import _Probe, _periods, _point, _run, _t95  # noqa: E402
from test_tune_honest import _sat_cos_coefficient  # noqa: E402

FS = 2560.0
ODD = ((3, 0.4), (5, -0.9), (7, 1.7))       # (order, phase) of the plant's odd harmonics


class _Plant:
    """A closed loop that follows the sine with gain ``gain(A)`` and lag ``lag_deg(kv)``, plus
    odd harmonics of ``h_scale`` (Fc - K_fc) rad (the relay's 4 / (k pi) pattern) and, per
    experiment, a period-to-period deviation of rms ``spread(request)`` rad (white, or with
    ``ring`` the share of one non-harmonic line) with the harmonic lines cut out of it, so the
    HOSIDFs stay exact. ``records``: the record of each request key."""

    def __init__(self, fc=0.1157, gain=lambda a: 0.98, lag_deg=lambda kv: 0.6, spread=lambda req: 0.0,
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
        lag = math.radians(self.lag_deg(kv))
        y = a * self.gain(a) * np.sin(w * t - lag)
        for k, phi in ODD:
            y = y + self.h_scale * 4 / (k * math.pi) * (self.fc - kfc) * np.sin(k * (w * t - lag) + phi)
        rng = np.random.default_rng([7, int(round(kfc * 1e7)), int(round(kv * 1e7)), int(round(a * 1e4))])
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
    return next(r for key, r in plant.records.items() if key.startswith("tune-") and "-kfc0-kv0" in key
                and (f"-a{amplitude:.6g}" in key or "-a" not in key))


# ---- the angle-noise check after a converged search: its figures, white against motion ----------

def test_white_spread_above_two_percent_is_named_noise_with_its_measured_share():
    # 4.94 % of 0.5 rad at K_fc = 0, more in the search's experiments (the lower is read)
    plant = _Plant(spread=lambda r: 0.0494 * r.amplitude_rad * (1 + r.gains["kfc"]))
    t = _tune(plant, {"amplitude_rad": 0.5})
    s = t["search"]
    assert not s["converged"] and s["cause"] == "noise"
    noise = _spread_rad(_zero_record(plant, 0.5), 4096)
    assert noise == pytest.approx(0.0494 * 0.5, rel=1e-3)
    assert s["stop_reason"].startswith(
        f"the angle noise ({noise:.2g} rad, spread over the recorded periods) is {100 * noise / 0.5:.2g} % of "
        f"the sine amplitude 0.5 rad: it dithers the friction")
    assert f"{100 * noise / 0.5:.2g}" == "4.9"
    assert f"raise tune.amplitude_rad to >= {noise / 0.02:.2g} rad or set it to auto" in s["stop_reason"]
    assert "settle_periods" not in s["stop_reason"]     # (the hint of the statistics' reading)


@pytest.mark.parametrize("ring, cause", [(0.0, "noise"), (0.45, "noise"), (0.55, "unsettled"), (0.9, "unsettled")])
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


def test_spread_the_same_in_rad_at_both_amplitudes_is_noise():
    # 8 mV .. 12.5 mrad: it did not double from 0.25 to 0.5 rad: measurement noise
    plant = _auto_plant(0.008)
    t = _tune(plant, {"amplitude_start_rad": 0.25, "amplitude_max_rad": 0.5})
    n_lo, n_hi = _spread_rad(_zero_record(plant, 0.25), 4096), _spread_rad(_zero_record(plant, 0.5), 4096)
    assert n_lo < n_hi <= 2 * n_lo
    assert t["search"]["cause"] == "noise" and t["search"]["stop_reason"].startswith(f"the angle noise ({n_hi:.2g}")
