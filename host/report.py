"""Results of a session: ``results.yaml``, the paper's figures (PNG) and an HTML report."""
import datetime
import html
import os

import yaml

from fftune.host.atomic import write_atomic


def write_results(out_dir, results):
    """``results.yaml`` (atomic)."""
    path = os.path.join(out_dir, "results.yaml")
    write_atomic(path, yaml.safe_dump(results, sort_keys=False, default_flow_style=None, width=100))
    return path


def _db(v):
    return "n/a" if v is None else f"{v:+.1f} dB"


def figure_conclusions(results, detect_levels=None, tune_data=None):
    """One line per figure, computed from the data: {figure name: text}."""
    import numpy as np
    out = {}
    d = (results or {}).get("detect")
    if d and detect_levels is not None:
        for tag, i in (("lowest", 0), ("highest", -1)):
            lv = d["levels"][i]
            s = lv["summary_db"]
            out[f"figure3_{tag}"] = (
                f"{lv['rms_requested']:g} V rms: nonlinear re output {_db(s.get('line_median_nl_re_output_db'))}, "
                f"noise re nonlinear {_db(s.get('line_median_noise_re_nl_db'))} (per-line medians); "
                + (f"odd lines {_db(s.get('odd_line_median_re_noise_db'))}, even "
                   f"{_db(s.get('even_line_median_re_noise_db'))} re noise; "
                   if s.get("parity_classifiable") else "")
                + lv["verdict"])
        g = np.abs(detect_levels.G)
        f_peak = float(detect_levels.freq[int(np.argmax(g[-1] * detect_levels.freq ** 2))])
        out["figure4"] = (f"the BLA changes by up to {d.get('bla_max_change_over_levels_db') or 0:.1f} dB "
                          f"over the levels; resonance (peak of |G| f^2) at {f_peak:.3g} Hz, "
                          f"line spacing {detect_levels.freq[1] - detect_levels.freq[0]:.3g} Hz")
    q = (results or {}).get("quantify")
    if q:
        out["figure5"] = (f"largest odd HOSIDF {100 * q['max_odd_relative_level']:.3g} % of |H_1|, "
                          f"largest even {100 * q['max_even_relative_level']:.3g} %")
    t = (results or {}).get("tune")
    if t and tune_data is not None:
        k, H = np.asarray(tune_data["k_sweep"]), np.asarray(tune_data["H_sweep"])
        ks = tune_data["k_star"]
        below, above = k < ks, k > ks
        if below.any() and above.any() and len(k) >= 3:
            from fftune.analysis.reproduction import phase_turn_deg
            turn = phase_turn_deg(k, H, ks, 3)
            out["figure7"] = (f"the unwrapped phase of H_3 turns by {turn:.0f} deg between the sweep "
                              f"points around K_fc* = {ks:.4g} V (the paper: 180 deg); ratio "
                              f"{100 * (t['ratio_at_zero'] or float('inf')):.3g} % at K_fc = 0, "
                              f"{100 * t['ratio_at_k_fc_star']:.3g} % at K_fc*")
        e = t["rms_error_rad"]
        where = "above" if (e["sweep_min_at_k_fc"] or 0) > ks else "not above"
        out["figure9"] = (f"rms error {e['k_fc_0']:.3g} rad at K_fc = 0, {e['k_fc_star']:.3g} rad at "
                          f"K_fc*, smallest {e['sweep_min']:.3g} rad at K_fc = {e['sweep_min_at_k_fc']:.4g} V "
                          f"({where} K_fc*)"
                          + (f"; with K_v* {e['k_fc_star_k_v_star']:.3g} rad"
                             if e.get("k_fc_star_k_v_star") is not None else ""))
    return out


def save_figure(out_dir, name, fig, caption):
    """``fig`` written atomically as ``<out_dir>/<name>.png``; returns (file name, caption)."""
    fname = f"{name}.png"
    tmp = os.path.join(out_dir, f".tmp-{fname}")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    os.replace(tmp, os.path.join(out_dir, fname))
    return fname, caption


