"""Detect on the drive's line statistics (issue 13): the multisine line statistics the drive
accumulates (objects 0x2042/0x2043) give the detect step the same BLA, variances and verdict
as its raw samples, with a few kB on the bus instead of the recording; capture 'both'
reports the difference; a list the drive cannot hold is refused with the limit named, or,
when the capture mode was not asked for, detect falls back to raw samples and says so."""
import os
import sys

import numpy as np
import pytest

from fftune.analysis.errors import FftuneError
from fftune.host import experiments as ex
from fftune.host.config import validate

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "tests"))
sys.path.insert(0, os.path.join(REPO, "firmware_sim", "tests"))

DETECT = {"inject": "plant_input", "period_samples": 1024, "band_hz": [5.0, 100.0], "group": 4,
          "seed": 3, "realizations": 3, "periods": 3, "settle_periods": 3,
          "rms_levels": [0.3, 3.0]}


def _config(**detect):
    cfg = validate({"output": "unused", "detect": dict(DETECT, **detect)}, "test_detect_stats")
    cfg["_source"] = "test_detect_stats"
    return cfg


def _detect(tmp_path, plant_over, name, **detect):
    from fwsim_drive import FwSimDrive, plant_file
    with FwSimDrive(plant_file(plant_over, directory=str(tmp_path))) as drive:
        drive.enable()
        session = ex.Session(drive, _config(**detect), str(tmp_path / name), log=lambda s: None)
        return ex.detect(session)


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    """One detect with capture 'both' on the demo plant (noise, Coulomb friction, the
    2000-count encoder): raw analysis, statistics analysis, and their difference."""
    tmp = tmp_path_factory.mktemp("both")
    return _detect(tmp, {"sensor": {"noise_std": 1e-4}}, "out", capture="both",
                   encoder_step_rad=2 * np.pi / 2000)


def test_statistics_give_the_bla_of_the_samples(both):
    res, _ = both
    d = res["stats_vs_raw"]
    # float32 FFTs and sums on the drive against float64 of the same float32 samples
    assert d["max_rel_diff_G"] <= 1e-5
    assert d["max_rel_diff_var_total"] <= 1e-5
    assert d["max_rel_diff_var_noise"] <= 1e-5
    assert res["capture"] == "both"
    # the drive counts the samples at u_max (0x2040:11) exactly as the host does from u
    assert d["max_abs_diff_saturation_fraction"] == 0.0
    assert res["levels"][1]["saturation_fraction"] > 0 and d["same_causes"]


def test_stats_only_run_gives_the_same_verdict_as_raw(tmp_path, both):
    raw, raw_levels = both
    st, st_levels = _detect(tmp_path, {"sensor": {"noise_std": 1e-4}}, "stats", capture="stats",
                            encoder_step_rad=2 * np.pi / 2000)
    assert st["capture"] == "stats"
    np.testing.assert_allclose(st_levels.G, raw_levels.G, rtol=1e-5)
    np.testing.assert_allclose(st_levels.rms, raw_levels.rms, rtol=1e-6)
    for a, b in zip(st["levels"], raw["levels"]):
        assert a["causes"] == b["causes"]
    assert st["verdict"].split("; ")[:2] == raw["verdict"].split("; ")[:2]
    # nothing recorded crossed into the captures: statistics files only
    caps = os.listdir(tmp_path / "stats" / "captures")
    assert caps and all(c.endswith(".stats.json") for c in caps)
    # ... and a second session resumes from them with the same numbers
    again, again_levels = _detect(tmp_path, {"sensor": {"noise_std": 1e-4}}, "stats",
                                  capture="stats", encoder_step_rad=2 * np.pi / 2000)
    np.testing.assert_array_equal(again_levels.G, st_levels.G)


