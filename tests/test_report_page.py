"""report.html as a decision page: the recommendation first (what to set, on which object,
in V and N m, with sigma), like-for-like rows (each with the feed-forward in the loop), one
number per quantity (table, figure legends, results.yaml), the raw results collapsed, the
page height in headless Chromium, and the legend rule (no legend over an axes) for every
figure of fftune.analysis.plots."""
import re
import shutil
import subprocess

import numpy as np
import pytest
import yaml

from fftune.analysis import plots
from fftune.analysis.bla import bla_levels
from fftune.analysis.hosidf import hosidf
from fftune.analysis.multisine import multisine_realizations
from fftune.host import report
from fftune.host.config import validate
from fftune.host.pipeline import run_pipeline
from host_fixtures import FakeDriveForTests

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


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    cfg = validate(yaml.safe_load(yaml.safe_dump(SMALL)), "test.yaml")
    cfg["_source"] = "test.yaml"
    drive = FakeDriveForTests(fc_volt=0.3, fv_volt=0.02, noise_std=1e-5)
    drive.enable()
    labels = {}
    orig = plots.figure9

    def spy(fs, reference, outputs, errors=None, title=None, rms_in_legend=True):
        labels["figure9"] = list(outputs)
        return orig(fs, reference, outputs, errors, title, rms_in_legend)
    mp = pytest.MonkeyPatch()
    mp.setattr(plots, "figure9", spy)
    data = {}
    try:
        results = run_pipeline(drive, cfg, str(out), log=lambda s: None, data=data)
    finally:
        mp.undo()
    labels["tune_data"] = data["tune_data"]
    return out, results, labels


def test_recommendation_comes_first_and_names_the_objects(page):
    out, results, _ = page
    text = (out / "report.html").read_text()
    rec = results["recommendation"]
    t = results["tune"]
    assert rec["set"] and rec["k_fc_object"] == "0x2000:04" and rec["k_v_object"] == "0x2000:05"
    # the same value and rounding everywhere: 4 significant digits of K_fc*, 2 of sigma
    assert rec["k_fc_v"] == float(f"{t['k_fc_star']:.4g}")
    assert rec["sigma_v"] == float(f"{t['search']['sigma_v']:.2g}")
    assert rec["k_v_v_s_per_rad"] == float(f"{t['viscous']['k_v_star']:.4g}")
    saved = yaml.safe_load((out / "results.yaml").read_text())
    assert saved["recommendation"] == rec
    i_rec = text.index("<h2>Recommendation</h2>")
    assert i_rec < text.index("like for like") < text.index("<h2>Key numbers</h2>") < text.index("<h2>Figures</h2>")
    first = text[i_rec:text.index("</p>", i_rec)]
    assert f"K_fc = {rec['k_fc_v']:g} V" in first and "0x2000:04" in first and "0x2000:05" in first
    # K_fc* appears with one rounding only: no other rendering of it on the page (above the
    # collapsed raw results.yaml)
    others = {m for m in re.findall(r"0\.\d{3,6}", text[:text.index("<details>")])
              if abs(float(m) - t["k_fc_star"]) < 2e-4 * t["k_fc_star"]}
    assert others <= {f"{rec['k_fc_v']:g}"}, others
    # the raw results and the configuration are collapsed
    assert re.search(r"<details><summary>All results \(results.yaml\)</summary><pre>", text)


