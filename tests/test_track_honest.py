"""track where the sensor is noisy, the viscous friction changes with K_v held and the drift
is fast (issue 32): one test per row of the issue, on the direct simulation path
(tests/track_sim.py: the drive core + plant through ctypes, the estimator and tracker of
``fftune track``), and the new estimator parts on independent references."""
import math

import numpy as np
import pytest

from fftune.analysis.track import (K_FC_MEANING, NOISE_BIAS_PER_R2, NOTE_NOISE_CORRECTED,
                                   NOTE_VISCOUS_CHANGE, curvature_scatter, drift_trend, sensor_noise_gain,
                                   viscous_shift, viscous_unresolved)

from track_sim import TWOMASS, plant_file, run_tracking


def _coverage(rows, skip):
    sel = [r for r in rows if r["task"] not in skip and r["k_fc_estimate"] is not None]
    return sum(abs(r["k_fc_estimate"] - r["k_fc_true"]) <= 2 * r["k_fc_sigma"] for r in sel) / len(sel)


@pytest.mark.parametrize("seed", [1, 2])
def test_sigma_covers_the_truth_with_noise_1e_2(tmp_path, seed):
    # today: the estimate -1.1 % low with sigma at its 0.4 % floor: truth within 2 sigma on
    # about half of the settled tasks
    plant = plant_file(str(tmp_path), sensor={"noise_std": 1e-2, "seed": seed})
    rows, _ = run_tracking(plant, 40, k_fc=0.1157, k_v=0.002, k_a=0.0)
    assert _coverage(rows, skip=range(3)) >= 0.9
    late = rows[10:]
    # the noise is read from the residual (within 5 % of the configured 1e-2 rad) ...
    assert np.median([r["sensor_noise_rad"] for r in late]) == pytest.approx(1e-2, rel=0.05)
    assert all(NOTE_NOISE_CORRECTED in r["notes"] for r in late)
    # ... and its bias removed: the mean error within 0.5 % (today -1.1 %)
    err = np.mean([r["k_fc_estimate"] / r["k_fc_true"] - 1 for r in late])
    assert abs(err) < 0.005


def test_noise_bias_follows_the_friction_level(tmp_path):
    # Coulomb level 0.7 x plant_twomass's, 1e-2 rad: the jitter's torque against a lower
    # friction averages more of it down. The correction of the first model (100 sigma_n^2
    # whatever the level) left -1.2 % (today's main); the relative bias as a function of
    # the input's noise over K_fc, NOISE_BIAS_PER_R2 (gain sigma_n / K_fc)^2: within 0.5 %
    from fwsim_drive import plant_file as derived
    fc0 = 5.785e-3
    plant = derived({"plant": {"coulomb": 0.7 * fc0, "static": 0.7 * fc0},
                     "sensor": {"noise_std": 1e-2, "seed": 2}}, directory=str(tmp_path))
    rows, _ = run_tracking(plant, 24, k_fc=0.7 * 0.1157, k_v=0.002, k_a=0.0)
    late = rows[8:]
    err = np.mean([r["k_fc_estimate"] / r["k_fc_true"] - 1 for r in late])
    assert abs(err) < 0.005
    # the correction is the model's: r from the smallest noise bound, K_fc before it
    r = late[-1]
    fc_plain = r["k_fc_estimate"] - r["k_fc_noise_correction"]
    assert r["k_fc_noise_correction"] / fc_plain == pytest.approx(
        NOISE_BIAS_PER_R2 * (23.75 * 1e-2 / fc_plain) ** 2, rel=0.15)
    assert _coverage(rows, skip=range(3)) >= 0.9


def test_noise_free_rows_have_no_noise_correction(tmp_path):
    rows, _ = run_tracking(TWOMASS, 8, k_fc=0.1157, k_v=0.002, k_a=0.0)
    assert not any(NOTE_NOISE_CORRECTED in r["notes"] for r in rows)
    assert rows[-1]["sensor_noise_rad"] < 1.5e-3       # the model error's bound, no more


