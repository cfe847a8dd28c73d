"""Every page a person reads (the demo report, the paper reproduction, the machine summary,
the track report, the fleet summary) built from small synthetic results: the
recommendation (or the verdict, or what the drive holds, or the fleet's summary) is the
first section, the numbers there are rounded as everywhere else, and in headless Chromium
(one browser launch for all five pages) each page is under about four 900 px screens.
Also: the multi-term recommendation of ``tune.method: model`` (each gain on its own
object) and the legend rule for the figures drawn outside fftune.analysis.plots (the
track path, the fleet's drift plot)."""
import json
import re
import shutil
import subprocess

import numpy as np
import pytest

from fftune.analysis import plots
from fftune.host import fleet, machine, paper, report, track_report
from fftune.host.track import plot_track

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


# ---------------------------------------------------------------------------------------
# synthetic results (asymmetric numbers: 0.123456 V is not 0.1235 V in another rounding)
# ---------------------------------------------------------------------------------------
def _tune(k_star=0.123456, sigma=0.00061234, kv=0.0456789):
    return {"method": "search", "frequency_hz": 0.625, "amplitude_rad": 0.5,
            "k_fc_star": k_star, "k_fc_best_measured": k_star, "true_coulomb_v": 0.1237,
            "k_fc_star_error_re_truth": k_star / 0.1237 - 1,
            "search": {"converged": True, "sigma_v": sigma, "experiments": 7, "stop_reason": "ok",
                       "verification_k_fc": 0.1231, "relative_to_sweep_optimum": -0.0123,
                       "sigma_parts_v": {"noise": 1.1e-4, "amplitude": 5.3e-4},
                       "evaluations": [{"k_fc": 0.0, "k_v": 0.0}, {"k_fc": 0.1231, "k_v": 0.0467}],
                       "budget": {"viscous": {"k_v_in_search": 0.0467}}, "k_v_in_search": 0.0467},
            "sweep": {"k_fc": [0.0, 0.05, 0.1, 0.15, 0.2], "rms_error_rad": [0.081, 0.05, 0.031, 0.024, 0.029],
                      "ratio": [0.035, 0.02, 0.006, 0.004, 0.012], "optimum_k_fc": 0.1249},
            "rms_error_rad": {"k_fc_0": 0.08227, "k_fc_star": 0.01754, "sweep_min": 0.024,
                              "sweep_min_at_k_fc": 0.15},
            "ratio_at_zero": 0.0356, "ratio_at_k_fc_star": 9.43e-5, "ratio_improvement": 377.5,
            "viscous": {"k_v_star": kv, "rms_error_rad": 0.01701}}


def _results(node=1, **kw):
    return {"drive": {"identity": {"node_id": node, "device_name": "fftune drive_sim"},
                      "plant_truth": {"sim_fc_volt": 0.1237, "sim_fc_torque": 0.1237 * 0.05}},
            "tune": _tune(**kw)}


@pytest.fixture(scope="module")
def figure_pngs(tmp_path_factory):
    """The figures of a session (each drawn by its plots function on small data) as PNGs,
    reused by every page."""
    from test_report_page import _figures

    d = tmp_path_factory.mktemp("figs")
    made = {}
    for name, fig in _figures().items():
        made[name] = report.save_figure(str(d), name, fig, f"{name} shown (the paper's Figure 1): text.")
    return d, made


def _with_figures(out, figure_pngs, names=None):
    src, made = figure_pngs
    figs = {}
    for name, (fname, cap) in made.items():
        if names is None or name in names:
            shutil.copy(src / fname, out / fname)
            figs[name] = (fname, cap)
    return figs


