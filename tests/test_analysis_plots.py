"""Figures 3, 4, 5, 7, 9: written, non-trivial PNGs (headless)."""
import numpy as np
import pytest
from matplotlib.figure import Figure

from fftune.analysis import plots
from fftune.analysis.bla import bla_levels
from fftune.analysis.hosidf import hosidf
from fftune.analysis.multisine import multisine_realizations


def assert_png(path, min_bytes=15000):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > min_bytes          # axes, data and labels, not an empty canvas
    assert not list(path.parent.glob(".*tmp"))


@pytest.fixture(scope="module")
def levels():
    n, p = 256, 3
    us, ys = [], []
    rng = np.random.default_rng(0)
    for rms in (0.2, 1.0):
        table = np.stack([d.period for d in multisine_realizations(4, 100.0, n, k_min=1, k_max=80,
                                                                 rms=rms, seed=2)])
        u = np.repeat(table[:, None, :], p, axis=1)
        us.append(u)
        ys.append(np.tanh(u) + 0.3 * u ** 2 + 1e-3 * rng.standard_normal(u.shape))
    return bla_levels(us, ys, fs=100.0)


def test_figure3_and_bla(tmp_path, levels):
    res = levels.results[-1]
    assert_png(plots.plot_output_spectrum(res, tmp_path / "f3.png"))
    assert_png(plots.plot_bla(res, tmp_path / "bla.png"))
    assert isinstance(plots.figure3(res), Figure)


def test_figure4(tmp_path, levels):
    assert_png(plots.plot_bla_levels(levels, tmp_path / "f4.png"))


def test_figure5_and_harmonics(tmp_path):
    n, r = 512, 3
    amps = np.array([0.3, 1.0, 3.0])
    t = np.arange(n)
    rng = np.random.default_rng(1)
    u = amps[:, None, None] * np.sin(2 * np.pi * 5 * t / n) * np.ones((3, r, 1))
    y = np.clip(u, -1, 1) + 1e-3 * rng.standard_normal(u.shape)
    res = hosidf(u[:, :, None, :], y[:, :, None, :], fs=512.0, n_harmonics=7)
    assert_png(plots.plot_hosidf_amplitude(res, tmp_path / "f5.png"))
    one = hosidf(u[1][:, None, :], y[1][:, None, :], fs=512.0, n_harmonics=7)
    assert_png(plots.plot_hosidf_harmonics(one, tmp_path / "h.png"))


def test_figure7_and_figure9(tmp_path):
    k = np.linspace(0, 0.2, 9)
    fc = 0.1157
    H = np.zeros((k.size, 7), complex)
    H[:, 0] = 2 + 4 * (fc - k) / np.pi
    for h in (3, 5, 7):
        H[:, h - 1] = (-1) ** ((h - 1) // 2) * 4 * (fc - k) / (h * np.pi)
    assert_png(plots.plot_tuning(k, H, tmp_path / "f7.png", k_star=fc))
    fs = 1000.0
    t = np.arange(2000) / fs
    ref = np.sin(2 * np.pi * 2 * t)
    outs = {f"K_fc = {kk}": ref - 0.05 * (0.1 - kk) * np.sign(ref) for kk in (0.0, 0.1, 0.12)}
    assert_png(plots.plot_time_response(fs, ref, outs, tmp_path / "f9.png"))
    with pytest.raises(Exception, match="samples"):
        plots.figure9(fs, ref, {"short": ref[:10]})