def test_viscous_step_with_k_v_held_is_flagged_and_covered(tmp_path):
    # +60 % viscous friction at 12 s (task 10), K_v held: today K_fc +2.9 % at z = +7 and
    # nothing but a note every row carries
    plant = plant_file(str(tmp_path), drift={"viscous_step": 0.6, "viscous_step_time_s": 12.0})
    rows, _ = run_tracking(plant, 24, k_fc=0.1157, k_v=0.002, k_a=0.0)
    step = next(r["task"] for r in rows if r["t_s"] > 12.0)
    flagged = [r["task"] for r in rows if NOTE_VISCOUS_CHANGE in r["notes"]]
    assert flagged and step < flagged[0] <= step + 5
    assert all(t >= step for t in flagged)                     # not before the change
    assert flagged == list(range(flagged[0], len(rows)))      # and from then on
    # flagged rows carry the change's effect on K_fc in their sigma: the truth is covered
    for r in rows[flagged[0]:]:
        assert r["k_v_shift"] > 0.3e-3
        assert abs(r["k_fc_estimate"] - r["k_fc_true"]) <= 2 * r["k_fc_sigma"]


def test_coulomb_step_is_no_viscous_change(tmp_path):
    plant = plant_file(str(tmp_path), drift={"coulomb_step": 0.3, "coulomb_step_time_s": 12.0})
    rows, _ = run_tracking(plant, 24, k_fc=0.1157, k_v=0.002, k_a=0.0)
    assert not any(NOTE_VISCOUS_CHANGE in r["notes"] for r in rows)
    step = next(r["task"] for r in rows if r["t_s"] > 12.0)
    err = [abs(r["k_fc"] / r["k_fc_true"] - 1) for r in rows]
    assert max(err[step + 3:]) < 0.02                  # no trend overshoot after a step
    assert not any(r["cause"] == "trend" for r in rows)
    # the free viscous coefficient jumps while the feed-forward is wrong (the step's task and
    # the next); those tasks are left out of the viscous part of the sigma: it stays below
    # 1 % of K_fc (with them: 8 .. 12 %, and the tracker held K_fc as uncertain)
    assert max(r["k_fc_sigma_viscous"] for r in rows[step:]) < 0.01 * rows[-1]["k_fc_true"]


def test_fast_exponential_drift_is_followed_from_three_tasks_after_its_start(tmp_path):
    # -30 % with tau 15 s from 12 s (2.4 % per task at first): today 1.5 tasks late (3.5 %)
    plant = plant_file(str(tmp_path), drift={"coulomb_exp": -0.3, "coulomb_exp_start_s": 12.0,
                                             "coulomb_exp_tau_s": 15.0})
    rows, _ = run_tracking(plant, 30, k_fc=0.1157, k_v=0.002, k_a=0.0)
    start = next(r["task"] for r in rows if r["t_s"] > 12.0)
    err = [abs(r["k_fc"] / r["k_fc_true"] - 1) for r in rows]
    assert max(err[start + 3:]) < 0.02
    assert any(r["cause"] == "trend" for r in rows[start:start + 4])


def test_position_dependent_friction_is_the_path_average(tmp_path):
    # friction x (1 + e sin th) on a 0 .. 1 rad task: the task's K_fc is the average over its
    # path (weighted by the time spent sliding there), not the nominal level tune reads
    # around 0; the summary says so (K_FC_MEANING)
    text = open(TWOMASS, encoding="utf-8").read().replace(
        "  coulomb_asymmetry: 0.0", "  coulomb_position: 0.4\n  coulomb_asymmetry: 0.0")
    text = text.replace("  static: 5.785e-3 ", "  static: 8.2e-3 ")
    path = tmp_path / "pos.yaml"
    path.write_text(text)
    rows, _ = run_tracking(str(path), 12, k_fc=0.1157, k_v=0.002, k_a=0.0)
    est = rows[-1]["k_fc_estimate"]
    uniform = 1 + 0.4 * (1 - math.cos(1.0))               # the plain path average, 1.184
    assert est / 0.1157 == pytest.approx(uniform, rel=0.04)
    assert "path" in K_FC_MEANING and "fftune tune" in K_FC_MEANING