# the paper page's figures (its names) and the synthetic figure drawn for each
PAPER_FIGURES = {"figure3_output_spectrum_lowest": "figure3", "figure3_output_spectrum_highest": "figure3",
                 "figure4_bla_vs_level": "figure4", "bla_confidence": "figure_bla",
                 "figure5_hosidf_vs_amplitude": "figure5", "figure7_tuning": "figure7",
                 "figure9_time_response": "figure9", "error_spectrum": "error_spectrum",
                 "sensitivity": "sensitivity",
                 "figure3_output_spectrum_paper_level": "figure3", "figure7_simulation": "figure7",
                 "figure8_setup_sweep": "figure8"}


@pytest.fixture(scope="module")
def pages(tmp_path_factory, figure_pngs):
    """{kind: (path of report.html, what its first section must say)}."""
    root = tmp_path_factory.mktemp("pages")
    out = {}
    # the demo
    d = root / "demo"
    d.mkdir()
    res = _results()
    report.write_results(str(d), res)
    report.write_html(str(d), res, _with_figures(d, figure_pngs))
    out["demo"] = (d / "report.html", "Recommendation", res["recommendation"]["text"])
    # the paper: its verdict first, the pipeline's figures beyond the paper's collapsed
    p = root / "paper"
    p.mkdir()
    res = _results()
    rows = [{"key": "a", "claim": "K_fc* re the Coulomb level", "paper": "< 1 %", "measured_text": "-0.2 %",
             "accepted": "|x| < 2 %", "agrees": True},
            {"key": "b", "claim": "odd ratio at 0", "paper": "15 %", "measured_text": "3.6 %",
             "accepted": "10 .. 25 %", "agrees": False},
            {"key": "c", "claim": "nonlinear re output", "paper": "-10 dB", "measured_text": "-30 dB",
             "accepted": "-15 .. -5 dB", "agrees": False, "verdict": "other set-up", "setup": "TEM stage"}]
    notes = {"b": "a long note " * 40}
    src, made = figure_pngs
    figs = {}
    for name, drawn in PAPER_FIGURES.items():
        shutil.copy(src / made[drawn][0], p / f"{name}.png")
        figs[name] = (f"{name}.png", made[drawn][1])
    paper.write_report(str(p), res, figs, rows, notes)
    out["paper"] = (p / "report.html", "Reproduction",
                    "1 of 2 results agree with the paper; 1 more the paper measured on another set-up "
                    "(shown, not compared); K_fc* = 0.1235 V +- 0.00061 V (1 sigma_total), -0.20 % off "
                    "the simulated Coulomb level 0.1237 V.")
    # the machine: one line per axis, from each axis' results.yaml
    m = root / "machine"
    axes = []
    for name, node, k in (("x", 2, 0.1111111), ("y", 3, 0.2222222)):
        (m / name).mkdir(parents=True)
        res = _results(node=node, k_star=k)
        report.write_results(str(m / name), res)
        axes.append({"name": name, "node_id": node, "status": "ok", "k_fc_star": k, "sigma": 0.00061234,
                     "k_fc_true": 0.1237, "k_fc_error_re_truth": k / 0.1237 - 1, "verdict": None,
                     "error": None, "results": f"{name}/results.yaml",
                     "time_budget_s": {"excitation": 10.0, "bus": 1.0, "drive_wait": 2.0}})
    axes.append({"name": "z", "node_id": 4, "status": "failed", "k_fc_star": None, "sigma": None,
                 "k_fc_true": None, "k_fc_error_re_truth": None, "verdict": None,
                 "error": "no heartbeat from node 4", "results": None, "time_budget_s": None})
    summ = machine.machine_summary({"name": "mill"}, axes, 12.5, "2026-11-27T10:00:00")
    machine.write_machine(str(m), summ)
    out["machine"] = (m / "report.html", "Recommendation",
                      "x: " + report.recommendation(_results(node=2, k_star=0.1111111))["text"])
    # the track report: the gains left on the drive
    t = root / "track"
    t.mkdir()
    rows_t = []
    k = 0.1
    for i in range(30):
        est = 0.12 + 0.0004 * i + (0.006 if i == 5 else 0.0)
        rows_t.append({"task": i + 1, "t_s": 2.0 * (i + 1), "k_fc": k, "k_fc_estimate": est,
                       "k_fc_sigma": 0.0011, "k_fc_next": est, "rms_error": 0.03 - 0.0005 * i,
                       "k_fc_true": 0.12 + 0.0004 * i, "action": "update"})
        k = est
    tres = {"track": rows_t, "track_summary": {
        "tasks": 30, "task_s": 2.0, "stop": None, "k_fc_final": k, "k_v_final": 0.0456789,
        "k_fc_true_final": rows_t[-1]["k_fc_true"], "check": None,
        "bus": {"bits_per_task_max": 4123, "task_traffic_load": 0.0123, "bitrate": 1000000}}}
    track_report.write_track_report(str(t), tres, {"drive": {"node_id": 1}})
    out["track"] = (t / "report.html", "On the drive", f"The drive runs K_fc = {report.gain_text(k)} (simulated "
                    f"truth {report.gain_text(rows_t[-1]['k_fc_true'])}) on object 0x2000:04 of node 1")
    out["track_rows"] = rows_t
    # the fleet: a summary line per axis first
    f = root / "fleet"
    f.mkdir()
    frows = []
    for day, kk, s in (("2026-01-05T10:00:00", 0.1234567, 0.0012), ("2026-03-05T10:00:00", 0.1304567, 0.0013)):
        r = fleet._empty_row(f"/data/{day}", "captures")
        r.update(machine="mill", axis="x", node_id=2, date=day, status="ok", k_fc_star=kk, k_fc_sigma=s,
                 k_fc_converged=True, ratio_at_zero=0.03, ratio_at_k_fc_star=1e-4, k_fc_true=None)
        frows.append(r)
    bad = fleet._empty_row("/data/broken", "captures")
    bad.update(reason="no results.yaml")
    frows.append(bad)
    drift = fleet.drift_plots(frows, str(f))
    fleet.write_summary_html(frows, str(f), [], drift, ["a", "b", "c"])
    out["fleet"] = (f / "report.html", "Summary",
                    "mill / x: K_fc* = 0.1305 V +- 0.0013 V on object 0x2000:04 (latest analysis, "
                    "2026-03-05 10:00 UTC); +5.7 % since 2026-01-05 10:00 UTC over 2 analyses (4.0 sigma)")
    return out


