"""Detection that says what the plant does (issue 12): plant-referred detection on the
simulated drive (ctypes core + plant) with known ground truth, grid-aware odd/even,
excited lines from a distorted input, per-line summary figures equal to Figure 3."""
import json
import os
import sys

import numpy as np
import pytest
import yaml

from fftune.analysis.bla import (classify_grid, detect_excited_lines, estimate_quantisation_step,
                                 level_verdict, robust_bla)
from fftune.analysis.multisine import drive_lines, drive_multisine, multisine_realizations
from fftune.host.cli import main
from fftune.host.experiments import detect_analysis

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "firmware_sim", "tests"))

LEVELS = [0.3, 1.0, 3.0]          # V rms at the plant input, as configs/demo.yaml
N, BAND, GROUP, SEED, M, P, T = 4096, (4, 160), 5, 7, 4, 2, 4


def write_plant(path, overrides):
    """configs/plant_twomass.yaml with {section: {key: value}} changed (drive_sim format)."""
    with open(os.path.join(REPO, "configs", "plant_twomass.yaml")) as f:
        base = yaml.safe_load(f)
    for section, values in overrides.items():
        base[section].update(values)
    with open(path, "w") as f:
        for section, values in base.items():
            f.write(f"{section}:\n" + "".join(f"  {k}: {v}\n" for k, v in values.items()))
    return path


def simulate_detect(plant_path, levels=LEVELS):
    """The detect experiment (multisine at the plant input, PD loop closed) on the C core."""
    from fwsim import FwSim
    lines = drive_lines(N, *BAND, GROUP, SEED)
    u_lv, y_lv, r_lv = [], [], []
    with FwSim(str(plant_path)) as sim:
        fs, u_max = sim.get("FS"), sim.get("U_MAX")
        for rms in levels:
            us, ys, rs = [], [], []
            for m in range(M):
                sim.enable()
                sim.configure(exc_kind=3, exc_inject=1, exc_amplitude=rms, exc_period=N,
                              exc_settle_periods=T, exc_record_periods=P, ms_k_min=BAND[0],
                              ms_k_max=BAND[1], ms_group=GROUP, ms_seed=SEED, ms_realization=m,
                              rec_signals=0x1F)
                sim.start()
                sim.run_until_idle()
                data, names = sim.record()
                sig = {name: data[:, i].astype(float) for i, name in enumerate(names)}
                us.append(sig["plant_input"].reshape(P, N))
                ys.append(sig["motor_angle"].reshape(P, N))
                rs.append(np.tile(drive_multisine(N, *BAND, GROUP, SEED, m, rms), (P, 1)))
            u_lv.append(np.stack(us))
            y_lv.append(np.stack(ys))
            r_lv.append(np.stack(rs))
    return detect_analysis(u_lv, y_lv, r_lv, fs=fs, excited_bins=lines.excited,
                           rms_levels=levels, u_max=u_max)


IDEAL = {"sensor": {"counts_per_rev": 0}}


def test_frictionless_plant_saturating_level_is_drive_saturation_not_plant(tmp_path):
    plant = write_plant(tmp_path / "p.yaml", dict(IDEAL, plant={"viscous": 2e-3, "coulomb": 0.0,
                                                                  "static": 0.0}))
    res, _ = simulate_detect(plant)
    low, mid, top = res["levels"]
    assert low["causes"] == ["linear"] and mid["causes"] == ["linear"]
    assert top["saturation_fraction"] > 0
    assert low["saturation_fraction"] == 0
    # the loop's output shows the saturation's odd distortion ...
    assert top["summary_db"]["odd_detected"] is True
    # ... the plant-referred lines do not, and the verdict names the drive, not the plant
    assert top["summary_db"]["plant_odd_detected"] is False
    assert top["causes"] == ["drive output saturation"]
    assert "drive output saturation at 3 V rms" in res["verdict"]
    assert "no odd nonlinearity in the plant" in res["verdict"]


def test_symmetric_friction_no_even_asymmetric_friction_even(tmp_path):
    sym = write_plant(tmp_path / "sym.yaml", dict(IDEAL, plant={"viscous": 2e-3}))
    res, _ = simulate_detect(sym, levels=[0.3, 1.0])
    for lv in res["levels"]:
        assert "plant odd nonlinearity" in lv["causes"]
        assert "plant even nonlinearity" not in lv["causes"]
    assert "no even nonlinearity in the plant" in res["verdict"]
    asym = write_plant(tmp_path / "asym.yaml", dict(IDEAL, plant={
        "viscous": 2e-3, "coulomb_asymmetry": 0.2, "static": 5.785e-3 * 1.2}))
    res, _ = simulate_detect(asym, levels=[0.3, 1.0])
    for lv in res["levels"]:
        assert "plant even nonlinearity" in lv["causes"]


