"""tune where the loop is slow, the sign smoothed and the plant drifting (issue 32): never
converged and wrong, every unconverged stop names its real cause. One test per row of the
issue; each runs `fftune tune`'s logic on the firmware core + plant (tests/bench/bench_tune.py,
about 0.3 s a row)."""
import math
import os
import sys

import numpy as np
import pytest

from fftune.analysis import tune_strategy, tuning
from fftune.host import experiments as ex

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "bench"))
import bench_tune  # noqa: E402


def _row(tmp_path, plant, tune=None, name="r"):
    return bench_tune.run_row(plant, dict(tune or {}, capture="raw"), str(tmp_path / name))


def _ok(t):
    """Converged within max(2 %, 2 sigma_total) of the truth at the tune's end."""
    s = t["search"]
    return abs(t["k_fc_star"] - t["true_coulomb_v"]) <= max(0.02 * t["true_coulomb_v"], 2 * s["sigma_v"])


def test_slow_loop_is_refused_at_its_frequency_and_tuned_at_half(tmp_path, monkeypatch):
    # kp 0.2: the motor lags the sine by 14 deg because of the loop (K_v does not remove it);
    # today's main reported -11 % with sigma 3.9 % (converged, wrong)
    plant = {"controller": {"kp": 0.2}}
    t = _row(tmp_path, plant)
    s = t["search"]
    assert s["converged"] and _ok(t)
    ch = t["frequency_changes"]
    assert ch[0]["from_hz"] == 0.625 and ch[0]["to_hz"] == pytest.approx(0.3125)
    assert "cannot follow" in ch[0]["reason"] and "lags the reference by 14" in ch[0]["reason"]
    assert t["frequency_hz"] == pytest.approx(0.3125) and 0 < s["experiments_at_other_frequencies"] < s["experiments"]
    # at the configured frequency alone: refused, the cause named, no value that is no estimate
    monkeypatch.setattr(ex, "tune", ex.tune_at_frequency)
    t1 = _row(tmp_path, plant, name="one")
    s1 = t1["search"]
    assert not s1["converged"] and s1["cause"] == "loop lag"
    assert s1["loop_lag_deg"] > tuning.LOOP_LAG_MAX_DEG and "noise" not in s1["stop_reason"]
    assert t1["k_fc_star"] is None and t1["k_fc_best_measured"] is None


def test_loop_lag_part_is_the_quadratic_bound_of_the_lag_left(tmp_path):
    # kp 0.4: 5.4 deg left after the viscous feed-forward; the part is 1.2e-3 lag^2 K_fc*
    t = _row(tmp_path, {"controller": {"kp": 0.4}})
    s = t["search"]
    assert s["converged"] and _ok(t)
    lag = s["loop_lag_deg"]
    assert 4.0 < lag < tuning.LOOP_LAG_MAX_DEG
    assert s["sigma_parts_v"]["loop_lag"] == pytest.approx(1.2e-3 * lag ** 2 * t["k_fc_star"], rel=1e-6)
    # it covers the bias the lag leaves (today: +3.8 % against a sigma of 1.1 %)
    assert abs(t["k_fc_star_error_re_truth"]) * t["true_coulomb_v"] <= 2 * s["sigma_v"]


def test_loop_lag_part_formula_and_limit():
    assert tuning.loop_lag_part(3.0, 0.2) == pytest.approx(1.2e-3 * 9 * 0.2)
    assert tuning.loop_lag_part(-5.0, 0.1) == pytest.approx(1.2e-3 * 25 * 0.1)    # a lead counts the same
    assert math.isinf(tuning.loop_lag_part(7.5, 0.1)) and math.isinf(tuning.loop_lag_part(float("nan"), 0.1))


def test_fast_sine_first_stop_names_the_loop_not_the_noise(tmp_path, monkeypatch):
    # 2.5 Hz: today "max_experiments reached ... (noise)" and a best measured K_fc 97 % low
    monkeypatch.setattr(ex, "tune", ex.tune_at_frequency)
    t = _row(tmp_path, {}, {"frequency_hz": 2.5})
    s = t["search"]
    assert not s["converged"] and s["cause"] == "loop lag"
    assert "cannot follow the 2.5 Hz sine" in s["stop_reason"] and "(noise)" not in s["stop_reason"]
    assert t["k_fc_best_measured"] is None and "no estimate" in t["k_fc_best_measured_note"]


