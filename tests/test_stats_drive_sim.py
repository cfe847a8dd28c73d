"""On-drive statistics through the CANopen node of drive_sim (python-canopen as the peer):
one small SDO upload of 0x2041 instead of the recording, the same HOSIDFs as from the raw
samples of the same run, the tune step on statistics, and bad requests refused by the
drive with its SDO abort and one error line naming the limit."""
import os

import numpy as np
import pytest
import yaml

from fftune.analysis.errors import FftuneError
from fftune.analysis.hosidf import hosidf
from fftune.analysis.stats import harmonic_stats, hosidf_from_stats, relative_difference
from fftune.host.cli import main
from fftune.host.drive import BusOptions, DriveClient
from fftune.host.experiments import sine_request
from fftune.host.sim import start_drive_sim
from host_fixtures import EDS, REPO, drive_sim_missing_reason

pytestmark = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                reason=drive_sim_missing_reason() or "")

PLANT = os.path.join(REPO, "configs", "plant_twomass.yaml")
DEMO = os.path.join(REPO, "configs", "demo.yaml")
TUNE_STATS = {"harmonics": 7, "signals": ["reference", "motor_angle"], "power": ["error"]}


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    drive = start_drive_sim(PLANT, log_path=str(d / "drive_sim.log"))
    yield drive
    drive.stop()


@pytest.fixture()
def drive(sim):
    with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False) as d:
        d.enable()
        yield d


def _tune_request(kfc=0.05, n=4096, cycles=1, periods=2):
    return sine_request(inject="reference", amplitude_peak=0.5, n=n, cycles=cycles, settle=1,
                        periods=periods, kfc=kfc, kv=0.0)


def test_one_run_captured_both_ways_gives_the_same_hosidf(drive):
    rec = drive.run(_tune_request(), signals=("reference", "motor_angle", "error"), capture="both",
                    stats=TUNE_STATS, desc="both")
    st = rec.stats
    assert st is not None and st.periods == 2 and st.harmonics == 7
    n = 4096
    r, y = rec.signals["reference"], rec.signals["motor_angle"]
    h_raw = hosidf(r.reshape(1, 2, n), y.reshape(1, 2, n), fs=rec.fs_hz, n_harmonics=7, f0=rec.fs_hz / n)
    h_st = hosidf_from_stats(st, st, u_name="reference", y_name="motor_angle", fs=rec.fs_hz, n=n, cycles=1)
    assert relative_difference(h_st.H, h_raw.H, abs(h_raw.H[0])) <= 1e-5
    ref = harmonic_stats({"motor_angle": y}, n=n, cycles=1, harmonics=7)
    assert relative_difference(st.mean["motor_angle"], ref.mean["motor_angle"]) <= 1e-5
    e = rec.signals["error"]
    assert abs(st.rms("error") / np.sqrt(np.mean(e ** 2)) - 1) <= 1e-5


def test_statistics_only_uploads_a_few_hundred_bytes(drive):
    rec = drive.run(_tune_request(), capture="stats", stats=TUNE_STATS, desc="stats")
    assert rec.signals == {}
    assert int(drive.get("rec_bytes")) == 0                 # nothing recorded
    size = int(drive.get("stat_bytes"))
    assert size == 8 + 2 * 7 * 12 + 8 == 184                 # <= 200 bytes per tune experiment
    assert rec.stats.periods == 2


def test_more_harmonics_than_the_drive_holds_is_its_abort_with_the_limit(drive):
    with pytest.raises(FftuneError) as exc:
        drive.run(_tune_request(), capture="stats", stats=dict(TUNE_STATS, harmonics=9))
    msg = str(exc.value)
    assert "SDO abort 0x06090031" in msg and "at most 8 harmonics" in msg and "\n" not in msg


def test_more_signals_than_the_drive_holds_is_its_abort_with_the_limit(drive):
    four = {"harmonics": 3, "signals": ["reference", "plant_input", "motor_angle", "error"]}
    with pytest.raises(FftuneError, match=r"SDO abort 0x06090031.*at most 3 signals"):
        drive.run(_tune_request(), capture="stats", stats=four)


def test_line_above_nyquist_is_refused_by_the_drive_naming_the_limit(drive):
    # sine at bin 300 of N = 4096: harmonic 7 is line 2100 >= N/2 = 2048
    with pytest.raises(FftuneError) as exc:
        drive.run(_tune_request(cycles=300), capture="stats", stats=TUNE_STATS)
    msg = str(exc.value)
    assert "SDO abort 0x06040043" in msg and "line 2100" in msg and "N/2 = 2048" in msg
    assert int(drive.get("run_last_error")) == 9 and int(drive.get("run_state")) != 1