def test_sensor_noise_gain_against_the_controller_recursion():
    kp, kd, tau, fs = 1.3, 0.07, 0.0035, 2000.0
    rng = np.random.default_rng(3)
    n = rng.standard_normal(400000)
    ts = 1 / fs
    p, g = tau / (tau + ts), kd / (tau + ts)
    d = np.zeros_like(n)
    for i in range(1, n.size):                               # the drive's D-filter, sample by sample
        d[i] = p * d[i - 1] + g * (n[i] - n[i - 1])
    u = kp * n + d
    assert sensor_noise_gain(kp, kd, tau, fs) == pytest.approx(np.std(u[100:]), rel=0.01)


def test_noise_correction_constant_and_the_first_task():
    # a task alone (no earlier bound) is not corrected: its residual may be model error
    from test_track import _synthetic
    from fftune.analysis.track import estimate_task
    st = _synthetic([0.12, 0.12, 0.003, 0.006], noise=0.05, seed=2)
    # (K_v in effect the plant's 0.003: the split's gap to the held fit is noise alone, no split part)
    first = estimate_task(st, noise_gain=10.0, recent=[], k_v_hold=0.003)
    assert first.k_fc_noise_correction == 0.0 and first.sensor_noise_rad == pytest.approx(
        first.rms_residual / 10.0)
    second = estimate_task(st, noise_gain=10.0, recent=[first], k_v_hold=0.003)
    sn = first.sensor_noise_rad
    plain = estimate_task(st)
    # the relative bias NOISE_BIAS_PER_R2 r^2, r = the input's noise rms (10 V/rad x sn) over K_fc
    assert second.k_fc_noise_correction == pytest.approx(
        NOISE_BIAS_PER_R2 * (10.0 * sn / plain.k_fc) ** 2 * plain.k_fc, rel=1e-9)
    assert second.k_fc == pytest.approx(plain.k_fc + second.k_fc_noise_correction, rel=1e-12)
    assert second.k_fc_sigma_sys == pytest.approx(
        math.hypot(0.02 * plain.k_fc, second.k_fc_noise_correction), rel=1e-9)   # K_v estimated: 2 % floor


def test_drift_trend_rules():
    rng = np.random.default_rng(5)
    base = 0.12 + 2e-5 * rng.standard_normal(12)
    ramp = base - 1.5e-3 * np.arange(12)
    d3 = np.diff(ramp)[-3:]
    # the mean change, or the last one if smaller (same sign)
    assert drift_trend(ramp) == pytest.approx(-min(abs(d3.mean()), abs(d3[-1])))
    # a drift that slows within the noise (the decay rule not triggered): led by its last
    # change, not by the mean of the three (the first pass's mean led an exponential's
    # tail, and a noisy early change, too far)
    slow = np.array([0.1200, 0.1200, 0.1200, 0.1185, 0.1170, 0.1158])
    assert drift_trend(slow, scatter_floor=3e-4) == pytest.approx(-1.2e-3, rel=1e-9)
    step = base + np.where(np.arange(12) >= 9, 0.03, 0.0)
    step[9] -= 0.015                                         # the mixed task
    assert drift_trend(step) == 0.0 and drift_trend(step[:11]) == 0.0
    assert drift_trend(base) == 0.0                          # noise is no trend
    # a ramp that ends: its last change the partial task (0.4 of the rate): it leads by
    # that change times its ratio to the changes before, not by their mean
    end = ramp.copy()
    end[-1] = end[-2] - 0.4 * 1.5e-3
    d = np.diff(end)[-3:]
    assert drift_trend(end) == pytest.approx(d[-1] * d[-1] / np.mean(d[:2]))
    # a noisy estimate makes one change of a drift small: with the estimate's scatter at
    # 3e-4 (a floor here) a change of 0.3 of the rate still belongs to it, without it not
    x = 0.12 - 1.5e-3 * np.arange(12.0)
    x[-3:] += 1.05e-3                                        # changes 0.3, 1, 1 of the rate
    assert drift_trend(x) == 0.0
    assert drift_trend(x, scatter_floor=3e-4) == pytest.approx(np.mean(np.diff(x)[-3:]))
    # a trend already seen continues through a small change while its mean stands out
    flat = x.copy()
    flat[-1] = flat[-2] - 0.2 * 1.5e-3
    d = np.diff(flat)[-3:]
    assert drift_trend(flat) == 0.0
    assert drift_trend(flat, active=True) == pytest.approx(d[-1] * d[-1] / np.mean(d[:2]))
    tau = 0.12 * (1 - 0.3 * (1 - np.exp(-np.arange(12) / 12.0)))
    assert drift_trend(tau + 2e-5 * rng.standard_normal(12)) == pytest.approx(np.diff(tau)[-1], rel=0.15)
    # the scatter from second differences ignores the curvature of the approach
    w = 0.12 + 3e-4 * rng.standard_normal((300, 10))
    assert np.mean([curvature_scatter(x + tau[:10]) for x in w]) == pytest.approx(3e-4, rel=0.15)