def test_fast_sine_is_tuned_at_a_frequency_the_loop_follows(tmp_path):
    t = _row(tmp_path, {}, {"frequency_hz": 2.5})
    assert t["search"]["converged"] and _ok(t)
    assert [c["to_hz"] for c in t["frequency_changes"]][0] == pytest.approx(1.25)


def test_fc_smooth_is_read_recorded_and_a_wide_one_refused(tmp_path):
    # fc_smooth 1 rad/s (51 % of the sine's peak velocity): today converged +8 % (sigma 1.3 %)
    t = _row(tmp_path, {"controller": {"fc_smooth": 1.0}})
    s = t["search"]
    assert t["drive_settings"]["fc_smooth"] == pytest.approx(1.0)
    assert not s["converged"] and s["cause"] == "smoothed sign"
    assert "smoothed_sign" in s["stop_reason"] and t["k_fc_star"] is None


def test_a_narrow_fc_smooth_is_carried_as_its_bound(tmp_path):
    t = _row(tmp_path, {"controller": {"fc_smooth": 0.2}})
    s = t["search"]
    assert s["converged"] and _ok(t)
    fs = s["budget"]["fc_smooth"]
    amps = s["budget"]["k_fc_at_amplitude"]["amplitude_rad"]
    v = 2 * math.pi * 0.625 * min(amps)
    assert fs["width_rad_s"] == pytest.approx(0.2) and fs["velocity_peak_rad_s"] == pytest.approx(v)
    assert s["sigma_parts_v"]["smoothed_sign"] == pytest.approx(
        tuning.smoothed_sign_bias(0.2, v) * t["k_fc_star"], rel=1e-6)
    # pure sign: no part
    t0 = _row(tmp_path, {}, name="pure")
    assert t0["drive_settings"]["fc_smooth"] == 0.0 and t0["search"]["sigma_parts_v"]["smoothed_sign"] == 0.0


def _sat_cos_coefficient(rho, k):
    """a_k of sat(cos t / rho) by quadrature (the relay's is 4 / (k pi) (-1)^((k-1)/2))."""
    from scipy.integrate import quad
    f = lambda t: np.clip(np.cos(t) / rho, -1, 1) * np.cos(k * t)  # noqa: E731
    brk = [math.acos(min(1.0, rho))] if rho < 1 else []
    return 2 / math.pi * quad(f, 0, math.pi, points=brk + [math.pi - b for b in brk], limit=200)[0]