def make_figures(out_dir, detect_levels=None, hos=None, tune_data=None, results=None):
    """The paper's Figures 3 (lowest and highest level), 4, 5, 7 and 9 as PNG files via
    :mod:`fftune.analysis.plots`, each caption ending with a conclusion computed from the
    data (:func:`figure_conclusions`).

    Returns ``{figure name: (file name, caption)}`` for the figures the data allow.
    """
    import matplotlib
    matplotlib.use("Agg")
    from fftune.analysis import plots

    made = {}
    concl = figure_conclusions(results, detect_levels, tune_data)

    def save(name, fig, caption, key=None):
        key = key or name.split("_")[0]
        if concl.get(key):
            caption = f"{caption} {concl[key]}."
        made[name] = save_figure(out_dir, name, fig, caption)

    if detect_levels is not None:
        unit_in = "V"
        d = (results or {}).get("detect") or {}
        if d.get("inject") == "reference":
            unit_in = "rad"
        for tag, i in (("lowest", 0), ("highest", -1)):
            res = detect_levels.results[i]
            rms = detect_levels.rms[i]
            save(f"figure3_output_spectrum_{tag}",
                 plots.figure3(res, title=f"Output spectrum at the {tag} level "
                                          f"({rms:.3g} {unit_in} rms)", unit="rad"),
                 f"Figure 3 ({tag} level): output spectrum of the multisine experiment: BLA "
                 f"output, nonlinear and noise levels, non-excited odd and even lines and the "
                 f"plant-referred level there.", key=f"figure3_{tag}")
        save("figure4_bla_vs_level", plots.figure4(detect_levels, g_unit=f"rad/{unit_in}",
                                                   level_unit=unit_in),
             "Figure 4: BLA as a function of frequency and excitation level.")
    if hos is not None:
        q_in = "V" if ((results or {}).get("quantify") or {}).get("inject") == "plant_input" else "rad"
        save("figure5_hosidf_vs_amplitude", plots.figure5(hos, unit=q_in, h_unit=f"rad/{q_in}"),
             "Figure 5: odd and even HOSIDFs vs amplitude at every measured frequency (mean and "
             "standard deviation over repeats).")
    if tune_data is not None:
        save("figure7_tuning", plots.figure7(tune_data["k_sweep"], tune_data["H_sweep"],
                                             tune_data["ratio_sweep"], k_star=tune_data["k_star"]),
             "Figure 7: odd HOSIDFs (magnitude, phase) and the odd-harmonic ratio vs K_fc.")
        fs, n = tune_data["fs"], tune_data["n"]
        recs = [("K_fc = 0", tune_data["p0"]), (f"K_fc* = {tune_data['p_star']['kfc']:.4g} V", tune_data["p_star"]),
                (f"min rms error, K_fc = {tune_data['p_rms']['kfc']:.4g} V", tune_data["p_rms"])]
        if tune_data.get("p_kv") is not None:
            p = tune_data["p_kv"]
            recs.append((f"K_fc* and K_v* = {p['kv']:.4g} V s/rad", p))
        if any(not p["record"].signals for _, p in recs):
            # capture: stats uploads no samples; the time response needs raw (capture: both)
            return made
        save("figure9_time_response", plots.figure9(
            fs, tune_data["p0"]["record"].signals["reference"],
            {label: p["record"].signals["motor_angle"] for label, p in recs},
            {label: p["record"].signals["error"] for label, p in recs}),
            "Figure 9: closed-loop response and tracking error without feed-forward, at "
            "K_fc*, at the smallest rms error of the sweep, and at K_fc* with the tuned "
            "viscous feed-forward K_v*.")
    return made