def test_viscous_shift_rules():
    kv = [0.08, 0.005, 0.001, 0.002, 0.00150, 0.00152, 0.00149, 0.00151, 0.00150, 0.00151]
    fc = [0.116] * 12
    assert viscous_shift(kv, 0.002, fc[:10]) == (0.0, False)
    shifted = kv + [0.00236, 0.00237]
    d, ok = viscous_shift(shifted, 0.002, fc)
    assert ok and d == pytest.approx(0.002365 - 0.00150, rel=1e-6)
    # not while K_fc moves (a Coulomb step drags the free viscous coefficient along)
    assert viscous_shift(shifted, 0.002, fc[:10] + [0.13, 0.15]) == (0.0, False)
    # one task is not a change
    assert viscous_shift(kv + [0.00151, 0.00236], 0.002, fc) == (0.0, False)


def test_stribeck_estimate_covers_the_friction_the_task_met(tmp_path):
    # static x2, Stribeck velocity 0.2 rad/s: the task's K_fc lies above the Coulomb level
    # (today +4.7 % with a 0.4 % sigma: "confidently wrong" for the Coulomb level). What it
    # tracks is the friction the task's motion meets (K_FC_MEANING), computed here from
    # the plant's state sample by sample (friction_met_v): covered within 2 sigma
    from fwsim_drive import plant_file as derived
    fc0 = 5.785e-3
    plant = derived({"plant": {"static": 2 * fc0, "stribeck_velocity": 0.2}}, directory=str(tmp_path))
    rows, _ = run_tracking(plant, 14, k_fc=0.1157, k_v=0.002, k_a=0.0, friction_met=True)
    sel = rows[3:]
    met = np.array([r["k_fc_met"] for r in sel])
    assert np.all((met > 1.03 * 0.1157) & (met < 1.08 * 0.1157))   # above the Coulomb level
    assert all(abs(r["k_fc_estimate"] - r["k_fc_met"]) <= 2 * r["k_fc_sigma"] for r in sel)
    assert "Stribeck" in K_FC_MEANING and "sticks" in K_FC_MEANING


