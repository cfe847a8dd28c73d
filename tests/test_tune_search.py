"""The tune step on the firmware core + plant (tests/fwsim_drive.py, no CANopen) and on
drive_sim through CANopen (`fftune tune`): the fast subset of the tuning-accuracy matrix
(tests/bench/bench_tune.py), the coverage of the reported sigma over noise seeds, the
amplitude choice, the sweep-free search, and the one-line errors for bad tune keys."""
import math
import os
import statistics
import sys

import numpy as np
import pytest
import yaml

from fftune.analysis.errors import FftuneError
from fftune.analysis import tune_strategy as ts
from fftune.analysis.tuning import harmonic_orders, odd_ratio
from fftune.host import experiments as ex
from fftune.host.cli import main
from host_fixtures import REPO, FakeDriveForTests, drive_sim_missing_reason

sys.path.insert(0, os.path.join(REPO, "tests", "bench"))
import bench_tune  # noqa: E402

ROWS = {name: (plant, tune) for name, plant, tune in bench_tune.rows()}


@pytest.fixture(scope="module")
def fast_rows(tmp_path_factory):
    out = {}
    for name in bench_tune.FAST:
        plant, tune = ROWS[name]
        out[name] = bench_tune.run_row(plant, tune, str(tmp_path_factory.mktemp("row")))
    return out


@pytest.mark.parametrize("name", bench_tune.FAST)
def test_matrix_row_is_right_or_says_why(fast_rows, name):
    t = fast_rows[name]
    ok, err = bench_tune.judge(t)
    assert ok, (name, t["search"])
    s = t["search"]
    if s["converged"]:
        assert abs(err) <= 0.02
        # never converged at a point whose ratio is above another measured one's beyond noise
        ver = min(s["evaluations"], key=lambda e: abs(e["k_fc"] - s["verification_k_fc"]))
        far = [e for e in s["evaluations"] if abs(e["k_fc"] - t["k_fc_star"]) > 0.05 * t["k_fc_star"]]
        assert all(ver["ratio"] <= e["ratio"] for e in far)


def test_matrix_fast_subset_uses_few_experiments(fast_rows):
    counts = [t["search"]["experiments"] for t in fast_rows.values()]
    assert statistics.median(counts) <= 6 and max(counts) <= 10


import bench_tune_matrix  # noqa: E402

MATRIX = {name: (plant, tune, cause) for rows in bench_tune_matrix.families().values()
          for name, plant, tune, cause in rows}


@pytest.fixture(scope="module")
def family_rows():
    return {name: bench_tune_matrix.run_row(*MATRIX[name][:2]) for name in bench_tune_matrix.FAST}


@pytest.mark.parametrize("name", bench_tune_matrix.FAST)
def test_family_row_is_covered_or_names_its_cause(family_rows, name):
    """The fast subset of tests/bench/bench_tune_matrix.py: a converged row's truth lies
    within max(2 %, 2 sigma_total); the u_max rows end unconverged with the cause named."""
    t = family_rows[name]
    ok, err, _ = bench_tune_matrix.judge(t, MATRIX[name][2])
    assert ok, (name, t["search"]["stop_reason"], t["search"].get("sigma_parts_v"))
    s = t["search"]
    if s["converged"]:
        parts = s["sigma_parts_v"]
        assert s["sigma_v"] == pytest.approx(np.sqrt(sum(v ** 2 for v in parts.values())), rel=1e-9)
        assert {"noise", "amplitude", "encoder", "flatness", "viscous"} <= set(parts)
        assert all(e["cause"] is None for e in s["evaluations"])


def test_family_rows_use_few_experiments(family_rows):
    assert statistics.median(t["search"]["experiments"] for t in family_rows.values()) <= 6