def _table(rows):
    out = ["<table>"]
    for k, v in rows:
        out.append(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>")
    out.append("</table>")
    return "\n".join(out)


def _fmt(v, unit="", pct=False, level=False):
    """A number for the report: ``pct`` a signed relative change in %, ``level`` a level
    relative to H_1 in % (as Figures 7 and 8 plot it)."""
    if v is None:
        return "n/a"
    if pct:
        return f"{100 * v:+.2f} %"
    if level:
        return f"{100 * v:.3g} %"
    return f"{v:.4g}{unit}"


def key_numbers(results):
    """The headline numbers (label, text) of a results dict."""
    rows = []
    t = results.get("tune")
    if t and t.get("method") == "model":       # every term at once (docs/method.md section 5)
        m = t["model"]
        rows.append(("feed-forward terms (tune.method model)", "converged" if m["converged"]
                     else f"not converged: {m['stop_reason']}"))
        for name, term in t["terms"].items():
            rows.append((f"{name} ({term['object']})", f"{_fmt(term['value'], ' ' + term['unit'])} +- "
                                                      f"{_fmt(term['sigma'], ' ' + term['unit'])}"))
        rows += [("closed-loop experiments", t["experiments"]),
                 ("odd / even level at the verifying experiment (re |H_1|)",
                  f"{_fmt(t['odd_ratio_at_optimum'], level=True)} / {_fmt(t['even_ratio_at_optimum'], level=True)}"),
                 ("true Coulomb friction (simulation)", _fmt(t["true_coulomb_v"], " V")),
                 ("Coulomb term vs truth", _fmt(t["k_fc_star_error_re_truth"], pct=True))]
        t = None
    if t:
        rows += [
            ("K_fc* (automated search)", _fmt(t["k_fc_star"], " V") if t["search"]["converged"]
             else f"not converged: {t['search']['stop_reason']}"),
            ("sigma_total(K_fc*): noise and the measured systematic parts", _fmt(t["search"].get("sigma_v"), " V")),
            ("sigma parts", ", ".join(f"{k} {_fmt(v, ' V')}" for k, v in
                                      (t["search"].get("sigma_parts_v") or {}).items()) or "-"),
            ("K_fc optimum of the sweep", _fmt((t["sweep"] or {}).get("optimum_k_fc"), " V")),
            ("search vs sweep optimum", _fmt(t["search"]["relative_to_sweep_optimum"], pct=True)),
            ("closed-loop experiments of the search", t["search"]["experiments"]),
            ("true Coulomb friction (simulation)", _fmt(t["true_coulomb_v"], " V")),
            ("K_fc* vs truth", _fmt(t["k_fc_star_error_re_truth"], pct=True)),
            ("odd-harmonic ratio at K_fc = 0 (re |H_1|)", _fmt(t["ratio_at_zero"], level=True)),
            ("odd-harmonic ratio at K_fc* (re |H_1|)", _fmt(t["ratio_at_k_fc_star"], level=True)),
            ("ratio improvement", _fmt(t["ratio_improvement"], "x")),
            ("rms tracking error at K_fc = 0", _fmt(t["rms_error_rad"]["k_fc_0"], " rad")),
            ("rms tracking error at K_fc*", _fmt(t["rms_error_rad"]["k_fc_star"], " rad")),
            ("smallest rms error of the sweep",
             f"{_fmt(t['rms_error_rad']['sweep_min'], ' rad')} at K_fc = "
             f"{_fmt(t['rms_error_rad']['sweep_min_at_k_fc'], ' V')}"),
        ]
        if t.get("viscous"):
            rows += [("K_v* (viscous feed-forward)", _fmt(t["viscous"]["k_v_star"], " V s/rad")),
                     ("rms tracking error at K_fc*, K_v*", _fmt(t["viscous"]["rms_error_rad"], " rad"))]
    d = results.get("detect")
    if d:
        rows.append(("detection verdict", d["verdict"]))
        for tag, lv in (("lowest", d["levels"][0]), ("highest", d["levels"][-1])):
            s = lv["summary_db"]
            rows.append((f"per line, {tag} level ({lv['rms_requested']:g} rms): nonlinear re output "
                         f"/ noise re nonlinear (median)",
                         f"{_fmt(s.get('line_median_nl_re_output_db'), ' dB')} / "
                         f"{_fmt(s.get('line_median_noise_re_nl_db'), ' dB')}"))
        top = d["levels"][-1]["summary_db"]
        if top.get("parity_classifiable"):
            rows.append(("highest level: odd re even (power ratio)",
                         _fmt(top.get("odd_re_even_db"), " dB")))
    q = results.get("quantify")
    if q:
        rows.append(("largest odd HOSIDF level re |H_1|", _fmt(q["max_odd_relative_level"], level=True)))
        rows.append(("largest even HOSIDF level re |H_1|", _fmt(q["max_even_relative_level"], level=True)))
    rows.append(("experiments measured / resumed from captures",
                 f"{results['experiments']['measured']} / {results['experiments']['resumed']}"))
    return rows


# dB values below this are a floor (an exactly zero power clipped at 1e-300 before the log,
# -3000 dB), not a level: the report prints them as "below floor".
DB_FLOOR = -200.0


def _floors_readable(node):
    """A copy of the results for display: every ``*_db`` number below :data:`DB_FLOOR` as
    the text "below floor (< -200 dB)"."""
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            if isinstance(v, float) and str(k).endswith("_db") and v < DB_FLOOR:
                out[k] = f"below floor (< {DB_FLOOR:g} dB)"
            else:
                out[k] = _floors_readable(v)
        return out
    if isinstance(node, list):
        return [_floors_readable(v) for v in node]
    return node


def _zero_levels_readable(results):
    """A copy of the results for display with each exact 0.0 quantify even level printed as
    "below floor (< F)" (F: its even_relative_level_floor, one encoder count; see the
    note quantify.even_relative_level_note), not as a measured 0."""
    q = results.get("quantify")
    if not q or not any(v == 0.0 for row in q.get("even_relative_level", []) for v in row):
        return results
    floors = q.get("even_relative_level_floor")
    rows = []
    for i, row in enumerate(q["even_relative_level"]):
        out = []
        for j, v in enumerate(row):
            if v == 0.0:
                f = floors[i][j] if floors else None
                out.append(f"below floor (< {f:.2g}): exact half-wave symmetry" if f is not None
                           else "below floor: exact half-wave symmetry")
            else:
                out.append(v)
        rows.append(out)
    return dict(results, quantify=dict(q, even_relative_level=rows))


def write_html(out_dir, results, figures, title="fftune report", sections=()):
    """``report.html``: ``sections`` ((heading, HTML) pairs) first, then the key numbers,
    the figures with captions, the full results (dB floors printed as such)."""
    ident = results.get("drive", {}).get("identity", {})
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1000px;margin:auto}"
        "table{border-collapse:collapse}th,td{border:1px solid #bbb;padding:3px 8px;text-align:left}"
        "img{max-width:100%}pre{background:#f4f4f4;padding:8px;white-space:pre-wrap;"
        "overflow-wrap:anywhere}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p>{html.escape(datetime.datetime.now().isoformat(timespec='seconds'))} &mdash; drive "
        f"{html.escape(str(ident.get('device_name', '?')))}, firmware "
        f"{html.escape(str(ident.get('firmware_version', '?')))}, "
        f"{html.escape(str(ident.get('bus', '')))}; configuration "
        f"{html.escape(str(results.get('config_file', '')))}</p>",
    ]
    for heading, body in sections:
        parts += [f"<h2>{html.escape(heading)}</h2>", body]
    parts += ["<h2>Key numbers</h2>", _table(key_numbers(results))]
    for name, (fname, caption) in figures.items():
        parts.append(f"<h2>{html.escape(caption.split(':')[0])}</h2>")
        parts.append(f"<figure><img src='{html.escape(fname)}' alt='{html.escape(name)}'>"
                     f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("<h2>All results (results.yaml)</h2><pre>")
    parts.append(html.escape(yaml.safe_dump(_floors_readable(_zero_levels_readable(results)), sort_keys=False,
                                            default_flow_style=None, width=90)))
    parts.append("</pre></body></html>")
    path = os.path.join(out_dir, "report.html")
    write_atomic(path, "\n".join(parts))
    return path