@pytest.mark.parametrize("noise, seed", [(5e-3, 1), (1e-2, 2)])
def test_stribeck_under_noise_covers_the_friction_met(tmp_path, noise, seed):
    # static x2, Stribeck velocity 0.2 rad/s under sensor noise: the friction the task met
    # (averaged over each sample, friction_met_v) falls with the noise (1.053 -> 1.045 ->
    # 1.033 x Coulomb at 0 / 5e-3 / 1e-2 rad: the jitter's slides average the Stribeck
    # peak down) and the estimate follows it; on today's main the bench read the law at each
    # sample's start (1.074 x at 5e-3: the motor breaks away and sticks within a sample)
    # and covered 71 % of the settled tasks at 5e-3
    from fwsim_drive import plant_file as derived
    fc0 = 5.785e-3
    plant = derived({"plant": {"static": 2 * fc0, "stribeck_velocity": 0.2},
                     "sensor": {"noise_std": noise, "seed": seed}}, directory=str(tmp_path))
    rows, _ = run_tracking(plant, 24, k_fc=0.1157, k_v=0.002, k_a=0.0, friction_met=True)
    sel = rows[4:]
    met = float(np.mean([r["k_fc_met"] for r in sel]))   # stationary plant: its mean is the truth
    assert 1.02 * 0.1157 < met < 1.05 * 0.1157
    cov = np.mean([abs(r["k_fc_estimate"] - met) <= 2 * r["k_fc_sigma"] for r in sel])
    assert cov >= 0.9


def test_friction_met_against_the_law_on_a_fine_grid(tmp_path):
    # the friction met is the friction averaged over each sample from the plant's momentum
    # balance; reference: the plant (Stribeck, static x2, 0.2 rad/s; load viscous too) run
    # at 128 points per sample, the law read at each (mode * (F_c + (F_s - F_c) e^-(w/v_s)^2)
    # sliding, k_m u - spring stuck) and averaged, projected on p, n, a_r by hand. The input
    # jitters every sample (as with sensor noise) so that the motor breaks away and sticks
    # within samples
    from fwsim_drive import plant_file as derived
    import yaml

    from track_sim import FwSim, friction_met_v
    fc0 = 5.785e-3
    plant = derived({"plant": {"static": 2 * fc0, "stribeck_velocity": 0.2, "load_viscous": 3e-5}},
                    directory=str(tmp_path))
    pp = yaml.safe_load(open(plant, encoding="utf-8"))["plant"]
    fs, n, fine = 2560.0, 1536, 128
    t = np.arange(n) / fs
    ref = 0.25 * (1 - np.cos(2 * np.pi * t / t[-1] * 1.0)) + 0.05 * t      # forward, then back
    rng = np.random.default_rng(3)
    u = 0.13 * np.sign(np.gradient(ref)) + 0.11 * rng.standard_normal(n)     # V
    def law_at(x, m, uk):
        if m == 0:
            return pp["km"] * uk - pp["k"] * (x[0] - x[2]) - pp["c"] * (x[1] - x[3])
        return m * (pp["coulomb"] + (pp["static"] - pp["coulomb"]) * math.exp(-(x[1] / pp["stribeck_velocity"]) ** 2))

    states, modes, law = [], [], np.zeros(n)
    with FwSim(plant) as sim:
        sim.plant_set_state(0.0, 0.0, 0.0, 0.0)
        for k in range(n):
            states.append(sim.plant_state())
            modes.append(sim.plant_mode())
            acc = 0.0
            for _ in range(fine):
                acc += law_at(sim.plant_state(), sim.plant_mode(), u[k])
                sim.plant_advance(u[k], 1.0 / fs / fine)
            law[k] = acc / fine
        states.append(sim.plant_state())
    states = np.array(states)
    assert 0.1 < np.mean(states[:, 1] == 0.0) < 0.9               # it sticks and slides
    v = np.gradient(ref) * fs
    a = np.gradient(v) * fs
    s = np.sign(np.round(v, 6))
    X = np.column_stack([(s > 0).astype(float), -(s < 0).astype(float), a])
    th = np.linalg.lstsq(X, law / pp["km"], rcond=None)[0]
    want = 0.5 * (th[0] + th[1])
    got = friction_met_v(pp, states, ref, u, fs)
    start = np.array([law_at(x, m, uk) for x, m, uk in zip(states[:-1], modes, u)])
    assert got == pytest.approx(want, rel=2e-3)
    # the input exercises what the first version missed: the law at each sample's start
    # reads this trajectory 14 % high (0.150 against 0.132 V)
    assert 0.5 * sum(np.linalg.lstsq(X, start / pp["km"], rcond=None)[0][:2]) > 1.05 * want
    assert 0.1157 < got < 2 * 0.1157                               # between Coulomb and static
    with pytest.raises(ValueError, match="states"):
        friction_met_v(pp, states[:-1], ref, u, fs)


