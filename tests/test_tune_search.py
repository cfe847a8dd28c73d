"""The tune step on the firmware core + plant (tests/fwsim_drive.py, no CANopen) and on
drive_sim through CANopen (`fftune tune`): the fast subset of the tuning-accuracy matrix
(tests/bench/bench_tune.py), the coverage of the reported sigma over noise seeds, the
amplitude choice, the sweep-free search, and the one-line errors for bad tune keys."""
import os
import statistics
import sys

import numpy as np
import pytest
import yaml

from fftune.analysis.errors import FftuneError
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
