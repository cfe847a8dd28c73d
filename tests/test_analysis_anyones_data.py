"""Detection and offline analysis of anyone's data (issue 23): one test (or more) per
numbered point, each failing on the code before the issue (5a35087)."""
import json
import os
import re
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io

import fftune.analysis as fa
from fftune.analysis.bla import (bla_levels, detect_excited_lines, f_sf_even, level_verdict,
                                 robust_bla)
from fftune.analysis.errors import InputError
from fftune.analysis.hosidf import hosidf
from fftune.analysis.multisine import multisine_realizations, random_odd_multisine
from fftune.host.cli import main

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "firmware_sim" / "tests"))
import groundtruth_systems as gt  # noqa: E402

DATA = REPO / "tests" / "data" / "kul_motorbench_twomass.npz"


def cli(capsys, *args):
    code = main(["analyze", *map(str, args)])
    out = capsys.readouterr()
    return code, out.out, out.err


def full_grid(m, p, n, k_max, seed=0, rms=0.5):
    rng = np.random.default_rng(seed)
    t = np.arange(n)
    k = np.arange(1, k_max + 1)
    u = np.stack([np.cos(2 * np.pi * np.outer(t, k) / n + rng.uniform(0, 2 * np.pi, k.size)).sum(1)
                  for _ in range(m)])
    u = rms * u / u.std()
    return np.repeat(u[:, None, :], p, axis=1), rng


# 1 -------------------------------------------------------------------------------------
def test_full_grid_verdict_from_the_excited_lines():
    u, rng = full_grid(6, 4, 1024, 200)
    cubic = robust_bla(u, u + 0.3 * u ** 3 + 1e-2 * rng.standard_normal(u.shape), fs=1000.0)
    assert cubic.grid == "full" and cubic.nonexcited_bins.size == 0
    s = cubic.summary
    assert s["excited_detected"] is True and s["excited_lines_over_noise_6db"] > 150
    v = level_verdict(s)
    assert v["causes"] == ["nonlinear distortion (excited lines)"]
    assert "var_total 6 dB over var_noise" in v["text"] and "re output" in v["text"]
    lin = robust_bla(u, u + 1e-2 * rng.standard_normal(u.shape), fs=1000.0)
    assert lin.summary["excited_detected"] is False
    assert level_verdict(lin.summary)["causes"] == ["linear"]
    # the reason given is the actual one: P = 5 here, M = 1 is what is missing (a linear
    # plant: nothing above the band either)
    one, _ = full_grid(1, 5, 1024, 200)
    v = level_verdict(robust_bla(one, 2.0 * one, fs=1000.0).summary)
    assert v["causes"] == ["cannot tell"] and "M = 1" in v["text"] and "P = 1" not in v["text"]
    assert "no distortion above the band either" in v["text"]
    # since issue 31 the lines above the band (up to 3 x 200, where the input is clean)
    # show a cubic's distortion
    v = level_verdict(robust_bla(one, one + 0.3 * one ** 3, fs=1000.0).summary)
    assert v["causes"] == ["nonlinear distortion (above the band)"]


# 2 -------------------------------------------------------------------------------------
def test_hosidf_refuses_a_multisine_library_and_cli(capsys):
    z = np.load(DATA)
    u = z["B_iq"][None, 1:].astype(float)[None]          # (1, 1, 19, 2500)
    y = z["B_theta_motor"][None, 1:].astype(float)[None]
    with pytest.raises(InputError, match="not one sine"):
        hosidf(u[0], y[0], fs=2500.0)
    code, out, err = cli(capsys, "hosidf", DATA, "--period", 2500, "--settle-periods", 1,
                         "--columns", "u=B_iq,y=B_theta_motor")
    assert code == 2 and out == ""
    assert err.startswith("fftune: error: input u: not one sine") and err.count("\n") == 1
    # a sine with a 3rd harmonic at -20 dB (a distorted actuator) is still a sine
    t = np.arange(1024)
    s = np.sin(2 * np.pi * 8 * t / 1024) + 0.1 * np.sin(2 * np.pi * 24 * t / 1024)
    assert hosidf(s.reshape(1, 1, -1), s.reshape(1, 1, -1), fs=1024.0, n_harmonics=3).bin == 8
    # ... and a second tone at -14 dB is refused by default
    two = np.sin(2 * np.pi * 8 * t / 1024) + 0.2 * np.sin(2 * np.pi * 13 * t / 1024)
    with pytest.raises(InputError, match="13 Hz"):
        hosidf(two.reshape(1, 1, -1), two.reshape(1, 1, -1), fs=1024.0, n_harmonics=3)