def test_quantised_encoder_even_lines_are_not_called_plant_even(tmp_path):
    """The plant file's 2000-count encoder: the step is found from the recorded angle and
    the symmetric plant gets no even nonlinearity."""
    plant = write_plant(tmp_path / "q.yaml", {"plant": {"viscous": 2e-3}})
    res, _ = simulate_detect(plant, levels=[0.3, 3.0])
    assert res["encoder_step_rad"] == pytest.approx(2 * np.pi / 2000, rel=1e-4)
    assert "no even nonlinearity in the plant" in res["verdict"]
    assert "odd nonlinearity in the plant at 0.3 V rms" in res["verdict"]


def test_estimate_quantisation_step():
    rng = np.random.default_rng(0)
    q = 2 * np.pi / 2000
    y = np.cumsum(rng.standard_normal(20000)) * 1e-3
    assert estimate_quantisation_step(np.float32(np.round(y / q) * q)) == pytest.approx(q, rel=1e-4)
    assert estimate_quantisation_step(y) is None


def test_classify_grid():
    assert classify_grid(drive_lines(512, 1, 100, 5, 1).excited, 512)["grid"] == "random odd"
    assert classify_grid(np.arange(1, 100, 2), 512)["grid"] == "odd"
    odd_odd = classify_grid(np.arange(5, 200, 4), 512)
    assert odd_odd["grid"] == "odd-odd" and odd_odd["parity"]
    full = classify_grid(np.arange(1, 100), 512)
    assert full["grid"] == "full" and not full["parity"]
    removed = classify_grid(np.setdiff1d(np.arange(1, 100), np.arange(3, 100, 5)), 512)
    assert removed["grid"] == "full with removed lines" and not removed["parity"]
    assert not classify_grid(np.arange(2, 100, 2), 512)["parity"]


def test_full_grid_with_removed_lines_cubic_via_cli_no_parity_claim(tmp_path, capsys):
    m, p, n = 4, 3, 1024
    excited = np.setdiff1d(np.arange(1, 200), np.arange(3, 200, 5))    # one line in five out
    rng = np.random.default_rng(2)
    t = np.arange(n)
    u = np.stack([sum(np.cos(2 * np.pi * k * t / n + rng.uniform(0, 2 * np.pi)) for k in excited)
                  for _ in range(m)])
    u = 0.5 * u / u.std()
    y = u + 0.3 * u ** 3
    u = np.repeat(u[:, None, :], p, axis=1)
    y = np.repeat(y[:, None, :], p, axis=1) + 1e-4 * rng.standard_normal((m, p, n))
    np.savez(tmp_path / "d.npz", u=u.ravel(), y=y.ravel(), fs=1000.0, n_period=n)
    out = tmp_path / "r.json"
    code = main(["analyze", "bla", str(tmp_path / "d.npz"), "--realizations", str(m),
                 "--json", str(out)])
    text = capsys.readouterr().out
    assert code == 0
    s = json.loads(out.read_text())["summary"]
    assert s["grid"] == "full with removed lines"
    assert s["nl_detected"] is True
    assert s["odd_detected"] is None and s["even_detected"] is None
    assert s["odd_re_even_db"] is None
    assert any("only 'nonlinear'" in note for note in s["notes"])
    assert "no odd/even" in text