def test_saturation_and_no_motion_are_named_never_nan(family_rows):
    sat = family_rows["Fc 0.46 V, u_max 0.6 V"]["search"]
    assert not sat["converged"] and sat["cause"] == "saturation"
    assert "u_max = 0.6 V" in sat["stop_reason"] and "raise the sine amplitude" not in sat["stop_reason"]
    stuck = family_rows["Fc 0.46 V, u_max 0.4 V"]
    s = stuck["search"]
    assert not s["converged"] and s["cause"] == "no motion" and stuck["k_fc_star"] is None
    assert "the friction exceeds what the drive can give" in s["stop_reason"]
    assert s["evaluations"][0]["saturated_fraction"] > 0.5 and s["evaluations"][0]["motion_h1"] < 0.2


def test_demo_plant_budget_is_small_and_corrects_the_lag(tmp_path, monkeypatch):
    """The demo plant (viscous 2e-3 N m s/rad = 0.04 V s/rad): the K_fc = 0 experiment's
    harmonics give K_v, which goes into the loop for the search; the motor then no longer
    lags the reference at K_fc*. K_fc* within 1.5 %, sigma_total <= 3 %. Without the
    correction the criterion's optimum sits about 1 % high (the lag)."""
    t = bench_tune.run_row({"plant": {"viscous": 2e-3}}, {}, str(tmp_path / "a"))
    s = t["search"]
    assert s["converged"] and abs(t["k_fc_star_error_re_truth"]) <= 0.015
    assert s["sigma_v"] <= 0.03 * t["k_fc_star"]
    v = s["budget"]["viscous"]
    assert v["k_v_in_search"] == pytest.approx(0.04, rel=0.2)
    assert abs(v["lag_deg"]) < ex.LAG_MIN_DEG and not v["applied"]
    assert s["k_v_in_search"] == v["k_v_in_search"]
    monkeypatch.setattr(ts, "KV_MIN_SHARE", math.inf)
    monkeypatch.setattr(ts, "LAG_MIN_DEG", math.inf)
    plain = bench_tune.run_row({"plant": {"viscous": 2e-3}}, {}, str(tmp_path / "b"))
    assert plain["search"]["budget"]["viscous"]["lag_deg"] > 3
    assert plain["k_fc_star_error_re_truth"] > t["k_fc_star_error_re_truth"] + 0.005


def test_lag_at_k_fc_star_is_corrected_after_the_search(tmp_path, monkeypatch):
    """With the viscous estimate kept out of the search, the lag at K_fc* (4.8 deg on the
    demo plant) triggers the correction experiment(s) at K_v read there."""
    monkeypatch.setattr(ts, "KV_MIN_SHARE", math.inf)
    t = bench_tune.run_row({"plant": {"viscous": 2e-3}}, {}, str(tmp_path))
    v = t["search"]["budget"]["viscous"]
    assert v["applied"] and v["lag_deg"] > 3 and abs(v["lag_after_deg"]) < 1.5
    assert v["k_v_estimate"] == pytest.approx(0.04, rel=0.1) and v["steps"]
    assert abs(t["k_fc_star_error_re_truth"]) <= 0.01 and t["search"]["sigma_parts_v"]["viscous"] > 0


def test_lead_at_k_fc_star_is_corrected_too(tmp_path, monkeypatch):
    """A K_v read at K_fc = 0 that is too large (brief sticking read as viscous friction:
    2.5x here, as on configs/plant_paper.yaml) makes the motor LEAD the reference at K_fc*,
    which moves the criterion's optimum low; the correction at K_v read at K_fc* acts on
    |lag| (issue 24 after issue 22: the paper set-up's K_fc* was 2.5 % low)."""
    real = ts._viscous_estimate
    calls = []

    def too_large_at_zero(probe, p):
        kv, share = real(probe, p)
        calls.append(p["kfc"])
        return (2.5 * kv, share) if p["kfc"] == 0.0 else (kv, share)

    monkeypatch.setattr(ts, "_viscous_estimate", too_large_at_zero)
    t = bench_tune.run_row({"plant": {"viscous": 2e-3}}, {}, str(tmp_path))
    assert calls[0] == 0.0 and len(calls) >= 2
    v = t["search"]["budget"]["viscous"]
    assert v["k_v_in_search"] == pytest.approx(0.1, rel=0.2)          # 2.5 x 0.04 V s/rad
    assert v["lag_deg"] < -3 and v["applied"] and abs(v["lag_after_deg"]) < ex.LAG_MIN_DEG
    assert v["k_v_estimate"] == pytest.approx(0.04, rel=0.15) and "led the reference" in v["note"]
    assert t["search"]["k_v_in_search"] == pytest.approx(v["k_v_estimate"])
    assert abs(t["k_fc_star_error_re_truth"]) <= 0.015 and t["search"]["sigma_parts_v"]["viscous"] > 0