# 3 -------------------------------------------------------------------------------------
def _sim(tmp_path, counts, friction, levels=(0.3, 1.0)):
    import test_analysis_detect as td
    plant = {"viscous": 2e-3} if friction else {"viscous": 2e-3, "coulomb": 0.0, "static": 0.0}
    p = td.write_plant(tmp_path / f"p{counts}{friction}.yaml",
                       {"sensor": {"counts_per_rev": counts}, "plant": plant})
    res, _ = td.simulate_detect(p, levels=list(levels))
    return res


PLANT = ("plant odd nonlinearity", "plant even nonlinearity")


@pytest.mark.parametrize("counts", [128, 200, 1024, 4096])
def test_coarse_encoder_on_a_frictionless_plant_is_not_a_plant_nonlinearity(tmp_path, counts):
    res = _sim(tmp_path, counts, friction=False)
    assert res["encoder_step_rad"] == pytest.approx(2 * np.pi / counts, rel=1e-4)
    for lv in res["levels"]:
        assert not set(lv["causes"]) & set(PLANT), (counts, lv["verdict"])
        assert lv["summary_db"]["quantisation_model"].startswith("periodic")


@pytest.mark.parametrize("counts", [2000, 4096])
def test_friction_above_the_quantisation_is_still_detected(tmp_path, counts):
    res = _sim(tmp_path, counts, friction=True)
    assert any("plant odd nonlinearity" in lv["causes"] for lv in res["levels"])
    assert not any("plant even nonlinearity" in lv["causes"] for lv in res["levels"])


def test_quantisation_error_of_a_periodic_signal_is_periodic_and_odd():
    from fftune.analysis.bla import quantisation_error_lines
    n = 1024
    t = np.arange(n)
    s = 3.3 * np.sin(2 * np.pi * t / n) + 1.1 * np.sin(2 * np.pi * 3 * t / n + 0.4)
    q = 0.5
    lines = np.abs(quantisation_error_lines(s, q, 0.0, np.arange(1, 60)))
    # half-wave symmetric signal, odd quantiser: the error sits on odd lines only
    assert np.max(lines[1::2]) < 1e-9 * np.max(lines[0::2])
    # and far above the white floor q^2/12 spread over N/2 lines at the low odd lines
    assert np.max(lines[0::2]) ** 2 > 10 * n * q ** 2 / 12
    # dither by noise of q shrinks it (exp(-2 pi^2 k^2 sigma^2 / q^2) per harmonic)
    assert np.max(np.abs(quantisation_error_lines(s, q, q, np.arange(1, 60)))) < 1e-3 * np.max(lines)


# 4 -------------------------------------------------------------------------------------
def test_line_finder_band_limited_record_with_in_band_distortion():
    rng = np.random.default_rng(0)
    u, exc = gt._band_limited(rng, 0, 0.5)
    rec = np.repeat(u[:, None, :], 2, axis=1)
    found, info = detect_excited_lines(rec, return_info=True)
    np.testing.assert_array_equal(found, exc)
    assert info["confidence"] == "clear" and info["margin_db"] > 20


def test_line_finder_a_stray_tone_keeps_the_odd_grid():
    d = multisine_realizations(2, 1.0, 4096, k_min=3, k_max=400, seed=1)
    u = np.stack([x.period for x in d])
    t = np.arange(4096)
    u = u + d[0].amplitudes[0] * 10 ** (-10 / 20) * np.cos(2 * np.pi * 150 * t / 4096 + 0.3)
    rec = np.repeat(u[:, None, :], 3, axis=1)
    rec = rec + 1e-6 * np.random.default_rng(0).standard_normal(rec.shape)
    found, info = detect_excited_lines(rec, return_info=True)
    np.testing.assert_array_equal(found, d[0].excited)
    np.testing.assert_array_equal(info["stray_bins"], [150])
    res = robust_bla(rec, rec + 0.1 * rec ** 3)
    assert res.grid == "random odd" and res.summary["parity_classifiable"]
    assert 150 not in res.nonexcited_bins
    assert any("stray tones: bin 150 at -10 dB" in note for note in res.notes)