def test_like_for_like_rows_say_what_was_in_the_loop(page):
    out, results, labels = page
    t = results["tune"]
    rows = report.loop_comparison(results)
    by = {r["what"]: r for r in rows}
    # the sweep ran at K_v = 0, the search with its own K_v, the recommendation with K_v*
    assert by["the sweep's smallest rms error"]["k_v"] == 0.0
    assert by["the sweep's point nearest K_fc*"]["k_v"] == 0.0
    # the K_v the verification run really had (the probe's record), not a later correction
    p_star = labels["tune_data"]["p_star"]
    assert by["the search's run nearest K_fc*"]["k_v"] == pytest.approx(p_star["kv"], rel=1e-6)
    assert by["the search's run nearest K_fc*"]["k_fc_v"] == pytest.approx(p_star["kfc"], rel=1e-6)
    assert by["recommended: K_fc* and K_v*"]["k_v"] == t["viscous"]["k_v_star"]
    near = by["the sweep's point nearest K_fc*"]
    k = np.asarray(t["sweep"]["k_fc"])
    assert near["k_fc_v"] == k[np.argmin(abs(k - t["k_fc_star"]))]
    html_text = (out / "report.html").read_text()
    table = html_text[html_text.index("<table class='cmp'>"):]
    table = table[:table.index("</table>")]
    for r in rows:
        assert f"<td>{r['what']}</td><td>{report.gain_text(r['k_fc_v'])}</td>" \
               f"<td>{report.gain_text(r['k_v'], 'V s/rad')}</td><td>{report.rms_text(r['rms_error_rad'])}</td>" \
            in table.replace("&#x27;", "'")
    # Figure 9's legend: the very labels of the table rows, with the table's rms numbers
    assert labels["figure9"] == [f"{report.loop_label(by[w])}: rms {report.rms_text(by[w]['rms_error_rad'])}"
                                 for w in ("no feed-forward", "the search's run nearest K_fc*",
                                           "the sweep's smallest rms error", "recommended: K_fc* and K_v*")]