def test_too_many_lines_for_the_drive_are_refused_or_fall_back(tmp_path, monkeypatch):
    from fwsim_drive import FwSimDrive
    cap_lines = 8   # a drive that holds 8 lines: the band has far more
    real_get = FwSimDrive.get
    monkeypatch.setattr(FwSimDrive, "get", lambda self, name: cap_lines if name == "stat_lines_cap"
                        else real_get(self, name))
    real_set_lines = None

    def set_lines(sim, bins):
        if len(bins) > cap_lines:
            raise FftuneError(f"line statistics: {len(bins)} lines, the drive holds at most {cap_lines}")
        return real_set_lines(sim, bins)
    from fwsim import FwSim
    real_set_lines = FwSim.set_lines
    monkeypatch.setattr(FwSim, "set_lines", set_lines)
    with pytest.raises(FftuneError, match="the drive holds at most 8"):
        _detect(tmp_path, {}, "asked", capture="stats", rms_levels=[0.3], realizations=2)
    # not asked for (a bus model or a real drive chooses statistics): raw, and it says why
    from fwsim_drive import FwSimDrive as D
    monkeypatch.setattr(D, "plant_truth", lambda self: None)
    res, _ = _detect(tmp_path, {}, "default", rms_levels=[0.3], realizations=2)
    assert res["capture"] == "raw"
    assert "exceed the 8 lines" in res["capture_note"]


# ---- through drive_sim's CANopen node (python-canopen as the peer) --------------------------

def _drive_sim_skip():
    from host_fixtures import drive_sim_missing_reason
    reason = drive_sim_missing_reason()
    if reason is not None:
        pytest.skip(reason)


def _demo_config(tmp_path, **detect):
    import yaml
    cfg = yaml.safe_load(open(os.path.join(REPO, "configs", "demo.yaml")))
    cfg["detect"].update(dict(period_samples=1024, band_hz=[5.0, 100.0], group=4, realizations=2,
                              periods=2, settle_periods=3, rms_levels=[0.3]), **detect)
    cfg["quantify"]["enabled"] = False
    cfg["tune"]["enabled"] = False
    path = tmp_path / "detect.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_fftune_detect_on_statistics_over_canopen(tmp_path, capsys):
    """`fftune demo` with detect.capture stats: the line list goes down by SDO, the drive's
    statistics come up (0x2043), no recording crosses the bus, and results.yaml says so."""
    import yaml
    from fftune.host.cli import main
    _drive_sim_skip()
    out = tmp_path / "out"
    code = main(["demo", "--config", str(_demo_config(tmp_path, capture="stats")), "--out", str(out),
                 "--no-progress"])
    assert code == 0, capsys.readouterr().err
    res = yaml.safe_load(open(out / "results.yaml"))
    det = res["detect"]
    assert det["capture"] == "stats" and det["levels"][0]["causes"]
    assert sorted(os.listdir(out / "captures")) == ["detect-L00-M00.stats.json", "detect-L00-M01.stats.json"]
    # the statistics of every line from the lowest to the highest excited one
    import json
    doc = json.load(open(out / "captures" / "detect-L00-M00.stats.json"))
    bins = doc["line_stats"]["bins"]
    assert bins == list(range(bins[0], bins[-1] + 1)) and det["k_min"] <= bins[0] < bins[-1] <= det["k_max"]
    assert doc["line_stats"]["periods"] == 2 and doc["stats"] is None
    # offline analysis of such a directory: no samples, and it says where the analysis is
    assert main(["analyze", "bla", str(out / "captures")]) != 0
    err = capsys.readouterr().err
    assert "2 statistics-only captures" in err and "results.yaml" in err