# 5 -------------------------------------------------------------------------------------
def test_plant_referred_lines_where_the_output_is_at_noise_are_not_flagged():
    z = np.load(DATA)
    res = robust_bla(z["B_iq"][None].astype(float), z["B_theta_motor"][None].astype(float),
                     fs=2500.0, settle_periods=1)
    six = 10 * np.log10(4.0)
    at_noise = res.nonexcited_db - res.nonexcited_noise_db <= six
    assert at_noise.sum() > 20
    flagged = res.plant_db - res.plant_expected_db > six
    assert not np.any(flagged & at_noise)
    s = res.summary
    assert s["plant_output_at_noise_lines_not_counted"] > 10     # what the old rule counted
    assert s["plant_even_lines_over_noise_6db"] < 60             # was 80 of 118


# 6 -------------------------------------------------------------------------------------
def test_narrow_band_nonlinearity_is_seen_per_octave_and_one_odd_re_even(tmp_path, capsys):
    # a cubic whose distortion is low-pass filtered (the cubic circuit's feedback): strong
    # in the lowest octaves, at the noise above 60 Hz, where most detection lines are
    m, p, n, fs = 4, 4, 4096, 1000.0
    d = multisine_realizations(m, fs, n, k_min=1, k_max=800, seed=3, rms=0.5)
    u = np.stack([x.period for x in d])
    y = u + gt.periodic_filter(u ** 3, b=(1e-3,), a=(1.0, -1.9, 0.9025))
    rng = np.random.default_rng(4)
    u4, y4 = np.repeat(u[:, None], p, 1), np.repeat(y[:, None], p, 1) + 1e-2 * rng.standard_normal((m, p, n))
    np.savez(tmp_path / "c.npz", u=u4.ravel(), y=y4.ravel(), fs=fs, n_period=n, realizations=m)
    code, out, err = cli(capsys, "bla", tmp_path / "c.npz", "--json", tmp_path / "c.json")
    assert code == 0, err
    s = json.loads((tmp_path / "c.json").read_text())["summary"]
    bands = s["bands"]
    assert len(bands) >= 5
    first, last = bands[0], bands[-1]
    assert first["odd"]["max_re_noise_db"] > 25 and first["odd_re_even_db"] > 20
    assert last["odd"]["median_re_noise_db"] < 3
    # the median over all lines hides it (the figure that was printed as "odd re even")
    assert abs(s["odd_line_median_re_noise_db"] - s["even_line_median_re_noise_db"]) < 6
    assert s["odd_re_even_db"] > 10
    # one odd-re-even figure, the same in print and JSON
    assert "line_median_odd_re_even_db" not in s
    printed = re.search(r"odd re even \(power ratio\)\s*: ([+-]\d+\.\d) dB", out).group(1)
    assert float(printed) == pytest.approx(s["odd_re_even_db"], abs=0.051)
    assert "per octave" in out and f"{bands[0]['odd']['max_re_noise_db']:+6.1f}" in out


def _doc_examples():
    text = (REPO / "docs" / "analysis.md").read_text()
    blocks = re.findall(r"```console\n(.*?)```", text, flags=re.S)
    out = []
    for block in blocks:
        lines = block.rstrip("\n").split("\n")
        if lines[0].startswith("$ fftune analyze"):
            out.append((lines[0][2:], "\n".join(lines[1:])))
    return out


def test_docs_analysis_examples_are_what_the_commands_print(capsys, monkeypatch):
    examples = _doc_examples()
    assert len(examples) >= 3
    monkeypatch.chdir(REPO)
    for command, expected in examples:
        argv = shlex.split(command)
        assert argv[0] == "fftune"
        code = main(argv[1:])
        got = capsys.readouterr()
        text = (got.out + got.err).rstrip("\n")
        assert text == expected, command
        assert code == (2 if "fftune: error:" in expected else 0)


# 7 -------------------------------------------------------------------------------------
def test_cross_coupling_is_named_unmeasured_inputs_not_a_plant_nonlinearity():
    ok, causes, text, _ = gt.judge("cross-coupling", 0)
    assert causes == ["unmeasured inputs"], text
    assert "MIMO" in text
    lv = gt.cross_coupling_levels()
    assert lv.notes and "not measured" in lv.notes[0]
    for res in lv.results:
        v = level_verdict(res.summary)
        assert v["causes"] == ["unmeasured inputs or a scale-free nonlinearity"]
    # a real nonlinearity changes with the level: no such note
    u_lv, y_lv = [], []
    for lvl in (0.1, 0.3, 1.0):
        u, _ = gt.excitation(0, lvl)
        x = gt.periodic_filter(u)
        u_lv.append(np.repeat(u[:, None], 3, 1))
        y_lv.append(np.repeat((x + 4 * x ** 3)[:, None], 3, 1)
                    + 1e-4 * np.random.default_rng(1).standard_normal((u.shape[0], 3, u.shape[1])))
    assert bla_levels(u_lv, y_lv).notes == []