def _first_section(text):
    """(heading, body text) of the first <h2> section of a page."""
    m = re.search(r"<h2>(.*?)</h2>(.*?)(?=<h2>|<details|$)", text, re.S)
    body = re.sub(r"<[^>]+>", " ", re.sub(r"</?(b|a|i|span)( [^>]*)?>", "", m.group(2)))
    return m.group(1), " ".join(body.replace("&#x27;", "'").replace("&#x27;", "'").split())


@pytest.mark.parametrize("kind", ["demo", "paper", "machine", "track", "fleet"])
def test_the_first_section_says_what_to_set(pages, kind):
    path, heading, want = pages[kind]
    got_heading, body = _first_section(path.read_text())
    assert got_heading == heading
    assert want in body, body


def test_machine_lists_every_axis_and_one_rounding(pages):
    path = pages["machine"][0]
    _, body = _first_section(path.read_text())
    # one line per axis: y's own K_fc* (0.2222 V, not x's), z's failure with its error
    assert "y: Set K_fc = 0.2222 V" in body and "of node 3" in body
    assert "z: nothing to set (failed: no heartbeat from node 4)" in body
    # the table: the same rounding as the recommendation (4 and 2 significant digits)
    table = path.read_text().split("<h2>Axes</h2>")[1]
    assert "<td>0.1111 V</td><td>0.00061 V</td>" in table