def test_too_small_bracket_is_extended_and_says_so(fast_rows):
    t = fast_rows["Coulomb x3, k_fc_max 0.3 x Fc"]
    ext = t["search"]["bracket_extended"]
    assert ext and ext["to_v"] > t["true_coulomb_v"] > ext["from_v"]
    assert "too small" in ext["reason"]
    # auto amplitude: out of stick-slip at Coulomb x3 needs more than the 0.5 rad start
    assert t["amplitude"]["chosen_rad"] > 0.5 and "out of stick-slip" in t["amplitude"]["reason"]
    assert t["amplitude"]["probes"][0]["ratio_at_zero"] > ex.AUTO_AMPLITUDE_MAX_RATIO


def test_fixed_amplitude_in_noise_is_refused_with_the_fix(tmp_path):
    plant, tune = ROWS["noise 3e-2 rad, fixed 0.5 rad"]
    t = bench_tune.run_row(plant, tune, str(tmp_path))
    assert not t["search"]["converged"] and t["k_fc_star"] is None
    assert "raise tune.amplitude_rad" in t["search"]["stop_reason"]
    # auto picks an amplitude at which the same plant tunes within 2 %
    plant, tune = ROWS["noise 3e-2 rad"]
    t = bench_tune.run_row(plant, tune, str(tmp_path / "auto"))
    assert t["search"]["converged"] and abs(t["k_fc_star_error_re_truth"]) <= 0.02
    assert t["amplitude_rad"] >= 1.5


@pytest.mark.parametrize("capture", ["raw", "stats"])
def test_sigma_covers_the_truth_over_noise_seeds(tmp_path, capture):
    """>= 20 noise seeds at 1e-2 rad: the truth within +-2 sigma in >= 90 %, with the
    per-period HOSIDFs of raw samples and with the drive's line statistics (mean and
    variance, the standard errors propagated)."""
    hits, z = 0, []
    for seed in range(1, 21):
        t = bench_tune.run_row({"sensor": {"noise_std": 1e-2, "seed": seed}}, {"capture": capture},
                               str(tmp_path / f"s{seed}"))
        s = t["search"]
        assert s["converged"], s["stop_reason"]
        z.append((t["k_fc_star"] - t["true_coulomb_v"]) / s["sigma_v"])
        hits += abs(z[-1]) <= 2
    assert hits >= 18, z
    # sigma is a measurement, not a bracket width: the measured noise of s grows with it
    quiet = bench_tune.run_row({"sensor": {"noise_std": 1e-3}}, {"capture": capture}, str(tmp_path / "quiet"))
    assert quiet["search"]["signed_objective_std"] < t["search"]["signed_objective_std"]


def test_search_alone_without_sweep_and_figures(tmp_path):
    from fftune.host.pipeline import run_pipeline
    from fwsim_drive import FwSimDrive, plant_file
    cfg = bench_tune.tune_config({"search": {"k_fc_max": 0.3}})
    assert cfg["tune"]["sweep"]["points"] == 0
    with FwSimDrive(plant_file({}, directory=str(tmp_path))) as drive:
        drive.enable()
        results = run_pipeline(drive, cfg, str(tmp_path / "out"), steps=("tune",), log=lambda s: None)
    t = results["tune"]
    assert t["sweep"] is None and t["search"]["converged"]
    assert results["experiments"]["measured"] == t["search"]["experiments"]
    assert (tmp_path / "out" / "figure7_tuning.png").exists()


