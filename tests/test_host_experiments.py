"""Experiments, captures, resume and reports on the Python test double of the drive.

FakeDriveForTests (tests/host_fixtures.py) simulates a mass with Coulomb + viscous
friction under the drive's controller law; the same checks against the real drive_sim
(CANopen) are in tests/test_host_drive_sim.py.
"""
import os

import numpy as np
import pytest
import yaml

from fftune.analysis.errors import FftuneError
from fftune.host import experiments as ex
from fftune.host.captures import export_captures
from fftune.host.config import validate
from fftune.host.pipeline import run_pipeline
from host_fixtures import FakeDriveForTests

FC, FV = 0.3, 0.02

SMALL = {
    "output": "unused",
    "detect": {"inject": "plant_input", "period_samples": 512, "band_hz": [5.0, 100.0],
               "group": 4, "seed": 3, "realizations": 3, "periods": 2, "settle_periods": 6,
               "rms_levels": [1.0, 3.0]},
    "quantify": {"inject": "reference", "period_samples": 1024, "frequencies_hz": [2.5, 5.0],
                 "rms_levels": [0.3], "repeats": 2, "periods": 1, "settle_periods": 2},
    "tune": {"frequency_hz": 2.5, "amplitude_rad": 0.5, "period_samples": 1024, "periods": 2,
             "settle_periods": 2, "sweep": {"k_fc_max": 1.0, "points": 11},
             "search": {"method": "root", "max_experiments": 8},
             "viscous": {"enabled": True, "k_v_max": 0.5, "max_experiments": 8}},
}


def _cfg(**over):
    raw = yaml.safe_load(yaml.safe_dump(SMALL))
    for k, v in over.items():
        raw[k].update(v)
    cfg = validate(raw, "test.yaml")
    cfg["_source"] = "test.yaml"
    return cfg


def _drive(**kw):
    d = FakeDriveForTests(fc_volt=FC, fv_volt=FV, noise_std=1e-5, **kw)
    d.enable()
    return d


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("tune"))
    session = ex.Session(_drive(), _cfg(), out, log=lambda s: None)
    results, data = ex.tune(session)
    return results, data, session, out


def test_automated_search_finds_the_coulomb_level(tuned):
    r, data, session, _ = tuned
    assert r["search"]["experiments"] <= 8
    assert abs(r["k_fc_star"] / FC - 1) < 0.02
    assert abs(r["search"]["relative_to_sweep_optimum"]) < 0.01
    assert r["true_coulomb_v"] == FC


def test_ratio_drops_tenfold_and_odd_phases_turn(tuned):
    r, data, _, _ = tuned
    assert r["ratio_at_zero"] / r["ratio_at_k_fc_star"] >= 10
    k, H = data["k_sweep"], data["H_sweep"]
    below = H[k < 0.9 * FC][-1]
    above = H[k > 1.1 * FC][0]
    for i in (2, 4):                                   # H_3, H_5
        turn = np.degrees(np.angle(above[i] / below[i]))
        assert abs(abs(turn) - 180) < 40


def test_viscous_friction_moves_the_rms_minimum_and_k_v_fixes_it(tuned):
    r, _, _, _ = tuned
    e = r["rms_error_rad"]
    assert e["sweep_min_at_k_fc"] > r["k_fc_star"]
    assert e["k_fc_star_k_v_star"] < min(e["sweep_min"], e["k_fc_star"])
    assert r["viscous"]["experiments"] <= 8


def test_captures_hold_metadata_and_export(tuned, tmp_path):
    _, _, session, out = tuned
    files = sorted(os.listdir(os.path.join(out, "captures")))
    assert len(files) == session.counts["measured"]
    from fftune.analysis import capture
    run = capture.read_run(os.path.join(out, "captures", files[0]))
    for key in ("parameters", "firmware_version", "eds_identity", "started_at", "finished_at",
                "fs_hz", "n_period", "record_periods"):
        assert key in run.meta
    for key in ("request", "identity", "config", "layout", "run_counter"):
        assert key in run.meta["metadata"]
    assert run.meta["parameters"]["kfc"] == run.meta["metadata"]["request"]["kfc"]
    assert len(run.signals["motor_angle"]) == run.meta["record_periods"] * run.meta["n_period"]
    mats = export_captures(os.path.join(out, "captures", files[0]), "mat", str(tmp_path))
    import scipy.io
    m = scipy.io.loadmat(mats[0], simplify_cells=True)
    (struct,) = [v for k, v in m.items() if not k.startswith("__")]    # one struct per capture
    np.testing.assert_array_equal(struct["signals"]["motor_angle"], run.signals["motor_angle"])
    assert struct["fs_hz"] == run.meta["fs_hz"] and struct["units"]["motor_angle"] == "rad"
    csvs = export_captures(os.path.join(out, "captures", files[0]), "csv", str(tmp_path))
    table = np.genfromtxt(csvs[0], delimiter=",", names=True, skip_header=1)
    np.testing.assert_allclose(table["motor_angle"], run.signals["motor_angle"], rtol=1e-8, atol=1e-12)