def test_loop_plots_are_drawn(page):
    out, _, _ = page
    text = (out / "report.html").read_text()
    for name in ("bla_confidence.png", "error_spectrum.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"src='{name}'" in text
    # headings say what the plot shows, the paper's figure number is the subtitle
    assert "<h3>Odd HOSIDFs and the tuning objective vs the Coulomb feed-forward K_fc</h3>" \
           "<p class='sub'>the paper&#x27;s Figure 7</p>" in text


def test_recommendation_in_newton_metres_and_not_converged():
    res = {"drive": {"identity": {"node_id": 5},
                     "plant_truth": {"sim_fc_volt": 0.2, "sim_fc_torque": 0.2 * 0.037}},
           "tune": {"k_fc_star": 0.123456, "k_fc_best_measured": 0.123456,
                    "search": {"converged": True, "sigma_v": 0.0012345, "stop_reason": "x"},
                    "viscous": {"k_v_star": 0.0456789}}}
    rec = report.recommendation(res)
    assert rec["k_fc_v"] == 0.1235 and rec["sigma_v"] == 0.0012 and rec["k_v_v_s_per_rad"] == 0.04568
    assert rec["torque_constant_n_m_per_v"] == 0.037
    assert rec["k_fc_n_m"] == pytest.approx(float(f"{0.1235 * 0.037:.4g}"))
    assert rec["text"].startswith("Set K_fc = 0.1235 V = 4.569 mN m at the drive's 0.037 N m/V (1 sigma 0.0012 V)"
                                  " on object 0x2000:04 of node 5 and K_v = 0.04568 V s/rad (= 1.69 mN m s/rad)")
    res["tune"]["search"] = {"converged": False, "stop_reason": "the objective is flat"}
    rec = report.recommendation(res)
    assert not rec["set"] and "Nothing to set" in rec["text"] and "the objective is flat" in rec["text"]
    assert report.recommendation({"detect": {}}) is None


def _page_height(html_path, width=1280):
    """document.documentElement.scrollHeight of ``html_path`` in headless Chromium (px)."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    probe = html_path.parent / "height-probe.html"
    probe.write_text(html_path.read_text().replace(
        "</body>", "<script>window.addEventListener('load',()=>document.body.setAttribute("
                   "'data-h',document.documentElement.scrollHeight))</script></body>"))
    try:
        out = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                              f"--user-data-dir={html_path.parent / 'chromium-profile'}",
                              f"--window-size={width},900", "--virtual-time-budget=5000",
                              "--dump-dom", probe.as_uri()],
                             capture_output=True, text=True, timeout=120).stdout
    finally:
        probe.unlink()
    m = re.search(r'data-h="(\d+)"', out)
    assert m, f"no height from chromium: {out[:300]!r}"
    return int(m.group(1))


@pytest.mark.skipif(not (shutil.which("chromium") or shutil.which("chromium-browser")
                         or shutil.which("google-chrome")),
                    reason="headless Chromium not installed (make system-deps installs chromium)")
def test_page_height_in_chromium(page):
    out, _, _ = page
    h = _page_height(out / "report.html")
    # every figure loaded (the images give the height), yet under four 900 px screens
    assert 1500 < h < 4 * 900, h
    # the same page with results.yaml expanded is far taller: the collapse is what keeps it short
    expanded = out / "expanded.html"
    expanded.write_text((out / "report.html").read_text().replace("<details>", "<details open>"))
    try:
        assert _page_height(expanded) > h + 1000
    finally:
        expanded.unlink()


# ---------------------------------------------------------------------------------------
# the legend rule: every figure of fftune.analysis.plots keeps its legends off the axes
# ---------------------------------------------------------------------------------------
def _levels():
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


def _figures():
    lv = _levels()
    n, r = 512, 3
    amps = np.array([0.3, 1.0, 3.0])
    t = np.arange(n)
    u = amps[:, None, None] * np.sin(2 * np.pi * 5 * t / n) * np.ones((3, r, 1))
    y = np.clip(u, -1, 1) + 1e-3 * np.random.default_rng(1).standard_normal(u.shape)
    hos = hosidf(u[:, :, None, :], y[:, :, None, :], fs=512.0, n_harmonics=7)
    k = np.linspace(0, 0.2, 9)
    H = np.zeros((k.size, 7), complex)
    H[:, 0] = 2 + 4 * (0.1157 - k) / np.pi
    for h in (3, 5, 7):
        H[:, h - 1] = (-1) ** ((h - 1) // 2) * 4 * (0.1157 - k) / (h * np.pi)
    fs = 1000.0
    tt = np.arange(2000) / fs
    ref = np.sin(2 * np.pi * 2 * tt)
    outs = {f"a long label naming K_fc = {kk} V and K_v = 0.04 V s/rad": ref - 0.05 * (0.1 - kk) * np.sign(ref)
            for kk in (0.0, 0.1, 0.12)}
    return {
        "figure3": plots.figure3(lv.results[-1]),
        "figure4": plots.figure4(lv),
        "figure_bla": plots.figure_bla(lv.results[-1], band_p=0.95),
        "figure5": plots.figure5(hos),
        "figure7": plots.figure7(k, H, k_star=0.1157),
        "figure8": plots.figure8(k, H, abs(H) * 0.01, k_star=0.1157),
        "figure9": plots.figure9(fs, ref, outs),
        "error_spectrum": plots.figure_error_spectrum(fs, {lb: ref - o for lb, o in outs.items()}, f0=2.0),
        "sensitivity": plots.figure_sensitivity(
            {f"{a} V rms": (lv.results[-1].freq, 1.0 / (1.0 + a * lv.results[-1].G)) for a in (0.3, 3.0)}),
    }


def test_no_legend_covers_an_axes():
    for name, fig in _figures().items():
        assert any(ax.get_legend() is not None for ax in fig.axes), name
        assert plots.legend_outside_data(fig) == [], name


def test_the_legend_rule_sees_a_legend_over_the_data():
    fig = plots.figure9(100.0, np.sin(np.arange(200) / 10), {"x": np.sin(np.arange(200) / 10) * 0.9})
    fig.axes[0].legend(loc="center")
    bad = plots.legend_outside_data(fig)
    assert len(bad) == 1 and bad[0][0] == fig.axes[0].get_title()


def test_bla_band_radius_is_the_circular_normal_quantile():
    lv = _levels()
    res = lv.results[-1]
    fig = plots.figure_bla(res, band_p=0.9)
    poly = fig.axes[0].collections[0]
    top = poly.get_paths()[0].vertices
    # upper edge of the band at the first line: 20 log10(|G| + sqrt(var ln 10))
    r = np.sqrt(res.var_total[0] * np.log(10.0))
    want = 20 * np.log10(abs(res.G[0]) + r)
    assert np.any(np.isclose(top[:, 0], res.freq[0]) & np.isclose(top[:, 1], want, rtol=1e-9))
    with pytest.raises(Exception, match="band_p"):
        plots.figure_bla(res, band_p=1.5)


def test_error_spectrum_amplitude_at_harmonics():
    fs, n = 1000.0, 2000
    t = np.arange(n) / fs
    e = 0.02 * np.sin(2 * np.pi * 2 * t) + 0.005 * np.sin(2 * np.pi * 6 * t + 0.3)
    fig = plots.figure_error_spectrum(fs, {"e": e}, f0=2.0, n_harmonics=4)
    x, ydb = fig.axes[0].lines[0].get_data()
    assert list(x) == [2.0, 4.0, 6.0, 8.0]
    assert ydb[0] == pytest.approx(20 * np.log10(0.02), abs=1e-6)
    assert ydb[2] == pytest.approx(20 * np.log10(0.005), abs=1e-6)
    assert ydb[1] < -200


def test_terminal_summary_is_short_and_the_budget_names_its_clocks(page):
    from fftune.host.demo import _clock_note

    _, results, _ = page
    # make demo's terminal: 2 setup lines, drive_sim, 3 steps, these, 5 budget lines, the
    # clock note and "done" stay under 30 lines
    assert len(report.key_numbers(results)) <= 14
    sim = _clock_note({"time_budget_s": {"total": {"excitation": 292.8}}}, realtime=False)
    assert "simulated time" in sim and "293 s of excitation" in sim and "wall: real time" in sim
    real = _clock_note({"time_budget_s": {"total": {"excitation": 292.8}}}, realtime=True)
    assert "real time (--realtime)" in real and "simulated" not in real


def test_the_legend_rule_sees_a_legend_over_an_axis_label():
    fs, n = 1000.0, 2000
    e = 0.02 * np.sin(2 * np.pi * 2 * np.arange(n) / fs)
    fig = plots.figure_error_spectrum(fs, {"e": e, "e2": 0.5 * e}, f0=2.0, n_harmonics=4)
    assert plots.legend_outside_data(fig) == []
    # under the axes but on its x label ("frequency (Hz)"), not on the data
    ax = fig.axes[0]
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), borderaxespad=0.0)
    bad = plots.legend_outside_data(fig)
    assert len(bad) == 1 and bad[0][0] == ax.get_title()


def test_every_figure_function_of_plots_is_checked():
    """figure_hosidf_harmonics (not drawn in a session's report) keeps the rule too, and no
    figure function of plots is left out of these tests."""
    n, r = 512, 3
    t = np.arange(n)
    u = np.array([0.3, 1.0])[:, None, None] * np.sin(2 * np.pi * 5 * t / n) * np.ones((2, r, 1))
    y = np.clip(u, -0.5, 0.6) + 1e-3 * np.random.default_rng(2).standard_normal(u.shape)
    hos = hosidf(u[:, :, None, :], y[:, :, None, :], fs=512.0, n_harmonics=5)
    fig = plots.figure_hosidf_harmonics(hos)
    assert fig.axes[0].get_legend() is not None and plots.legend_outside_data(fig) == []
    drawn = {"figure3", "figure4", "figure5", "figure7", "figure8", "figure9", "figure_bla",
             "figure_error_spectrum", "figure_sensitivity", "figure_hosidf_harmonics"}
    assert {n for n in plots.__all__ if n.startswith("figure")} == drawn