# 8 -------------------------------------------------------------------------------------
def test_mat_in_matlab_column_layout_is_read_or_refused_naming_the_layout(tmp_path, capsys):
    z = np.load(DATA)
    u, y = z["B_iq"].astype(float), z["B_theta_motor"].astype(float)       # (P, N)
    scipy.io.savemat(tmp_path / "cols.mat", {"u": u.T, "y": y.T, "fs": 2500.0})   # N x P
    scipy.io.savemat(tmp_path / "rows.mat", {"u": u, "y": y, "fs": 2500.0})       # P x N
    outs = []
    for name in ("cols.mat", "rows.mat"):
        code, out, err = cli(capsys, "bla", tmp_path / name, "--period", 2500,
                             "--settle-periods", 1, "--json", tmp_path / f"{name}.json")
        assert code == 0, err
        outs.append(json.loads((tmp_path / f"{name}.json").read_text()))
    assert outs[0]["G"] == outs[1]["G"] and len(outs[0]["freq"]) == 60
    code, out, err = cli(capsys, "bla", tmp_path / "cols.mat", "--period", 2000)
    assert code == 2 and "2500 x 20 matrix" in err and "N x P" in err and err.count("\n") == 1


def test_csv_time_column_checks_fs(tmp_path, capsys):
    z = np.load(DATA)
    u, y = z["B_iq"].ravel(), z["B_theta_motor"].ravel()
    t = np.arange(u.size) / 2500.0
    f = tmp_path / "t.csv"
    np.savetxt(f, np.c_[t, u, y], delimiter=",", header="time_s,u,y", comments="", fmt="%.10g")
    code, out, err = cli(capsys, "bla", f, "--period", 2500, "--fs", 2.5)
    assert code == 2 and out == ""
    assert err == ("fftune: error: " + str(f) + ": --fs 2.5 Hz disagrees with the time column "
                   "'time_s' (2500 Hz from its spacing)\n")
    code, out, err = cli(capsys, "bla", f, "--period", 2500, "--settle-periods", 1)
    assert code == 0 and "fs = 2500 Hz" in out


def test_open_loop_data_is_not_called_distortion_in_the_loop():
    ok, causes, text, res = gt.judge("input distortion", 0)
    assert ok and not res.known_reference
    assert "in the loop" not in text and "at the output" in text


def test_a_two_period_disturbance_is_explained_in_a_note():
    m, p, n = 4, 8, 1024
    d = multisine_realizations(m, 1.0, n, k_min=1, k_max=200, seed=2, rms=0.5)
    u = np.repeat(np.stack([x.period for x in d])[:, None], p, 1)
    t = np.arange(p * n)
    # a disturbance of period 2N: sign flips every period, the same in every realization
    dist = 0.05 * np.sin(2 * np.pi * (np.arange(1, 200, 2)[:, None] + 0.5) * t / n
                         + np.arange(100)[:, None]).sum(0).reshape(p, n)
    y = u + dist[None] + 1e-4 * np.random.default_rng(0).standard_normal(u.shape)
    res = robust_bla(u, y)
    assert res.summary["n_var_nl_negative"] > 0.8 * res.bins.size
    assert any("2N" in note and "overestimated" in note for note in res.notes)
    # the figures in the note: the share of var_nl < 0 lines, and what noise alone gives
    # (P(F < 1) for F(2 (M - 1), 2 M (P - 1)))
    share = 100 * res.summary["n_var_nl_negative"] / res.bins.size
    alone = 100 * (1 - f_sf_even(np.array(1.0), 2 * (m - 1), 2 * m * (p - 1)))
    note = next(n for n in res.notes if "2N" in n)
    assert note.startswith(f"{share:.0f} % of the lines have var_nl < 0 where noise alone "
                           f"gives {alone:.0f} %")
    clean = robust_bla(u, u + 1e-4 * np.random.default_rng(0).standard_normal(u.shape))
    assert not any("2N" in note for note in clean.notes)