def test_fftune_tune_on_statistics_matches_raw(sim, tmp_path):
    """`fftune tune` with capture: stats and capture: raw on the same plant: the same K_fc*
    within the search's reported uncertainty. With statistics nothing is recorded: the
    search works from the mean HOSIDFs and their period-to-period variance (184 bytes per
    experiment); a second call resumes every experiment from the statistics captures."""
    cfg = yaml.safe_load(open(DEMO))
    cfg["tune"].update(frequency_hz=1.25, period_samples=2048)
    cfg["tune"]["sweep"]["points"] = 5
    cfg["tune"]["viscous"]["enabled"] = False
    out = {}
    for mode in ("stats", "raw"):
        cfg["tune"]["capture"] = mode
        path = tmp_path / f"{mode}.yaml"
        path.write_text(yaml.safe_dump(cfg))
        d = tmp_path / mode
        assert main(["tune", "--config", str(path), "--out", str(d), "--port", str(sim.port),
                     "--no-progress", "--no-figures"]) == 0
        out[mode] = (yaml.safe_load(open(d / "results.yaml"))["tune"], d)
    (ts, ds), (tr, dr) = out["stats"], out["raw"]
    caps = os.listdir(ds / "captures")
    assert caps and all(f.endswith(".stats.json") for f in caps), caps
    assert all(f.endswith(".h5") for f in os.listdir(dr / "captures"))
    assert ts["search"]["converged"] and tr["search"]["converged"]
    unc = max(ts["search"]["uncertainty"] or 0, tr["search"]["uncertainty"] or 0, 1e-4)
    assert abs(ts["k_fc_star"] - tr["k_fc_star"]) <= 2 * unc
    # the propagated noise is of the size of the per-period spread (both > 0)
    sd_s = [e["ratio_std"] for e in ts["search"]["evaluations"]]
    sd_r = [e["ratio_std"] for e in tr["search"]["evaluations"]]
    assert 0 < np.median(sd_s) and 0 < np.median(sd_r)
    assert 0.2 <= np.median(sd_s) / np.median(sd_r) <= 5
    # resumed from the statistics captures alone: the same result, no experiment
    cfg["tune"]["capture"] = "stats"
    assert main(["tune", "--config", str(tmp_path / "stats.yaml"), "--out", str(ds),
                 "--port", str(sim.port), "--no-progress", "--no-figures"]) == 0
    again = yaml.safe_load(open(ds / "results.yaml"))
    assert again["experiments"]["measured"] == 0
    assert again["tune"]["k_fc_star"] == ts["k_fc_star"]
    # two sessions are two sets of experiments (the plant starts each from where the last
    # run left it): close, not equal; the same run both ways is compared exactly above
    np.testing.assert_allclose(ts["sweep"]["ratio"], tr["sweep"]["ratio"], rtol=1e-2)


def test_quantify_on_statistics_equals_quantify_on_the_samples_of_the_same_runs(sim, tmp_path):
    """capture: both, then the same session resumed from the raw captures alone (the
    .stats.json removed): the HOSIDF levels agree to 1e-5 of H_1."""
    cfg = yaml.safe_load(open(DEMO))
    cfg["quantify"].update(frequencies_hz=[2.5, 5.0], rms_levels=[0.2], repeats=2, period_samples=1024,
                           periods=2, capture="both")
    path = tmp_path / "q.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "q"
    args = ["quantify", "--config", str(path), "--out", str(out), "--port", str(sim.port),
            "--no-progress", "--no-figures"]
    assert main(args) == 0
    q_stats = yaml.safe_load(open(out / "results.yaml"))["quantify"]
    caps = out / "captures"
    stats_files = [f for f in os.listdir(caps) if f.endswith(".stats.json")]
    assert len(stats_files) == 4 and len([f for f in os.listdir(caps) if f.endswith(".h5")]) == 4
    for f in stats_files:
        os.remove(caps / f)
    assert main(args) == 0
    res = yaml.safe_load(open(out / "results.yaml"))
    assert res["experiments"] == {"measured": 0, "resumed": 4}
    q_raw = res["quantify"]
    for key in ("odd_relative_level", "even_relative_level"):
        np.testing.assert_allclose(q_stats[key], q_raw[key], rtol=0, atol=1e-5)
    assert q_stats["max_odd_relative_level"] > 1e-3     # something to compare