def test_viscous_step_under_noise_1e_2_is_covered(tmp_path):
    # +60 % viscous friction at 12 s with K_v held and 1e-2 rad of sensor noise: the free
    # coefficient scatters as much as the change moves it, the watch does not flag it;
    # today K_fc +2.9 % at z ~ +2.5 on most tasks. The sigma carries the viscous change
    # the tasks cannot rule out: the truth within 2 sigma from the task after the change's
    for seed in (1, 2):
        plant = plant_file(str(tmp_path), drift={"viscous_step": 0.6, "viscous_step_time_s": 12.0},
                           sensor={"noise_std": 1e-2, "seed": seed})
        rows, _ = run_tracking(plant, 22, k_fc=0.1157, k_v=0.002, k_a=0.0)
        step = next(r["task"] for r in rows if r["t_s"] > 12.0)
        after = rows[step + 1:]
        assert np.mean([r["k_fc_estimate"] / r["k_fc_true"] - 1 for r in after]) > 0.02   # K_fc took it
        assert all(abs(r["k_fc_estimate"] - r["k_fc_true"]) <= 2 * r["k_fc_sigma"] for r in after)
        assert all(r["k_fc_sigma_viscous"] > 0 for r in after)
        # and before the change the sigma stays below 2.5 % (the part is what the data allow)
        assert all(r["k_fc_sigma"] < 0.025 * r["k_fc_true"] for r in rows[5:step])


def test_viscous_unresolved_against_its_definition():
    rng = np.random.default_rng(7)
    kv = list(0.0015 + 1e-4 * rng.standard_normal(16))
    kv[:4] = [0.08, 0.01, 0.003, 0.002]                       # the first tasks (K_a learnt)
    x = np.array(kv)
    base = np.median(x[4:9])
    d = np.diff(x[4:])
    scat = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2)
    want = max(math.hypot(np.mean(x[-n:]) - base, scat * math.sqrt(1 / n + 1 / 5)) for n in (8, 4))
    assert viscous_unresolved(kv) == pytest.approx(want, rel=1e-12)
    assert viscous_unresolved(kv[:9]) == 0.0                  # no task after the baseline yet
    shifted = kv + [0.0024] * 8
    assert viscous_unresolved(shifted) > 0.0024 - 0.0015 - 0.0002


def test_fast_drift_under_noise_1e_2_trend_does_not_extrapolate_one_change(tmp_path):
    # -30 % with tau 15 s under 1e-2 rad noise: today the update leads by 1.5 x the last
    # change (its noise x 1.5) and the share rule loses the trend on a noisy change:
    # 3.6 % off after the start. The mean change, a noise-aware share rule and a trend that
    # continues while it stands out: within 3 %
    plant = plant_file(str(tmp_path), drift={"coulomb_exp": -0.3, "coulomb_exp_start_s": 12.0,
                                             "coulomb_exp_tau_s": 15.0},
                       sensor={"noise_std": 1e-2, "seed": 5})
    rows, _ = run_tracking(plant, 40, k_fc=0.1157, k_v=0.002, k_a=0.0)
    start = next(r["task"] for r in rows if r["t_s"] > 12.0)
    err = [abs(r["k_fc"] / r["k_fc_true"] - 1) for r in rows]
    assert max(err[start + 3:]) < 0.03
    assert sum(r["cause"] == "trend" for r in rows) >= 5


