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


def make_figures(out_dir, detect_levels=None, hos=None, tune_data=None):
    """The paper's Figures 3, 4, 5, 7 and 9 as PNG files via :mod:`fftune.analysis.plots`.

    Returns ``{figure name: file name}`` for the figures that the available data allow.
    """
    import matplotlib
    matplotlib.use("Agg")
    from fftune.analysis import plots

    made = {}

    def save(name, fig, caption):
        fname = f"{name}.png"
        tmp = os.path.join(out_dir, f".tmp-{fname}")
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
        os.replace(tmp, os.path.join(out_dir, fname))
        import matplotlib.pyplot as plt
        plt.close(fig)
        made[name] = (fname, caption)

    if detect_levels is not None:
        top = detect_levels.results[-1]
        save("figure3_output_spectrum", plots.figure3(top),
             "Figure 3: output spectrum of the multisine experiment at the highest level: "
             "BLA output, nonlinear and noise levels, non-excited odd and even lines.")
        save("figure4_bla_vs_level", plots.figure4(detect_levels),
             "Figure 4: BLA as a function of frequency and excitation level.")
    if hos is not None:
        save("figure5_hosidf_vs_amplitude", plots.figure5(hos),
             "Figure 5: HOSIDFs vs amplitude (mean and standard deviation over repeats).")
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


def _fmt(v, unit="", pct=False):
    if v is None:
        return "n/a"
    if pct:
        return f"{100 * v:+.2f} %"
    return f"{v:.4g}{unit}"


def key_numbers(results):
    """The headline numbers (label, text) of a results dict."""
    rows = []
    t = results.get("tune")
    if t:
        rows += [
            ("K_fc* (automated search)", _fmt(t["k_fc_star"], " V")),
            ("K_fc optimum of the sweep", _fmt(t["sweep"]["optimum_k_fc"], " V")),
            ("search vs sweep optimum", _fmt(t["search"]["relative_to_sweep_optimum"], pct=True)),
            ("closed-loop experiments of the search", t["search"]["experiments"]),
            ("true Coulomb friction (simulation)", _fmt(t["true_coulomb_v"], " V")),
            ("K_fc* vs truth", _fmt(t["k_fc_star_error_re_truth"], pct=True)),
            ("odd-harmonic ratio at K_fc = 0", _fmt(t["ratio_at_zero"])),
            ("odd-harmonic ratio at K_fc*", _fmt(t["ratio_at_k_fc_star"])),
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
        top = d["levels"][-1]["summary_db"]
        for k in ("nl_re_output_db", "odd_re_even_db", "noise_re_nl_db"):
            rows.append((f"{k} (highest level)", _fmt(top.get(k), " dB")))
    q = results.get("quantify")
    if q:
        rows.append(("largest odd HOSIDF level re H_1", _fmt(q["max_odd_relative_level"])))
        rows.append(("largest even HOSIDF level re H_1", _fmt(q["max_even_relative_level"])))
    rows.append(("experiments measured / resumed from captures",
                 f"{results['experiments']['measured']} / {results['experiments']['resumed']}"))
    return rows


def write_html(out_dir, results, figures):
    """``report.html``: the key numbers, the figures with captions, the full results."""
    ident = results.get("drive", {}).get("identity", {})
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>fftune report</title>",
        "<style>body{font-family:sans-serif;max-width:1000px;margin:auto}"
        "table{border-collapse:collapse}th,td{border:1px solid #bbb;padding:3px 8px;text-align:left}"
        "img{max-width:100%}pre{background:#f4f4f4;padding:8px;overflow:auto}</style></head><body>",
        "<h1>fftune report</h1>",
        f"<p>{html.escape(datetime.datetime.now().isoformat(timespec='seconds'))} &mdash; drive "
        f"{html.escape(str(ident.get('device_name', '?')))}, firmware "
        f"{html.escape(str(ident.get('firmware_version', '?')))}, "
        f"{html.escape(str(ident.get('bus', '')))}; configuration "
        f"{html.escape(str(results.get('config_file', '')))}</p>",
        "<h2>Key numbers</h2>", _table(key_numbers(results)),
    ]
    for name, (fname, caption) in figures.items():
        parts.append(f"<h2>{html.escape(caption.split(':')[0])}</h2>")
        parts.append(f"<figure><img src='{html.escape(fname)}' alt='{html.escape(name)}'>"
                     f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("<h2>All results (results.yaml)</h2><pre>")
    parts.append(html.escape(yaml.safe_dump(results, sort_keys=False, default_flow_style=None, width=100)))
    parts.append("</pre></body></html>")
    path = os.path.join(out_dir, "report.html")
    write_atomic(path, "\n".join(parts))
    return path