def test_quantify_and_tune_share_one_odd_level_definition(tmp_path):
    from host_fixtures import FakeDriveForTests
    from fftune.host.config import validate
    cfg = validate({"output": "x", "quantify": {"inject": "reference", "period_samples": 1024,
                                                "frequencies_hz": [2.5], "rms_levels": [0.3],
                                                "repeats": 2, "periods": 1, "harmonics": 9}}, "t.yaml")
    cfg["_source"] = "t.yaml"
    d = FakeDriveForTests(fc_volt=0.3, noise_std=1e-5)
    d.enable()
    r, hos = ex.quantify(ex.Session(d, cfg, str(tmp_path), log=lambda s: None))
    assert r["odd_relative_level"][0][0] == pytest.approx(float(odd_ratio(hos.H[0, 0], (3, 5, 7, 9))))
    assert r["even_relative_level"][0][0] == pytest.approx(
        float(odd_ratio(hos.H[0, 0], harmonic_orders(9, "even"))))
    assert "rms of |H_k|" in r["level_definition"]


@pytest.mark.parametrize("tune, expected", [
    ({"amplitude_rad": 2000.0}, "key 'tune.amplitude_rad': expected a number <= 1000"),
    ({"amplitude_rad": "big"}, "key 'tune.amplitude_rad': expected a number"),
    ({"amplitude_rad": "auto", "amplitude_max_rad": 5000}, "key 'tune.amplitude_max_rad': expected a number <= 1000"),
    ({"search": {"k_fc_max": -0.1}}, "key 'tune.search.k_fc_max': expected a number > 0"),
    ({"search": {"k_fc_max": 0}}, "key 'tune.search.k_fc_max': expected a number > 0"),
    ({"sweep": {"k_fc_max": 0}}, "key 'tune.sweep.k_fc_max': expected a number > 0"),
    ({"periods": 1}, "key 'tune.periods': expected an integer >= 2"),
])
def test_bad_tune_keys_give_one_error_line(tmp_path, capsys, tune, expected):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"tune": tune}))
    code = main(["tune", "--config", str(bad), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"fftune: error: {bad}: {expected}")
    assert not (tmp_path / "o").exists() or not os.listdir(tmp_path / "o")


@pytest.mark.parametrize("tune, expected", [
    ({"harmonics": 41, "frequency_hz": 40.0, "period_samples": 1024},
     "key 'tune.harmonics': harmonic 41 of 40 Hz is above fs/2 = 1280 Hz"),
    ({"search": {"k_fc_max": 20.0}}, "key 'tune.search.k_fc_max': 20 V is above what the drive allows"),
    ({"harmonics": 9, "capture": "stats"},
     "key 'tune.harmonics': 9 harmonics with tune.capture stats: the drive's statistics hold at most 8"),
])
def test_tune_plan_against_the_drive_is_checked_before_any_experiment(tmp_path, tune, expected):
    from fftune.host.config import validate
    from fftune.host.pipeline import run_pipeline
    raw = {"output": "x", "tune": tune}
    cfg = validate(raw, "t.yaml")
    cfg["_source"] = "t.yaml"
    d = FakeDriveForTests(fc_volt=0.3)
    d.enable()
    with pytest.raises(FftuneError, match=expected.replace("(", r"\(")):
        run_pipeline(d, cfg, str(tmp_path), steps=("tune",), log=lambda s: None)
    assert d.runs == 0 and not (tmp_path / "results.yaml").exists()


# ---- the product path: `fftune tune` through CANopen on drive_sim --------------------------
needs_drive_sim = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                     reason=drive_sim_missing_reason() or "")