def test_paper_page_collapses_its_secondary_parts(pages):
    text = pages["paper"][0].read_text()
    # the verdict, then the recommendation, then the table
    assert text.index("<h2>Reproduction</h2>") < text.index("<h2>Recommendation</h2>") \
        < text.index("<h2>The paper&#x27;s results reproduced")
    # the long note is behind a "why", the key numbers and the pipeline's figures folded
    assert "<details><summary>why</summary>a long note" in text
    assert "<details><summary>Key numbers (" in text
    i = text.index("<summary>More figures")
    head, more = text[:i], text[i:]
    for name in PAPER_FIGURES:
        assert (f"src='{name}.png'" in more) == (name in paper.MORE_FIGURES), name
        assert (f"src='{name}.png'" in head) != (name in paper.MORE_FIGURES), name
    # the paper's own figures and the time response stay open
    assert {n for n in PAPER_FIGURES if n not in paper.MORE_FIGURES} == {
        "figure9_time_response", "figure3_output_spectrum_paper_level", "figure7_simulation", "figure8_setup_sweep"}


def test_fleet_summary_counts_rows_without_a_value(pages):
    _, body = _first_section(pages["fleet"][0].read_text())
    assert "1 of 3 rows without a K_fc* (the table says why)" in body


def _heights(paths, width=1280):
    """{path: document height in px} of every page in one headless Chromium (the pages in
    iframes of one probe page, read once all have loaded)."""
    root = paths[0].parents[1]
    probe = root / "heights.html"
    frames = "".join(f"<iframe id='f{i}' src='{p.as_uri()}' style='width:{width}px;height:900px'></iframe>"
                     for i, p in enumerate(paths))
    probe.write_text(
        f"<!DOCTYPE html><html><body>{frames}<script>window.addEventListener('load',()=>{{"
        f"const h=[];for(let i=0;i<{len(paths)};i++){{const d=document.getElementById('f'+i)"
        f".contentDocument;h.push(d?d.documentElement.scrollHeight:-1)}}"
        f"document.body.setAttribute('data-h',JSON.stringify(h))}})</script></body></html>")
    out = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                          "--allow-file-access-from-files", "--no-first-run",
                          "--disable-background-networking", "--disable-component-update", "--disable-sync",
                          f"--user-data-dir={root / 'chromium-profile'}", f"--window-size={width},900",
                          "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()],
                         capture_output=True, text=True, timeout=180).stdout
    m = re.search(r'data-h="([^"]+)"', out)
    assert m, f"no heights from chromium: {out[:300]!r}"
    return dict(zip(paths, json.loads(m.group(1).replace("&quot;", '"'))))


@pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium not installed (make system-deps installs chromium)")
def test_every_page_fits_in_about_four_screens(pages):
    kinds = ["demo", "paper", "machine", "track", "fleet"]
    h = _heights([pages[k][0] for k in kinds])
    got = {k: h[pages[k][0]] for k in kinds}
    for k in kinds:
        assert got[k] > 0, (k, got)
        assert got[k] < 4 * 900, (k, got)
    # the figures are loaded (the demo's grid of eight figures is far taller than a screen)
    assert got["demo"] > 1500 and got["paper"] > got["fleet"], got