def test_ramp_end_trend_stops(tmp_path):
    # -30 % over 24 s (ends with task 29): the task after the end is overshot by the lead
    # (the end is not in the data yet); the one after that no more: the partial last change
    # leads by its ratio to the ones before (today 2.4 % over, the full last change again)
    plant = plant_file(str(tmp_path), drift={"coulomb_ramp": -0.3, "coulomb_ramp_start_s": 12.0,
                                             "coulomb_ramp_end_s": 36.0})
    rows, _ = run_tracking(plant, 36, k_fc=0.1157, k_v=0.002, k_a=0.0)
    end = next(r["task"] for r in rows if r["t_s"] >= 36.0 - 1e-9)
    err = [r["k_fc"] / r["k_fc_true"] - 1 for r in rows]
    assert max(abs(e) for e in err[end + 2:]) < 0.02
    assert max(abs(e) for e in err[13:end + 1]) < 0.01         # the ramp itself followed
    assert not any(r["cause"] == "trend" for r in rows[end + 2:])


@pytest.mark.parametrize("drift", [
    {"coulomb_ramp": -0.3, "coulomb_ramp_start_s": 12.0, "coulomb_ramp_end_s": 36.0},
    {"coulomb_exp": -0.3, "coulomb_exp_start_s": 12.0, "coulomb_exp_tau_s": 15.0}])
def test_fast_drift_under_noise_1e_2_applied_value_within_its_sigma(tmp_path, drift):
    # under 1e-2 rad a fast drift is not followed within 2 % (single estimates scatter by
    # about 0.6 %, the trend's lead adds its rate's noise, a ramp's end is not in the data
    # when the lead overshoots it): the applied K_fc's error stays within 2 sigma of the
    # estimate it came from, from 3 tasks after the start; and the tail (0.7 x the level)
    # carries no noise bias beyond 1 % (today's main: -1.2 % there)
    plant = plant_file(str(tmp_path), drift=drift, sensor={"noise_std": 1e-2, "seed": 1})
    rows, _ = run_tracking(plant, 50, k_fc=0.1157, k_v=0.002, k_a=0.0)
    start = next(r["task"] for r in rows if r["t_s"] > 12.0)
    for k in range(start + 3, len(rows)):
        assert abs(rows[k]["k_fc"] - rows[k]["k_fc_true"]) <= 2 * rows[k - 1]["k_fc_sigma"]
    tail = [r["k_fc_estimate"] / r["k_fc_true"] - 1 for r in rows[-10:]]
    assert abs(np.mean(tail)) < 0.01


def test_friction_falling_with_speed_is_named(tmp_path):
    # static x3, Stribeck velocity 0.4 rad/s: the estimate falls short of the friction met
    # by 1.6 % with a 0.8 % sigma (a strong rise the sigma does not cover; today's main says
    # nothing). The unconstrained fit's viscous coefficient turns negative (friction that
    # falls with speed; +1.5 mV s/rad on the Coulomb plant): the rows name it. Not on a
    # Coulomb plant under 1e-2 rad of noise, nor during a Coulomb drift
    from fwsim_drive import plant_file as derived
    from fftune.analysis.track import NOTE_FRICTION_FALLS_WITH_SPEED
    fc0 = 5.785e-3
    plant = derived({"plant": {"static": 3 * fc0, "stribeck_velocity": 0.4}}, directory=str(tmp_path / "s"))
    rows, _ = run_tracking(plant, 14, k_fc=0.1157, k_v=0.002, k_a=0.0)
    assert all(NOTE_FRICTION_FALLS_WITH_SPEED in r["notes"] for r in rows[8:])
    assert all(r["k_v_free"] < 0 for r in rows[8:])
    assert not any(NOTE_FRICTION_FALLS_WITH_SPEED in r["notes"] for r in rows[:8])   # (K_a learnt first)
    for sensor, drift in (({"noise_std": 1e-2, "seed": 3}, None),
                          (None, {"coulomb_exp": -0.3, "coulomb_exp_start_s": 6.0, "coulomb_exp_tau_s": 10.0})):
        plant = plant_file(str(tmp_path), sensor=sensor, drift=drift)
        rows, _ = run_tracking(plant, 24, k_fc=0.1157, k_v=0.002, k_a=0.0)
        assert not any(NOTE_FRICTION_FALLS_WITH_SPEED in r["notes"] for r in rows)
