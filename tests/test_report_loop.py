"""The loop's measured sensitivity (fftune.analysis.loop.sensitivity) against a loop whose
sensitivity is known in closed form, and its figure in a session's report."""
import numpy as np
import pytest

from fftune.analysis import plots
from fftune.analysis.errors import InputError
from fftune.analysis.loop import sensitivity
from fftune.analysis.multisine import multisine_realizations


def _loop(m=3, p=2, n=256, fs=200.0, noise=0.0):
    """Excitation d and plant input u = S_i d of the discrete loop C = 0.8 (a gain), G =
    0.5 z^-1 / (1 - 0.7 z^-1) (a lag): S_i = 1 / (1 + C G) per line, applied in the
    frequency domain to the periodic d."""
    ms = multisine_realizations(m, fs, n, k_min=2, k_max=90, rms=1.0, seed=5)
    table = np.stack([x.period for x in ms])
    k = np.arange(n // 2 + 1)
    z = np.exp(2j * np.pi * k / n)
    S = 1.0 / (1.0 + 0.8 * 0.5 / (z - 0.7))
    u = np.fft.irfft(np.fft.rfft(table, axis=-1) * S, n=n, axis=-1)
    d = np.repeat(table[:, None, :], p, axis=1)
    u = np.repeat(u[:, None, :], p, axis=1) + noise * np.random.default_rng(1).standard_normal((m, p, n))
    return d, u, S, fs, n, np.asarray(ms[0].excited)


def test_sensitivity_is_u_over_d_at_the_excited_lines():
    d, u, S, fs, n, exc = _loop()
    f, est, var = sensitivity(u, d, fs=fs)
    lines = np.rint(f * n / fs).astype(int)
    # the design's excited lines, none other
    np.testing.assert_array_equal(lines, np.sort(exc))
    np.testing.assert_allclose(est, S[lines], rtol=1e-9, atol=1e-12)
    assert np.all(var < 1e-20)
    # with noise: the spread over the realizations is its variance, near the truth
    d, u, S, fs, n, exc = _loop(noise=0.05)
    f, est, var = sensitivity(u, d, fs=fs)
    lines = np.rint(f * n / fs).astype(int)
    assert np.all(var > 0)
    z = np.abs(est - S[lines]) / np.sqrt(var)
    assert np.median(z) < 2.0 and np.max(np.abs(est - S[lines])) < 0.2


def test_sensitivity_inputs_are_checked():
    d, u, _, fs, _, _ = _loop()
    with pytest.raises(InputError, match="does not match"):
        sensitivity(u, d[:, :, :-1], fs=fs)
    with pytest.raises(InputError, match=r"\(M, P, N\)"):
        sensitivity(u[0], d, fs=fs)
    with pytest.raises(InputError, match="no line"):
        sensitivity(u, np.zeros_like(d), fs=fs)


def test_sensitivity_figure_marks_the_peak_and_keeps_the_legend_off():
    d, u, S, fs, n, exc = _loop()
    f, est, _ = sensitivity(u, d, fs=fs)
    fig = plots.figure_sensitivity({"low": (f, est), "high": (f, 1.3 * est)})
    assert plots.legend_outside_data(fig) == []
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    db = 20 * np.log10(np.abs(est))
    k = int(np.argmax(db))
    assert labels[0] == f"low: peak {db[k]:+.1f} dB at {f[k]:.3g} Hz"
    assert labels[1] == f"high: peak {db[k] + 20 * np.log10(1.3):+.1f} dB at {f[k]:.3g} Hz"


def test_the_demo_report_draws_the_measured_sensitivity(tmp_path):
    """A session with detect captures (samples) gets the sensitivity figure: its curve is
    U/D of its own captures."""
    import yaml

    from fftune.host.config import validate
    from fftune.host.pipeline import run_pipeline
    from fftune.host import report
    from host_fixtures import FakeDriveForTests

    cfg = validate({"output": "unused", "detect": {
        "inject": "plant_input", "period_samples": 256, "band_hz": [5.0, 100.0], "group": 4, "seed": 3,
        "realizations": 2, "periods": 1, "settle_periods": 2, "rms_levels": [0.5, 2.0]},
        "quantify": {"enabled": False}, "tune": {"enabled": False}}, "t.yaml")
    drive = FakeDriveForTests(fc_volt=0.3, fv_volt=0.02, noise_std=1e-5)
    drive.enable()
    results = run_pipeline(drive, cfg, str(tmp_path), log=lambda s: None)
    assert (tmp_path / "sensitivity.png").read_bytes()[:4] == b"\x89PNG"
    assert "src='sensitivity.png'" in (tmp_path / "report.html").read_text()
    sens = report.measured_sensitivity(str(tmp_path), yaml.safe_load((tmp_path / "results.yaml").read_text()))
    assert [rms for rms, _ in sens] == [0.5, 2.0]
    from fftune.analysis.capture import load_experiment
    ex = load_experiment(tmp_path / "captures", experiment="detect", level_index=1)
    U = np.fft.rfft(ex.signals["plant_input"][:, -1].astype(float), axis=-1)
    D = np.fft.rfft(ex.signals["excitation"][:, -1].astype(float), axis=-1)
    f, S = sens[1][1]
    k = np.rint(f * ex.n_period / ex.fs_hz).astype(int)
    np.testing.assert_allclose(S, (U[:, k] / D[:, k]).mean(axis=0), rtol=1e-9)
    assert results["detect"]["levels"][1]["rms_requested"] == 2.0