@needs_drive_sim
@pytest.mark.parametrize("name", ["Coulomb x3, k_fc_max 0.3 x Fc", "noise 1e-2 rad"])
def test_matrix_rows_through_canopen_on_drive_sim(tmp_path, name):
    from fftune.host.sim import start_drive_sim
    from fwsim_drive import plant_file
    plant, tune = ROWS[name]
    cfg = bench_tune.tune_config(tune)
    raw = {"output": str(tmp_path / "out"), "tune": {k: v for k, v in cfg["tune"].items()}}
    path = tmp_path / "tune.yaml"
    path.write_text(yaml.safe_dump(raw))
    sim = start_drive_sim(plant_file(plant, directory=str(tmp_path)))
    try:
        code = main(["tune", "--config", str(path), "--port", str(sim.port), "--no-progress",
                     "--no-figures"])
    finally:
        sim.stop()
    assert code == 0
    t = yaml.safe_load(open(tmp_path / "out" / "results.yaml"))["tune"]
    # the same experiments as through ctypes: the same answer
    direct = bench_tune.run_row(plant, tune, str(tmp_path / "direct"))
    assert t["search"]["converged"] and abs(t["k_fc_star_error_re_truth"]) <= 0.02
    assert t["k_fc_star"] == pytest.approx(direct["k_fc_star"], rel=1e-3)
    assert t["search"]["experiments"] == direct["search"]["experiments"]


def test_statistics_only_noise_check_is_an_upper_bound_that_says_so(tmp_path):
    """With one settle period the loop is still settling in the first recorded period. The
    spread of the samples over the periods (raw, both) dilutes that over every line; the
    line variances of the statistics carry it at the harmonic lines and overstate the
    angle noise: the search is refused with the reason and the fix, never a wrong K_fc*."""
    short = {"frequency_hz": 1.25, "period_samples": 2048, "settle_periods": 1, "amplitude_rad": 0.5,
             "search": {"k_fc_max": 0.3}}
    out = {mode: bench_tune.run_row({}, dict(short, capture=mode), str(tmp_path / mode))
           for mode in ("raw", "stats", "both")}
    for mode in ("raw", "both"):
        t = out[mode]
        assert t["search"]["converged"], (mode, t["search"]["stop_reason"])
        assert abs(t["k_fc_star"] / t["true_coulomb_v"] - 1) <= 0.02
    s = out["stats"]["search"]
    assert not s["converged"] and out["stats"]["k_fc_star"] is None
    assert "harmonic lines" in s["stop_reason"] and "tune.settle_periods" in s["stop_reason"]


@pytest.mark.parametrize("h1, ratio, ratio_std, noise, verdict", [
    (1.0, 0.030, 1e-4, 0.004, "pass"),
    (1.0, 0.045, 1e-4, 0.004, "near"),       # within 25 % below the limit 0.05
    (1.0, 0.055, 1e-4, 0.004, "near"),       # within 25 % above it: taken, the alternative named
    (1.0, 0.070, 1e-4, 0.004, "fail"),
    (1.0, 0.030, 0.012, 0.004, "near"),      # two standard errors reach the limit
    (0.49, 0.030, 1e-4, 0.004, "near"),      # |H_1| within 5 % of 0.5
    (0.45, 0.030, 1e-4, 0.004, "fail"),
    (0.70, 0.030, 1e-4, 0.004, "pass"),      # a damped loop follows with |H_1| 0.7
    (1.0, 0.030, 1e-4, 0.0170, "fail"),      # noise near its 2 % limit is not taken
    (1.0, math.inf, math.inf, 0.004, "fail"),
])
def test_amplitude_verdict_has_a_margin(h1, ratio, ratio_std, noise, verdict):
    assert ex.amplitude_verdict(h1, ratio, ratio_std, noise) == verdict


def test_amplitude_choice_near_its_threshold_tells_both_answers(tmp_path):
    """r(0) = 0.041 at 0.5 rad on the asymmetric plant (0.2) is within the margin of the
    0.05 limit: every noise seed takes 0.5 rad, names 1 rad as the alternative and measures
    K_fc* there (the amplitude part of the budget)."""
    plant = {"plant": {"coulomb_asymmetry": 0.2, "static": 1.2 * bench_tune.FC0}}
    for seed in (1, 2, 3):
        t = bench_tune.run_row(dict(plant, sensor={"noise_std": 2e-3, "seed": seed}), {},
                               str(tmp_path / f"s{seed}"))
        a = t["amplitude"]
        assert a["chosen_rad"] == 0.5 and a["alternative_rad"] == pytest.approx(1.0)
        assert a["probes"][-1]["verdict"] == "near" and "another noise seed may choose" in a["reason"]
        assert t["search"]["budget"]["k_fc_at_amplitude"]["amplitude_rad"] == [0.5, pytest.approx(1.0)]
        assert t["search"]["converged"] and abs(t["k_fc_star_error_re_truth"]) <= 0.01