def test_more_lines_than_the_drive_holds_is_one_error_line(tmp_path, capsys):
    """A band of 3839 lines (N = 8192, up to 1200 Hz) asked for as statistics: the preflight
    refuses it against the drive's capacity (0x2040:9) before anything moves; a client that
    writes the list anyway gets the drive's abort (0x06070012) as one line naming the limit."""
    from fftune.host.cli import main
    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.odmap import EXC_KINDS, INJECT
    from fftune.host.sim import start_drive_sim
    from host_fixtures import EDS
    _drive_sim_skip()
    cfg = _demo_config(tmp_path, capture="stats", period_samples=8192, band_hz=[0.3125, 1200.0])
    code = main(["demo", "--config", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not (tmp_path / "out").exists()
    assert len(err) == 1 and err[0].startswith("fftune: error: ") and "key 'detect.band_hz'" in err[0]
    assert "3839 lines is above 1024 lines" in err[0] and "0x2040:9" in err[0], err
    sim = start_drive_sim(os.path.join(REPO, "configs", "plant_twomass.yaml"),
                          log_path=str(tmp_path / "d.log"))
    try:
        with DriveClient(BusOptions(port=sim.port, eds=EDS), heartbeat_ms=250, progress=False) as c:
            c.enable()
            req = {"exc_kind": EXC_KINDS["multisine"], "exc_inject": INJECT["plant_input"],
                   "exc_amplitude": 0.3, "exc_period": 8192, "exc_settle_periods": 0,
                   "exc_record_periods": 1, "ms_k_min": 1, "ms_k_max": 3839, "ms_group": 0}
            with pytest.raises(FftuneError) as exc:
                c.run(req, capture="stats", lines=np.arange(1, 3840))
    finally:
        sim.stop()
    msg = str(exc.value)
    assert msg.startswith("line statistics: 3839 lines (bins 1 .. 3839)")
    assert "the drive holds at most 1024" in msg and "0x2040:9" in msg and "0x06070012" in msg


def test_a_line_at_nyquist_is_refused_by_the_drive_with_the_limit_named(tmp_path):
    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.sim import start_drive_sim
    from host_fixtures import EDS
    _drive_sim_skip()
    sim = start_drive_sim(os.path.join(REPO, "configs", "plant_twomass.yaml"),
                          log_path=str(tmp_path / "drive_sim.log"))
    try:
        with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False) as d:
            d.enable()
            params = {"exc_kind": 3, "exc_inject": 1, "exc_amplitude": 0.3, "exc_offset": 0.0,
                      "exc_period": 1024, "ms_k_min": 3, "ms_k_max": 100, "ms_group": 4, "ms_seed": 1,
                      "ms_realization": 0, "exc_settle_periods": 1, "exc_record_periods": 2}
            with pytest.raises(FftuneError, match=r"line 512 is at or above N/2 = 512 \(fs/2\).*0x06090030"):
                d.run(params, capture="stats", lines=[3, 5, 512])
            # a sine period of 1000 samples: no power of two for the drive's FFT, refused at
            # the start (stop reason 11) with the conditions named
            sine = {"exc_kind": 1, "exc_inject": 0, "exc_amplitude": 0.1, "exc_offset": 0.0,
                    "exc_period": 1000, "exc_sine_cycles": 4, "exc_settle_periods": 1,
                    "exc_record_periods": 2}
            with pytest.raises(FftuneError, match=r"line statistics: the drive refused the run "
                                                  r"\(stop reason 11.*power of two"):
                d.run(sine, capture="stats", lines=[4, 8, 12])
            # the drive still works: a list inside N/2 gives statistics of the run
            rec = d.run(params, capture="stats", lines=np.arange(3, 101))
            assert rec.line_stats.periods == 2 and rec.signals == {}
            assert rec.line_stats.saturated_samples == 0
            # 'both': the drive records r, u, y for its statistics; the samples asked for come up
            rec = d.run(params, capture="both", lines=np.arange(3, 101),
                        signals=("plant_input", "motor_angle"))
            assert set(rec.signals) == {"plant_input", "motor_angle"}
            assert rec.signals["motor_angle"].size == 2 * 1024 and rec.line_stats.periods == 2
    finally:
        sim.stop()


def test_noise_free_plant_the_drive_float32_floor_is_not_distortion(tmp_path):
    """An ideal encoder and no noise: the period-to-period spread is ~0, so the float32 FFT
    rounding of the drive's spectra (the same in every period) would pass for even
    distortion at the detection lines without its floor; with it both paths agree."""
    # the demo's detect at its 1 V level (where the unfloored path claimed even lines)
    res, _ = _detect(tmp_path, {"plant": {"viscous": 2e-3}, "sensor": {"counts_per_rev": 0, "noise_std": 0.0}},
                     "quiet", capture="both", rms_levels=[1.0], period_samples=4096,
                     band_hz=[2.5, 100.0], group=5, seed=7, realizations=4, periods=2, settle_periods=2)
    d = res["stats_vs_raw"]
    assert d["same_causes"], res["levels"]
    assert d["max_rel_diff_G"] <= 1e-5
    assert all("plant even nonlinearity" not in lv["causes"] for lv in res["levels"])