# 9 -------------------------------------------------------------------------------------
def test_library_edges():
    with pytest.raises(InputError, match="f_max = 600 Hz lies above the Nyquist"):
        random_odd_multisine(1000.0, 1000, 2, f_min=1.0, f_max=600.0)
    random_odd_multisine(1000.0, 1000, 2, f_min=1.0, f_max=500.0)       # fs/2: "all"
    t = np.arange(64)
    s = np.sin(2 * np.pi * 10 * t / 64).reshape(1, 1, -1)
    with pytest.raises(InputError) as err:
        hosidf(s, s, fs=64.0, n_harmonics=5)
    assert "--" not in str(err.value) and "harmonics K" in str(err.value)
    doc_names = set(re.findall(r"^([A-Za-z_][A-Za-z0-9_]*(?:, [A-Za-z_][A-Za-z0-9_]*)*)[ \t]+--",
                               fa.__doc__, flags=re.M))
    names = {n for group in doc_names for n in group.split(", ")}
    assert len(names) > 25 and names <= set(fa.__all__), names - set(fa.__all__)
    for name in names:
        assert getattr(fa, name) is not None


def test_settle_periods_option_and_its_deprecated_alias(capsys):
    args = ("bla", DATA, "--period", 2500, "--columns", "u=B_iq,y=B_theta_motor")
    code, new, err = cli(capsys, *args, "--settle-periods", 1)
    assert code == 0 and err == "" and "T = 1" in new
    code, old, err = cli(capsys, *args, "--skip-periods", 1)
    assert code == 0 and old == new
    assert err == ("fftune: warning: --skip-periods is deprecated, use --settle-periods "
                   "(the library's settle_periods)\n")


def test_bla_to_python_control_frd():
    control = pytest.importorskip("control", reason="python-control is optional and not "
                                                    "installed here (pip install control)")
    designs = multisine_realizations(2, 100.0, 256, k_min=1, k_max=60, seed=1)
    u = np.repeat(np.stack([x.period for x in designs])[:, None], 2, 1)
    res = robust_bla(u, gt.periodic_filter(u), fs=100.0)
    frd = res.to_frd()
    assert isinstance(frd, control.FrequencyResponseData)
    np.testing.assert_allclose(frd.omega, 2 * np.pi * res.freq)
    for i in (0, 3, res.freq.size - 1):
        np.testing.assert_allclose(np.squeeze(frd(2j * np.pi * res.freq[i])), res.G[i])


# 10 ------------------------------------------------------------------------------------
def test_class_test_false_alarm_rate_on_pure_noise_with_200_lines():
    """~200 detection lines of pure noise, nu = 4: without the Bonferroni factor n the
    strongest-line rule alone fires in ~18 % of the records; with it, in ~0.1 %."""
    m, p, n = 2, 3, 2048
    d = multisine_realizations(m, 1.0, n, k_min=1, k_max=330, seed=5)
    u = np.repeat(np.stack([x.period for x in d])[:, None], p, 1)
    alarms_nl = alarms_exc = 0
    trials = 60
    for seed in range(trials):
        y = u + 1e-3 * np.random.default_rng(seed).standard_normal(u.shape)
        s = robust_bla(u, y, excited_bins=d[0].excited, warn_transient=False).summary
        assert s["nonexcited_lines"] >= 190
        alarms_nl += bool(s["nl_detected"])
        alarms_exc += bool(s["excited_detected"])
    assert alarms_nl <= 2 and alarms_exc <= 2