def test_period_spread_growing_with_the_amplitude_is_named_not_climbed_into_saturation(tmp_path):
    """Heavy motor inertia (x30): the loop near its resonance at 0.625 Hz. Before issue 32's
    hidden families auto climbed to saturation, then stopped 'unsettled' after two probes (the
    spread grew with the amplitude); now the first probe names it: without feed-forward the
    motor moves more than 1.4 times the reference, which friction cannot cause (it only holds
    the motor back). tune then tries half the frequency, where the loop follows."""
    ex.tune, real = ex.tune_at_frequency, ex.tune
    try:
        t = bench_tune_matrix.run_row(*MATRIX["j1 x30, seed 1"][:2])
    finally:
        ex.tune = real
    s = t["search"]
    assert not s["converged"] and s["cause"] == "loop lag" and t["k_fc_star"] is None
    assert "near its resonance" in s["stop_reason"] and "tune.frequency_hz" in s["stop_reason"]
    probes = t["amplitude"]["probes"]
    assert len(probes) == 1 and probes[0]["saturated_fraction"] == 0 and probes[0]["h1"] > 1.4
    assert s["experiments"] == 1
    t2 = bench_tune_matrix.run_row(*MATRIX["j1 x30, seed 1"][:2])
    assert t2["frequency_changes"][0]["reason"].startswith("loop lag")
    assert t2["search"]["converged"] and abs(t2["k_fc_star_error_re_truth"]) < 0.02


def test_a_budget_above_ten_percent_is_no_result_and_names_its_largest_part(tmp_path):
    """Strong stiction (Coulomb x8, static x3, Stribeck 0.1 rad/s): K_fc* changes with the
    amplitude by as much as itself; the result says it cannot tell, with the part and the fix,
    instead of a converged value with +-50 %."""
    P, FC0 = bench_tune_matrix._plant, bench_tune_matrix.FC0
    plant = P(coulomb=8 * FC0, static=24 * FC0, stribeck_velocity=0.1, noise_std=2e-3, seed=5)
    t = bench_tune_matrix.run_row(plant, {"search": {"k_fc_max": 2.0}})
    s = t["search"]
    assert not s["converged"] and t["k_fc_star"] is None and s["sigma_v"] is None
    assert s["stop_reason"].startswith("cannot tell K_fc* better than")
    assert "the largest part is 'amplitude'" in s["stop_reason"] and "tune.amplitude_max_rad" in s["stop_reason"]
    assert s["sigma_total_v"] > ex.MAX_SIGMA_RE_K_FC * t["k_fc_best_measured"]
    assert max(s["sigma_parts_v"], key=s["sigma_parts_v"].get) == "amplitude"


def test_second_amplitude_stays_within_the_configured_limits(tmp_path):
    """A fixed amplitude of 0.5 rad with limits.max_amplitude_rad 0.6: the budget's second
    amplitude is not 1 rad (beyond what the preflight checked) but 0.25 rad."""
    from fwsim_drive import FwSimDrive, plant_file
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5, "search": {"k_fc_max": 0.3}})
    cfg["limits"]["max_amplitude_rad"] = 0.6
    with FwSimDrive(plant_file({"plant": {"viscous": 2e-3}}, directory=str(tmp_path))) as drive:
        drive.enable()
        results, _ = ex.tune(ex.Session(drive, cfg, str(tmp_path / "out"), log=lambda s: None))
    amps = results["search"]["budget"]["k_fc_at_amplitude"]["amplitude_rad"]
    assert amps == [0.5, 0.25]
    assert results["search"]["converged"] and abs(results["k_fc_star_error_re_truth"]) <= 0.02