# ---------------------------------------------------------------------------------------
# tune.method: model: each gain on its own object
# ---------------------------------------------------------------------------------------
def test_model_recommendation_sets_every_term_on_its_object():
    gains = {"kfc": 0.1234567, "kfa": 0.0, "kv": 0.04567891, "kps": -0.0123456, "kpc": 0.00876543}
    terms = {"coulomb": {"value": 0.1234567, "sigma": 0.00123456, "unit": "V"},
             "viscous": {"value": 0.04567891, "sigma": 0.000345678, "unit": "V s/rad"},
             "position": {"value": float(np.hypot(-0.0123456, 0.00876543)), "sigma": 0.000456789, "unit": "V"}}
    res = {"drive": {"identity": {"node_id": 7}},
           "tune": {"method": "model", "terms": terms,
                    "model": {"converged": True, "gains": gains, "stop_reason": "ok",
                              "verification": {"tag": "verify"},
                              "experiments": [{"tag": "identify", "amplitude_rad": 1.0, "rms_error_rad": 0.05,
                                               "odd_ratio": 0.03, "gains": dict.fromkeys(gains, 0.0)},
                                              {"tag": "identify", "amplitude_rad": 1.0, "rms_error_rad": 0.01,
                                               "odd_ratio": 0.003, "gains": gains},
                                              {"tag": "verify", "amplitude_rad": 0.5, "rms_error_rad": 0.008,
                                               "odd_ratio": 0.002, "gains": gains}]}}}
    rec = report.recommendation(res)
    g = rec["gains"]
    # the asymmetry term was not requested: its gain is not set
    assert list(g) == ["kfc", "kv", "kps", "kpc"]
    assert {a: g[a]["object"] for a in g} == {"kfc": "0x2000:04", "kv": "0x2000:05",
                                              "kps": "0x2000:0A", "kpc": "0x2000:0B"}
    assert g["kps"]["value"] == -0.01235 and g["kpc"]["value"] == 0.008765 and g["kps"]["sigma"] == 0.00046
    assert rec["text"] == ("Set K_fc = 0.1235 V (1 sigma 0.0012 V) on object 0x2000:04, K_v = 0.04568 V s/rad "
                           "(1 sigma 0.00035 V s/rad) on object 0x2000:05, K_ps = -0.01235 V (1 sigma "
                           "0.00046 V) on object 0x2000:0A and K_pc = 0.008765 V (1 sigma 0.00046 V) on "
                           "object 0x2000:0B of node 7 (tune.method: model, every term at once).")
    assert rec["k_fc_v"] == 0.1235 and rec["k_v_v_s_per_rad"] == 0.04568
    # the comparison: no feed-forward, the last run at its amplitude (like for like) and the
    # verifying run, whose other amplitude is said
    rows = report.loop_comparison(res)
    assert [r["what"] for r in rows] == [
        "no feed-forward", "experiment 2 (identify), the gains of the estimate before it",
        "experiment 3 (verify), the gains of the estimate before it (at 0.5 rad, not 1 rad: not like for like)"]
    assert [r["rms_error_rad"] for r in rows] == [0.05, 0.01, 0.008]
    assert rows[2]["k_fc_v"] == 0.1234567 and rows[0]["k_fc_v"] == 0.0
    res["tune"]["model"]["converged"] = False
    res["tune"]["model"]["stop_reason"] = "uncertain: the position term"
    rec = report.recommendation(res)
    assert not rec["set"] and "uncertain: the position term" in rec["text"]


# ---------------------------------------------------------------------------------------
# the legend rule for the figures outside fftune.analysis.plots
# ---------------------------------------------------------------------------------------
def test_track_and_fleet_figures_keep_legends_off_the_data(pages, tmp_path):
    rows = pages["track_rows"]
    figs = {"track": track_report.track_figure(rows)}
    frows = []
    for day, kk in (("2026-01-05T10:00:00", 0.12), ("2026-02-05T10:00:00", 0.125)):
        r = fleet._empty_row("s", "captures")
        r.update(machine="m", axis="x", date=day, status="ok", k_fc_star=kk, k_fc_sigma=0.001,
                 ratio_at_zero=0.03, ratio_at_k_fc_star=1e-4, k_fc_true=0.121)
        frows.append(r)
    figs["fleet"] = fleet.drift_figure(frows, "m", "x")
    for name, fig in figs.items():
        assert any(ax.get_legend() is not None for ax in fig.axes), name
        assert plots.legend_outside_data(fig) == [], name
    # fftune track's own PNG is that figure
    plot_track(rows, str(tmp_path / "track_kfc.png"))
    assert (tmp_path / "track_kfc.png").read_bytes()[:4] == b"\x89PNG"