def distorted_input(notch_db, m=2, p=3, n=8192, seed=1):
    """A random odd multisine force shaped by the structure (a notch of notch_db) with
    broadband periodic distortion 30 .. 40 dB under the excited lines on every line."""
    rng = np.random.default_rng(seed)
    designs = multisine_realizations(m, 1.0, n, k_min=20, k_max=2400, seed=3)
    k = np.arange(n // 2 + 1)
    shape = 10 ** (-notch_db / 20 * np.exp(-((k - 900) / 60.0) ** 2)) * (1 + 0.5 * np.sin(k / 300))
    spec = np.zeros((m, k.size), complex)
    for i, d in enumerate(designs):
        spec[i, d.excited] = (n / 2) * d.amplitudes * np.exp(1j * d.phases) * shape[d.excited]
    level = (n / 2) * designs[0].amplitudes[0] * 10 ** ((-30 - 10 * k / k.max()) / 20)
    dist = level * (rng.standard_normal((m, k.size)) + 1j * rng.standard_normal((m, k.size))) / np.sqrt(2)
    dist[:, [0, -1]] = 0
    x = np.fft.irfft(spec + dist, n=n)
    return designs[0].excited, np.repeat(x[:, None, :], p, axis=1) + 1e-7 * rng.standard_normal((m, p, n))


@pytest.mark.parametrize("notch_db", [0.0, 25.0])
def test_excited_lines_from_a_distorted_input(notch_db):
    design, u = distorted_input(notch_db)
    found = detect_excited_lines(u)
    assert np.setxor1d(found, design).size <= 0.05 * design.size
    y = u + 0.1 * u ** 3
    res = robust_bla(u, y, excited_bins=None)
    s = res.summary
    assert s["excitation_distorted"] is True
    assert -45 < s["excitation_nonexcited_re_excited_db"] < -25
    assert any("input u is distorted" in note and "give the reference" in note for note in res.notes)


def test_clean_input_is_not_reported_distorted():
    designs = multisine_realizations(3, 1.0, 1024, k_min=1, k_max=300, seed=2)
    u = np.repeat(np.stack([d.period for d in designs])[:, None, :], 3, axis=1)
    res = robust_bla(u, u + 0.2 * u ** 3 + 1e-4 * np.random.default_rng(0).standard_normal(u.shape))
    assert res.summary["excitation_distorted"] is False
    assert not any("distorted" in note for note in res.notes)


def test_summary_per_line_figures_equal_figure3_medians():
    import matplotlib
    matplotlib.use("Agg")
    from fftune.analysis import plots
    designs = multisine_realizations(4, 100.0, 1024, k_min=2, k_max=300, seed=5, rms=0.5)
    u = np.repeat(np.stack([d.period for d in designs])[:, None, :], 3, axis=1)
    y = u + 0.5 * u ** 3 + 3e-3 * np.random.default_rng(1).standard_normal(u.shape)
    res = robust_bla(u, y, fs=100.0)
    fig = plots.figure3(res)
    drawn = {line.get_label(): np.asarray(line.get_ydata(), float) for line in fig.axes[0].lines}
    out = next(v for k, v in drawn.items() if k.startswith("output"))
    nl = next(v for k, v in drawn.items() if k.startswith("nonlinear"))
    noise = next(v for k, v in drawn.items() if k.startswith("noise level"))
    s = res.summary
    assert s["line_median_nl_re_output_db"] == pytest.approx(np.median(nl - out), abs=1.0)
    assert s["line_median_noise_re_nl_db"] == pytest.approx(np.median(noise - nl), abs=1.0)
    # and the power ratio is a different figure (dominated by the strongest lines)
    assert s["nl_re_output_db"] is not None


def test_verdict_texts_name_the_cause():
    s = {"odd_detected": True, "even_detected": False, "nl_detected": True,
         "parity_classifiable": True, "plant_odd_detected": False, "plant_even_detected": False,
         "plant_odd_lines_over_noise_6db": 0, "plant_odd_lines": 20, "plant_odd_lines_needed": 5,
         "plant_odd_lines_by_noise": 0.4, "plant_even_lines_over_noise_6db": 1,
         "plant_even_lines": 80, "plant_even_lines_needed": 9, "plant_even_lines_by_noise": 1.6,
         "quantisation_floor_db": None}
    v = level_verdict(s, 0.004, "3 V rms")
    assert v["causes"] == ["drive output saturation"] and "0.4 % of the samples" in v["text"]
    v = level_verdict(s, 0.0)
    assert v["causes"] == ["loop nonlinearity outside the plant"]
    v = level_verdict(dict(s, quantisation_floor_db=-85.0), 0.0)
    assert v["causes"] == ["quantisation floor"]
    v = level_verdict(dict(s, plant_odd_lines_over_noise_6db=3), 0.0)
    assert v["causes"] == ["cannot tell"] and "3 of 20" in v["text"]
    v = level_verdict(dict(s, odd_detected=False, nl_detected=False), 0.0)
    assert v["causes"] == ["linear"]


def test_no_plant_referred_figures_means_cannot_tell_not_a_cause():
    s = {"odd_detected": True, "even_detected": False, "nl_detected": True,
         "parity_classifiable": True, "quantisation_floor_db": None}
    v = level_verdict(s, 0.01)
    assert v["causes"] == ["cannot tell"] and "plant-referred" in v["text"]


def test_encoder_step_key_is_validated_naming_the_key():
    from fftune.analysis.errors import FftuneError
    from fftune.host.config import validate
    with pytest.raises(FftuneError, match=r"c.yaml: key 'detect.encoder_step_rad'"):
        validate({"detect": {"encoder_step_rad": -1.0}}, "c.yaml")
    cfg = validate({"detect": {"encoder_step_rad": 0.00314}}, "c.yaml")
    assert cfg["detect"]["encoder_step_rad"] == 0.00314