@pytest.mark.parametrize("rho", [0.07, 0.3, 0.45])
def test_smoothed_sign_bias_against_quadrature(rho):
    ks = (3, 5, 7)
    c = [_sat_cos_coefficient(rho, k) / (4 / (k * math.pi) * (-1) ** ((k - 1) // 2)) for k in ks]
    num = sum(abs(ck) / k for ck, k in zip(c, ks))
    den = sum(math.copysign(1, ck) / k for ck, k in zip(c, ks))
    expected = abs(den / num - 1)
    assert tuning.smoothed_sign_bias(rho * 2.3, 2.3) == pytest.approx(expected, rel=1e-3)
    assert tuning.smoothed_sign_bias(0.0, 2.3) == 0.0


def test_friction_step_during_the_second_amplitude_is_named_non_stationary(tmp_path):
    # -20 % at 30 s, inside the second-amplitude experiment: today read as amplitude
    # dependence ("cannot tell K_fc* better than +-30 %: the largest part is 'amplitude'")
    t = _row(tmp_path, {"drift": {"coulomb_step": -0.2, "coulomb_step_time_s": 30.0}})
    s = t["search"]
    assert not s["converged"] and s["cause"] == "non-stationary"
    assert "changed during the tune" in s["stop_reason"] and "no amplitude dependence" in s["stop_reason"]
    assert t["true_coulomb_v"] == pytest.approx(0.8 * t["true_coulomb_v_at_start"], rel=1e-6)


def test_friction_ramp_during_the_tune_is_right_for_its_end_or_named(tmp_path):
    t = _row(tmp_path, {"drift": {"coulomb_ramp": 0.3, "coulomb_ramp_start_s": 0.0, "coulomb_ramp_end_s": 40.0}})
    s = t["search"]
    assert t["true_coulomb_v"] > 1.25 * t["true_coulomb_v_at_start"]
    assert (s["converged"] and _ok(t)) or s["cause"] == "non-stationary"


def test_drift_between_and_halved_frequency():
    assert tuning.drift_between(0.100, 0.104, 0.001, 0.0008) == (True, pytest.approx(0.004))
    assert tuning.drift_between(0.100, 0.1035, 0.001, 0.0008)[0] is False     # 3.5 mV < 3 x 1.28 mV
    assert tuning.drift_between(0.100, 0.1009, 0.0, 0.0, floor=0.001)[0] is False
    # a repeat without a K_fc* (NaN: its search failed) is no evidence of a drift
    changed, d = tuning.drift_between(0.100, float("nan"), 0.001, 0.0008)
    assert changed is False and math.isnan(d)
    assert tuning.halved_frequency(4096, 4) == (4096, 2)
    assert tuning.halved_frequency(4096, 3) == (8192, 3)
    assert tuning.halved_frequency(8192, 1) is None


def _h(k_fc, fc=0.1157, jump=0.0):
    h = np.zeros(7, dtype=complex)
    h[0] = 2.0
    for k in (3, 5, 7):
        h[k - 1] = (-1) ** ((k - 1) // 2) * 4 * (fc - k_fc) / (k * math.pi) + jump * (1 if k == 3 else 0)
    return h


def test_search_does_not_blame_the_noise_for_a_plant_that_changes():
    # a plant whose friction jumps between experiments (noise-free): not the noise
    calls = []

    def jumping(k):
        calls.append(k)
        fc = 0.1157 * (1 + 0.25 * (len(calls) % 2))
        return np.repeat(_h(k, fc)[None, :], 3, axis=0) + 1e-9 * np.arange(3)[:, None]

    res = tuning.KfcSearch(0.0, 0.3, max_experiments=6).run(jumping)
    assert not res.converged and res.cause == "not verified" and "not because of the noise" in res.reason


# ---- issue 32, the reviewer's hidden families (tests/bench/bench_tune_matrix.py --hidden) ----

def test_exponential_drift_inside_the_tune_is_named_not_converged_off(tmp_path):
    # -40 % with tau 15 s from the tune's start: on main converged +8.9 % off the final level
    # with sigma 1.9 % (the second amplitude agreed within its noise, no repeat was asked)
    t = _row(tmp_path, {"drift": {"coulomb_exp": -0.4, "coulomb_exp_start_s": 0.0, "coulomb_exp_tau_s": 15.0},
                        "sensor": {"noise_std": 1e-3, "seed": 4}})
    s = t["search"]
    assert t["true_coulomb_v"] < 0.7 * t["true_coulomb_v_at_start"]
    assert (s["converged"] and _ok(t)) or s["cause"] == "non-stationary"
    assert not s["converged"] and "changed during the tune" in s["stop_reason"]
    assert s["period_drift"]["repeated"] and s["period_drift"]["rate_re_k_fc_per_period"] < 0
    assert t["k_fc_best_measured"] is None


def test_a_stationary_plant_brings_no_repeat(tmp_path):
    t = _row(tmp_path, {"sensor": {"noise_std": 2e-3, "seed": 1}})
    s = t["search"]
    assert s["converged"] and _ok(t) and s["period_drift"]["repeated"] is False


def test_period_drift_rule():
    slope, k = -2.0, 0.1
    # every experiment falls by 6e-4 per period: 6e-4 / 2 / 0.1 = 0.3 % of K_fc* per period
    down = [[0.01, 0.0094], [-0.002, -0.0026, -0.0032], [0.003, 0.0024], [-0.05, -0.0506]]
    drifting, rate = tune_strategy.period_drift(down, slope, k)
    assert drifting and rate == pytest.approx(-3e-3)
    # the mean over the experiments (per period: a 3-period experiment counts its mean step)
    assert tune_strategy.period_drift(down[:3] + [[-0.05, -0.0505]], slope, k)[1] == pytest.approx(
        (-6e-4 * 3 - 5e-4) / 4 / 2 / 0.1)
    # one experiment the other way: noise, not a drift
    mixed = down[:3] + [[-0.05, -0.0494]]
    assert tune_strategy.period_drift(mixed, slope, k)[0] is False
    # one way, but below DRIFT_MIN_REL of K_fc* per period
    small = [[x, x - 1e-5] for x in (0.01, 0.0, -0.01, 0.02)]
    assert tune_strategy.period_drift(small, slope, k)[0] is False
    # too few experiments
    assert tune_strategy.period_drift(down[:3], slope, k)[0] is False


def test_load_anti_resonance_names_the_loop_not_the_friction(tmp_path, monkeypatch):
    # k 0.05 N m/rad: the motor's anti-resonance sqrt(k / j2) at 2.5 Hz, the tuning frequency.
    # On main: "no motion ... the friction exceeds what the drive can give" (the auto amplitude
    # climbed to 8 rad into u_max); the motor moves 12 % of the sine at 0.5 and 2 rad alike
    plant = {"plant": {"k": 0.05}, "sensor": {"noise_std": 1e-3, "seed": 31}}
    monkeypatch.setattr(ex, "tune", ex.tune_at_frequency)
    t = _row(tmp_path, plant, {"frequency_hz": 2.5}, name="one")
    s = t["search"]
    assert not s["converged"] and s["cause"] == "loop lag"
    assert "cannot follow the 2.5 Hz sine" in s["stop_reason"] and "friction exceeds" not in s["stop_reason"]
    assert [p["amplitude_rad"] for p in t["amplitude"]["probes"]] == [0.5, 2.0]


def test_load_anti_resonance_is_tuned_at_a_lower_frequency(tmp_path):
    t = _row(tmp_path, {"plant": {"k": 0.05}, "sensor": {"noise_std": 1e-3, "seed": 31}}, {"frequency_hz": 2.5})
    assert t["search"]["converged"] and _ok(t)
    assert t["frequency_changes"][0]["to_hz"] == pytest.approx(1.25)


def test_loop_near_its_anti_resonance_names_the_loop_not_the_viscous_part(tmp_path, monkeypatch):
    # k 0.02 at 1.875 Hz (anti-resonance 1.59 Hz): the motor moves 0.65 times the sine; on
    # main "the largest part is 'viscous' ... check the plant's damping"
    monkeypatch.setattr(ex, "tune", ex.tune_at_frequency)
    t = _row(tmp_path, {"plant": {"k": 0.02}, "sensor": {"noise_std": 1e-3, "seed": 31}},
             {"frequency_hz": 1.875})
    s = t["search"]
    assert not s["converged"] and s["cause"] == "loop lag"
    assert "times the reference" in s["stop_reason"] and "outside 0.8 .. 1.25" in s["stop_reason"]


def test_lag_bound_from_either_side_of_the_root():
    # the lag falls as K_fc rises: above the root (s < 0) the lag is a lower bound of the
    # lag at K_fc*, below it (s > 0) an upper one
    assert tune_strategy.lag_bound_deg([26.0, 16.1], [14.6, 4.1]) == pytest.approx(14.6)
    assert tune_strategy.lag_bound_deg([8.6, 2.5], [-12.3]) == 0.0            # 0.4 deg at the root: no bound
    assert tune_strategy.lag_bound_deg([-9.0, -3.0], [-20.0]) == pytest.approx(-9.0)   # a lead of 9 deg or more
    assert tune_strategy.lag_bound_deg([], [float("nan")]) == 0.0


def test_sine_the_loop_cannot_follow_is_left_after_one_experiment(tmp_path, monkeypatch):
    # 2.5 Hz on the demo loop: without feed-forward the motor moves 2.07 times the reference
    # (its resonance; friction only holds a motor back). On main the search ran 10
    # experiments there, then 8 at 1.25 Hz (refused again) before 0.625 Hz
    monkeypatch.setattr(ex, "tune", ex.tune_at_frequency)
    t = _row(tmp_path, {}, {"frequency_hz": 2.5}, name="one")
    s = t["search"]
    assert not s["converged"] and s["cause"] == "loop lag" and s["experiments"] == 1
    assert "times the reference at 0.5 rad (more than 1.4" in s["stop_reason"]
    monkeypatch.undo()
    t = _row(tmp_path, {}, {"frequency_hz": 2.5})
    s = t["search"]
    assert s["converged"] and _ok(t) and s["experiments"] <= 8
    assert [c["to_hz"] for c in t["frequency_changes"]] == [pytest.approx(1.25)]


def test_slow_loop_is_left_once_the_lag_at_the_root_is_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr(tune_strategy, "LAG_BOUND_STOP", True)     # (off by default: make paper)
    # kp 0.1: K_fc = 0 lags 28 deg, the over-compensated top 0.3 V still 13 deg, so the lag at
    # K_fc* is 13 deg or more: the search stops there (main: 10 experiments at 0.625 Hz)
    monkeypatch.setattr(ex, "tune", ex.tune_at_frequency)
    t = _row(tmp_path, {"controller": {"kp": 0.1}}, name="one")
    s = t["search"]
    assert not s["converged"] and s["cause"] == "loop lag" and s["experiments"] <= 3
    assert s["loop_lag_bound_deg"] > tune_strategy.LAG_BOUND_MARGIN * tuning.LOOP_LAG_MAX_DEG
    assert s["loop_lag_deg"] == s["loop_lag_bound_deg"] and "deg or more at K_fc*" in s["stop_reason"]
    monkeypatch.undo()
    monkeypatch.setattr(tune_strategy, "LAG_BOUND_STOP", True)
    t = _row(tmp_path, {"controller": {"kp": 0.1}})
    assert t["search"]["converged"] and _ok(t) and t["search"]["experiments"] <= 12
    assert [c["to_hz"] for c in t["frequency_changes"]] == [pytest.approx(0.3125)]
    # off (the default): the same plant is still tuned right at 0.3125 Hz, after the lag
    # left at K_fc* at 0.625 Hz is judged by the budget
    monkeypatch.setattr(tune_strategy, "LAG_BOUND_STOP", False)
    t = _row(tmp_path, {"controller": {"kp": 0.1}}, name="off")
    assert t["search"]["converged"] and _ok(t)
    assert [c["to_hz"] for c in t["frequency_changes"]] == [pytest.approx(0.3125)]


def test_a_lag_bound_far_above_the_limit_leaves_the_frequency(tmp_path, monkeypatch):
    monkeypatch.setattr(tune_strategy, "LAG_BOUND_STOP", True)     # (off by default: make paper)
    # kp 0.2 at 1.25 Hz: the lag at K_fc* is bounded far above 14 deg after three experiments;
    # scaled to 0.625 Hz still above 7 deg: skipped, tuned at 0.3125 Hz (main: 0.625 Hz tried)
    # (at 1.25 Hz the search runs with a K_v pre-estimate, whose own lag takes no bound, so
    # 1.25 Hz ends on the K_v step's refusal and 0.625 Hz is tried, bounded after 5
    # experiments: the paper's set-up, whose leads at K_v 0.157 are K_v's, not the loop's,
    # would otherwise be refused at a frequency it tunes at)
    t = _row(tmp_path, {"controller": {"kp": 0.2}}, {"frequency_hz": 1.25})
    ch = t["frequency_changes"]
    assert [c["to_hz"] for c in ch] == [pytest.approx(0.625), pytest.approx(0.3125)]
    assert "deg or more at K_fc*" in ch[1]["reason"] or ch[1]["reason"].startswith("skipped: the lag")
    assert t["search"]["converged"] and _ok(t)


def test_lower_frequency_on_the_grid():
    assert tuning.lower_frequency(4096, 4) == (4096, 2)           # half the cycles
    assert tuning.lower_frequency(4096, 3) == (8192, 3)           # twice the period
    assert tuning.lower_frequency(8192, 3) == (8192, 1)           # odd cycles in the longest period: a third
    assert tuning.lower_frequency(8192, 5) == (8192, 2)
    assert tuning.lower_frequency(8192, 1) is None


def test_slow_loop_at_odd_cycles_in_the_longest_period_goes_lower(tmp_path, monkeypatch):
    # kp 0.3 at 0.9375 Hz (3 cycles in 8192 samples): no half on the grid; main ended there
    # with `loop lag`, now at 0.3125 Hz (a third), where the loop follows. Every experiment
    # run is counted once (main added the amplitude probes of a refused frequency twice)
    told = []
    real_tell = tune_strategy.SearchTune.tell
    monkeypatch.setattr(tune_strategy.SearchTune, "tell",
                        lambda self, req, m: (told.append(req.frequency_hz), real_tell(self, req, m))[1])
    t = _row(tmp_path, {"controller": {"kp": 0.3}}, {"frequency_hz": 0.9375, "period_samples": 8192})
    s = t["search"]
    assert s["converged"] and _ok(t)
    assert [c["to_hz"] for c in t["frequency_changes"]] == [pytest.approx(0.3125)]
    assert s["experiments"] == len(told)
    assert s["experiments_at_other_frequencies"] == sum(f == 0.9375 for f in told) >= 2


def test_two_viscous_steps_the_same_way_carry_the_rest_of_their_series(tmp_path):
    # kp 1 at 0.3125 Hz: K_v read at K_fc = 0 is 20 times the plant's; the lag correction's
    # two steps (2.3 %, then 1.4 % the same way) converge geometrically. On main the part was
    # the last step: K_fc* -3.5 % with sigma_total 1.7 % (converged, wrong)
    t = _row(tmp_path, {"controller": {"kp": 1.0}, "sensor": {"noise_std": 1e-3, "seed": 8}},
             {"frequency_hz": 0.3125, "period_samples": 8192})
    s = t["search"]
    assert s["converged"] and _ok(t)
    steps = s["budget"]["viscous"]["steps"]
    assert len(steps) == 2
    d1, d2 = (st["root"] - st["k_fc"] for st in steps)
    assert d1 * d2 > 0 and abs(d2) < abs(d1)
    q = d2 / d1
    assert s["sigma_parts_v"]["viscous"] == pytest.approx(max(abs(d2), abs(d2) * q / (1 - q)), rel=1e-9)


def test_line_variance_whiteness():
    rng = np.random.default_rng(3)
    flat = rng.exponential(1e-4, size=7)          # white noise: about equal at every line
    assert tune_strategy.line_variance_is_white(np.full(7, 2e-4))
    assert tune_strategy.line_variance_is_white(np.array([1.0, 1.2, 0.8, 1.1, 0.9, 9.9, 1.0]))
    assert not tune_strategy.line_variance_is_white(np.array([1.0, 1.2, 0.8, 1.1, 0.9, 10.2, 1.0]))
    assert tune_strategy.line_variance_is_white(flat) == (flat.max() <= 10 * np.median(flat))


def test_stats_spread_of_a_ringing_load_is_unsettled_not_noise(tmp_path, monkeypatch):
    # k 0.01 N m/rad at 0.625 Hz and 8 rad, drive statistics: the load rings (the third
    # harmonic at its 1.95 Hz resonance); main ended `noise` (after 1.25 Hz: "0.56 rad ... 6.9 %"),
    # the raw samples converge. The line variances are far from flat: the loop, not the sensor
    monkeypatch.setattr(ex, "tune", ex.tune_at_frequency)
    plant = {"plant": {"k": 0.01}, "sensor": {"noise_std": 1e-3, "seed": 31}}
    t = bench_tune.run_row(plant, {"frequency_hz": 0.625, "capture": "stats", "amplitude_rad": 8.0},
                           str(tmp_path / "s"))
    s = t["search"]
    assert not s["converged"] and s["cause"] == "unsettled"
    assert "is not flat" in s["stop_reason"] and "not measurement noise" in s["stop_reason"]


def test_resonant_loop_at_a_fixed_amplitude_is_the_loops_not_saturation(tmp_path, monkeypatch):
    # kp 5, kd 0.01 at 3.75 Hz, tune.amplitude_rad 0.5: the motor moves 5.8 times the sine and
    # the output sits at u_max. On main: `saturation` ("the friction plus the sine's demand ...")
    plant = {"controller": {"kp": 5.0, "kd": 0.01}, "sensor": {"noise_std": 1e-3, "seed": 3}}
    monkeypatch.setattr(ex, "tune", ex.tune_at_frequency)
    t = _row(tmp_path, plant, {"frequency_hz": 3.75, "amplitude_rad": 0.5}, name="one")
    s = t["search"]
    assert not s["converged"] and s["cause"] == "loop lag" and "near its resonance" in s["stop_reason"]
    assert "u_max in" in s["stop_reason"]
    monkeypatch.undo()
    # then lower: at 1.875 Hz the loop still rings from 3.75 Hz (main there: `noise`; the
    # spread's spectrum is one line): unsettled, then 0.9375 Hz
    t = _row(tmp_path, plant, {"frequency_hz": 3.75, "amplitude_rad": 0.5})
    s = t["search"]
    assert s["converged"] and _ok(t)
    ch = t["frequency_changes"]
    assert [c["to_hz"] for c in ch] == [pytest.approx(1.875), pytest.approx(0.9375)]
    assert ch[1]["reason"].startswith("the motor angle differs between the recorded periods")
    assert "not measurement noise" in ch[1]["reason"]


def test_spread_concentration_white_and_ringing():
    rng = np.random.default_rng(7)
    white = rng.normal(0, 1e-3, (2, 4096))
    share = tune_strategy.spread_concentration(white)
    assert 0.03 < share < 0.09                      # about 1 % (1 + ln 100) = 5.6 %
    t = np.arange(4096)
    ring = white + np.vstack([0.02 * np.sin(2 * np.pi * 37.3 * t / 4096), np.zeros(4096)])
    assert tune_strategy.spread_concentration(ring) > 0.9
    # the same motion in every period is no spread
    assert math.isnan(tune_strategy.spread_concentration(np.tile(np.sin(t / 50.0), (2, 1))))


def test_friction_step_inside_one_experiment_is_not_the_noise(tmp_path):
    # +50 % at 6 s, inside the K_fc = 0 experiment (0 .. 6.4 s) at 1 rad, drive statistics: on
    # main `noise` ("0.15 rad ... 15 % of the amplitude": that experiment's spread); the other
    # experiments see the new level, the raw samples converge
    t = bench_tune.run_row({"drift": {"coulomb_step": 0.5, "coulomb_step_time_s": 6.0}},
                           {"amplitude_rad": 1.0, "capture": "stats"}, str(tmp_path / "s"))
    s = t["search"]
    assert (s["converged"] and _ok(t)) or s["cause"] == "non-stationary"
    assert t["true_coulomb_v"] == pytest.approx(1.5 * t["true_coulomb_v_at_start"], rel=1e-6)


def test_stick_slip_spread_near_the_root_is_not_the_noise(tmp_path):
    # static x2, Stribeck 0.05 rad/s, noise 2e-3, drive statistics: the spread of the
    # experiments near K_fc* (stick-slip) is larger than at K_fc = 0; the noise check reads the
    # lower of the K_fc = 0 spread and the search's median, so it does not end `noise`
    fc0 = bench_tune.FC0
    plant = {"plant": {"static": 2 * fc0, "stribeck_velocity": 0.05}, "sensor": {"noise_std": 2e-3, "seed": 2}}
    t = bench_tune.run_row(plant, {"capture": "stats"}, str(tmp_path / "s"))
    s = t["search"]
    assert (s["converged"] and _ok(t)) or s["cause"] in ("stick-slip", "amplitude dependence")


def test_a_lead_from_the_k_v_pre_estimate_takes_no_lag_bound():
    """The lag bound reads only experiments without a viscous feed-forward, each side by the
    sign of K_fc = 0's signed objective (under-compensated by definition, whatever sign the
    phases give it): on the paper's set-up K_fc = 0 lags 38 deg and K_v 0.157 leads 5 .. 27
    deg on either side of a root the search verifies at 0.625 Hz (make paper)."""
    from types import SimpleNamespace

    def signed_point(point, phases, harmonics):
        return {0.0: (-0.05, 1e-3), 0.1: (-0.01, 1e-3), 0.2: (0.02, 1e-3)}[point] + (0.0,)

    probe = SimpleNamespace(harmonics=(3, 5), search_point=lambda p: p["k"])

    def pts(kv):
        return {k: {"k": k, "ratio": 0.1, "H": np.ones(3, complex), "kv": 0.0 if k == 0.0 else kv,
                    "lag_deg": lag} for k, lag in ((0.0, 38.0), (0.1, 12.0), (0.2, 9.0))}
    orig_sp, orig_rp = tuning.signed_point, tuning.reference_phases
    try:
        tuning.signed_point = signed_point
        tuning.reference_phases = lambda *a: None
        # K_v = 0 everywhere: K_fc = 0 reads s < 0, so 0.1 (s < 0) is below, 0.2 (s > 0) above
        assert tune_strategy._lag_sides(probe, pts(0.0)) == ([38.0, 12.0], [9.0])
        assert tune_strategy.lag_bound_deg(*tune_strategy._lag_sides(probe, pts(0.0))) == 9.0
        # a K_v pre-estimate: no bound
        assert tune_strategy._lag_sides(probe, pts(0.157)) == ([], [])
    finally:
        tuning.signed_point, tuning.reference_phases = orig_sp, orig_rp