def test_a_sweep_point_is_one_row_when_nearest_and_smallest():
    res = _results()
    res["tune"]["rms_error_rad"].update(sweep_min=0.031, sweep_min_at_k_fc=0.1)   # nearest 0.1235 V
    rows = report.loop_comparison(res)
    whats = [r["what"] for r in rows]
    assert "the sweep's point nearest K_fc*" not in whats
    row = rows[whats.index("the sweep's smallest rms error")]
    assert (row["k_fc_v"], row["k_v"], row["rms_error_rad"], row["ratio"]) == (0.1, 0.0, 0.031, 0.006)
    # apart: both rows, the smallest without a ratio (the sweep's row at 0.15 V is not recorded here)
    res["tune"]["rms_error_rad"].update(sweep_min=0.024, sweep_min_at_k_fc=0.15)
    by = {r["what"]: r for r in report.loop_comparison(res)}
    assert by["the sweep's point nearest K_fc*"]["k_fc_v"] == 0.1 and by["the sweep's smallest rms error"]["ratio"] is None


def test_fleet_summary_tells_one_drive_in_two_folders_apart():
    rows = []
    for folder, k in (("out/demo", 0.1156), ("out/fmu", 0.1166)):
        r = fleet._empty_row(folder, "captures")
        r.update(machine=folder, axis="node1", date="2026-11-27T15:27:02.301+00:00", status="ok",
                 k_fc_star=k, k_fc_sigma=0.0006, _display="fftune drive_sim, node 1")
        rows.append(r)
    items = fleet.summary_items(rows)
    assert items == [
        "fftune drive_sim, node 1 [out/demo/node1]: K_fc* = 0.1156 V +- 0.0006 V on object 0x2000:04 "
        "(latest analysis, 2026-11-27 15:27 UTC)",
        "fftune drive_sim, node 1 [out/fmu/node1]: K_fc* = 0.1166 V +- 0.0006 V on object 0x2000:04 "
        "(latest analysis, 2026-11-27 15:27 UTC)"]


def test_the_search_run_is_one_row_also_through_float32():
    """A statistics capture reads the verifying K_fc back through the drive's float32: the
    search's smallest rms error at that run is the run itself, one row (not two equal
    ones), with the K_v of its evaluation."""
    res = _results()
    t = res["tune"]
    t["sweep"] = None
    k64 = 0.11559891034863183
    k32 = float(np.float32(k64))
    t["search"].update(verification_k_fc=k64, evaluations=[{"k_fc": 0.0, "k_v": 0.0}, {"k_fc": k32, "k_v": 0.0399}])
    t["rms_error_rad"].update(k_fc_star=0.01754, sweep_min=0.01754, sweep_min_at_k_fc=k32)
    rows = report.loop_comparison(res)
    assert [r["what"] for r in rows] == ["no feed-forward", "the search's run nearest K_fc*",
                                         "recommended: K_fc* and K_v*"]
    assert rows[1]["k_v"] == 0.0399


def test_without_a_kv_step_the_search_kv_is_part_of_the_recommendation():
    res = _results()
    res["tune"]["viscous"] = None
    res["tune"]["search"]["k_v_in_search"] = 0.0462134
    rec = report.recommendation(res)
    assert rec["k_v_v_s_per_rad"] == 0.04621 and rec["k_v_object"] == "0x2000:05"
    assert rec["text"].endswith("and K_v = 0.04621 V s/rad (= 2.311 mN m s/rad) on object 0x2000:05 "
                                "(the K_v the search read K_fc* with; tune.viscous.enabled false).")
    res["tune"]["search"]["k_v_in_search"] = 0.0           # no viscous feed-forward in the search
    rec = report.recommendation(res)
    assert rec["k_v_v_s_per_rad"] is None and rec["text"].endswith("(K_v not tuned: tune.viscous.enabled false).")