def test_detect_sees_odd_but_not_even_distortion(tmp_path):
    session = ex.Session(_drive(), _cfg(), str(tmp_path), log=lambda s: None)
    r, levels = ex.detect(session)
    assert r["levels"][0]["summary_db"]["odd_detected"] is True
    assert r["levels"][0]["summary_db"]["even_detected"] is False
    assert r["levels"][0]["summary_db"]["odd_re_even_db"] > 20
    assert "odd nonlinearity" in r["verdict"] and "no even" in r["verdict"]
    assert session.counts["measured"] == 2 * 3
    # u_max as read back with the runs; the fake drive's 1 and 3 V rms never reach 10 V
    assert r["u_max_v"] == 10.0
    assert [lv["saturation_fraction"] for lv in r["levels"]] == [0.0, 0.0]
    assert all(lv["causes"] == ["plant odd nonlinearity"] for lv in r["levels"])


def test_quantify_off_grid_frequency_is_refused_naming_the_key(tmp_path):
    cfg = _cfg(quantify={"frequencies_hz": [3.0]})
    session = ex.Session(_drive(), cfg, str(tmp_path), log=lambda s: None)
    with pytest.raises(FftuneError, match=r"key 'quantify.frequencies_hz': 3 Hz is not on the DFT grid"):
        ex.quantify(session)


class _Interrupting(FakeDriveForTests):
    def __init__(self, after, **kw):
        super().__init__(**kw)
        self.after = after

    def run(self, *a, **kw):
        if self.runs >= self.after:
            raise KeyboardInterrupt
        return super().run(*a, **kw)


def test_interrupted_experiment_resumes_from_its_captures(tmp_path):
    cfg = _cfg()
    d = _Interrupting(7, fc_volt=FC, fv_volt=FV, noise_std=1e-5)
    d.enable()
    with pytest.raises(KeyboardInterrupt):
        ex.tune(ex.Session(d, cfg, str(tmp_path), log=lambda s: None))
    assert len(os.listdir(tmp_path / "captures")) == 7
    assert not [f for f in os.listdir(tmp_path / "captures") if f.startswith(".tmp")]
    s2 = ex.Session(_drive(), cfg, str(tmp_path), log=lambda s: None)
    r2, _ = ex.tune(s2)
    assert s2.counts["resumed"] == 7
    fresh = ex.Session(_drive(), cfg, str(tmp_path / "fresh"), log=lambda s: None)
    r3, _ = ex.tune(fresh)
    assert r2["k_fc_star"] == r3["k_fc_star"]


def test_other_configuration_into_the_same_directory_is_refused(tmp_path):
    ex.detect(ex.Session(_drive(), _cfg(), str(tmp_path), log=lambda s: None))
    cfg2 = _cfg(detect={"rms_levels": [1.5, 3.0]})
    with pytest.raises(FftuneError, match="captured with other parameters"):
        ex.detect(ex.Session(_drive(), cfg2, str(tmp_path), log=lambda s: None))


def test_pipeline_writes_results_figures_and_report(tmp_path):
    results = run_pipeline(_drive(), _cfg(), str(tmp_path), log=lambda s: None)
    saved = yaml.safe_load(open(tmp_path / "results.yaml"))
    assert saved["tune"]["k_fc_star"] == results["tune"]["k_fc_star"]
    assert saved["experiments"]["measured"] > 0
    for name in ("figure3_output_spectrum_lowest", "figure3_output_spectrum_highest",
                 "figure4_bla_vs_level", "figure5_hosidf_vs_amplitude",
                 "figure7_tuning", "figure9_time_response"):
        png = tmp_path / f"{name}.png"
        assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    html = (tmp_path / "report.html").read_text()
    assert "figure7_tuning.png" in html and f"{results['tune']['k_fc_star']:.4g}" in html
    # each figure's caption ends with a conclusion computed from the data
    assert "H_3 turns by" in html and "the BLA changes by up to" in html
    assert results["detect"]["levels"][0]["verdict"].split(";")[0] in html


def test_drive_rate_mismatch_is_named(tmp_path):
    cfg = _cfg()
    cfg["drive"]["fs_hz"] = 5120.0
    with pytest.raises(FftuneError, match=r"key 'drive.fs_hz': the drive runs at 2560 Hz"):
        ex.Session(_drive(), cfg, str(tmp_path), log=lambda s: None)


def test_analysing_the_captures_again_gives_the_live_bla(tmp_path):
    from fftune.analysis import capture
    from fftune.analysis.bla import robust_bla
    from fftune.analysis.multisine import drive_lines
    session = ex.Session(_drive(), _cfg(), str(tmp_path), log=lambda s: None)
    r, levels = ex.detect(session)
    for li, live in enumerate(levels.results):
        data = capture.load_experiment(str(tmp_path / "captures"), experiment="detect", level_index=li)
        sig = {k: v.astype(np.float64) for k, v in data.signals.items()}   # stored float32
        again = robust_bla(sig["plant_input"], sig["motor_angle"], sig["excitation"],
                           fs=data.fs_hz, settle_periods=0,
                           excited_bins=drive_lines(r["period_samples"], r["k_min"], r["k_max"],
                                                    4, 3).excited, warn_transient=False)
        np.testing.assert_array_equal(again.G, live.G)
        np.testing.assert_array_equal(again.var_nl, live.var_nl)


def test_detect_at_the_reference_uses_the_recorded_reference(tmp_path):
    cfg = _cfg(detect={"inject": "reference", "rms_levels": [0.3]})
    session = ex.Session(_drive(), cfg, str(tmp_path), log=lambda s: None)
    r, levels = ex.detect(session)
    res = levels.results[0]
    assert res.known_reference
    assert r["levels"][0]["summary_db"]["odd_detected"] is True
    # The plant seen through the loop: a mass with friction, |G| falling with frequency.
    g = np.abs(res.G)
    assert g[0] > 10 * g[-1]