def test_line_finder_full_grid_band_limited_force_and_a_designed_step():
    """A full grid whose force carries distortion 50 dB down up to N/4 (nothing between
    the excited lines to show the level): the lines beside the band scatter like noise and
    are not excited. A designed 20 dB amplitude step on an odd grid stays excited."""
    n, m = 8192, 3
    rng = np.random.default_rng(0)
    k = np.arange(n // 2 + 1)
    exc = np.arange(20, 151)
    spec = np.zeros((m, k.size), complex)
    spec[:, exc] = (n / 2) * np.exp(2j * np.pi * rng.random((m, exc.size)))
    dist = (n / 2) * 10 ** (-50 / 20) * (rng.standard_normal(spec.shape)
                                         + 1j * rng.standard_normal(spec.shape)) / np.sqrt(2)
    dist[:, k > n // 4] *= 1e-8
    dist[:, [0, -1]] = 0
    spec = np.where(np.isin(k, exc), spec, dist)
    u = np.repeat(np.fft.irfft(spec, n=n)[:, None], 3, 1) + 1e-9 * rng.standard_normal((m, 3, n))
    np.testing.assert_array_equal(detect_excited_lines(u), exc)
    step = np.arange(11, 601, 2)
    spec = np.zeros((m, k.size), complex)
    spec[:, step] = (n / 2) * np.where(step < 300, 1.0, 0.1) * np.exp(2j * np.pi * rng.random((m, step.size)))
    u = np.repeat(np.fft.irfft(spec, n=n)[:, None], 2, 1) + 1e-7 * rng.standard_normal((m, 2, n))
    np.testing.assert_array_equal(detect_excited_lines(u), step)


def test_cli_finds_the_encoder_step_and_does_not_blame_the_plant(tmp_path, capsys):
    u, y, kw, _ = gt.system("quantisation", seed=1)
    np.savez(tmp_path / "q.npz", u=u.ravel(), y=y.ravel(), fs=gt.FS, n_period=gt.N,
             realizations=u.shape[0])
    code, out, err = cli(capsys, "bla", tmp_path / "q.npz", "--json", tmp_path / "q.json")
    assert code == 0, err
    assert "quantisation step of y found from its values" in out
    doc = json.loads((tmp_path / "q.json").read_text())
    assert not any(c.startswith("plant ") for c in doc["verdict"]["causes"]), doc["verdict"]
    assert doc["summary"]["quantisation_model"].startswith("periodic")
    # the step given explicitly gives the same verdict
    code, out2, err = cli(capsys, "bla", tmp_path / "q.npz", "--y-step", kw["y_quantisation_step"])
    assert code == 0 and "verdict: " + doc["verdict"]["text"] in out2


def test_mimo_bla_takes_the_cross_coupling_into_g():
    """Two measured inputs, two outputs, cross-coupled, linear: the MIMO BLA gives all four
    entries and no nonlinearity; a cubic term on output 1 is found on its row only. The
    SISO analysis of u1 -> y1 calls the linear system's coupling 'unmeasured inputs'."""
    from fftune.analysis import robust_bla_mimo
    m, p, n = 8, 3, 2048
    d = multisine_realizations(2 * m, gt.FS, n, k_min=1, k_max=300, seed=4, rms=0.5)
    per = np.stack([x.period for x in d]).reshape(m, 2, n)         # own phases per input
    U = np.repeat(np.moveaxis(per, 1, -1)[:, None], p, 1)           # (M, P, N, 2)
    coupling = ((0.2,), (1.0, -0.6))
    y1 = gt.periodic_filter(per[:, 0]) + 0.8 * gt.periodic_filter(per[:, 1], *coupling)
    y2 = gt.periodic_filter(per[:, 1])
    noise = 1e-4 * np.random.default_rng(0).standard_normal((m, p, n, 2))
    Y = np.repeat(np.stack([y1, y2], -1)[:, None], p, 1) + noise
    res = robust_bla_mimo(U, Y, fs=gt.FS)
    w = np.exp(-2j * np.pi * res.bins / n)
    h12 = 0.8 * 0.2 / (1.0 - 0.6 * w)
    # the truth within 4 standard deviations of the estimate at every line
    assert np.all(np.abs(res.G[:, 0, 1] - h12) <= 4 * np.sqrt(res.var_total[:, 0, 1]))
    assert np.median(np.abs(res.G[:, 0, 1] / h12 - 1)) < 1e-3
    # no path u1 -> y2: zero within its uncertainty
    assert np.all(np.abs(res.G[:, 1, 0]) <= 4 * np.sqrt(res.var_total[:, 1, 0]))
    assert not res.detected.any()
    siso = robust_bla(U[..., 0], Y[..., 0], fs=gt.FS)
    assert level_verdict(siso.summary)["causes"] == ["unmeasured inputs"]
    Y3 = Y.copy()
    Y3[..., 0] += 4.0 * np.repeat(gt.periodic_filter(per[:, 0])[:, None], p, 1) ** 3
    res3 = robust_bla_mimo(U, Y3, fs=gt.FS)
    assert res3.detected[0].all() and not res3.detected[1].any()
    with pytest.raises(InputError, match="not a multiple of the n_u = 2 inputs"):
        robust_bla_mimo(U[:7], Y[:7], fs=gt.FS)
