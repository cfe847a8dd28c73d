"""Results of a session: ``results.yaml``, the figures (PNG) and ``report.html``, a decision
page: what to set first (:func:`recommendation`), then the loop with and without the
feed-forward compared like with like (:func:`loop_comparison`), the key numbers, the figures
titled by what they show; every number through one formatter (:func:`gain_text`,
:func:`sigma_text`, :func:`rms_text`) so that the table, the legends, the terminal and
results.yaml's ``recommendation`` show one value per quantity."""
import datetime
import html
import os

import yaml

from fftune.host.atomic import write_atomic


def write_results(out_dir, results):
    """``results.yaml`` (atomic), with the ``recommendation`` block (:func:`recommendation`)
    added to ``results`` when the tune step ran: the values the report and the terminal
    show, rounded as they show them."""
    rec = recommendation(results)
    if rec is not None:
        results["recommendation"] = rec
    path = os.path.join(out_dir, "results.yaml")
    write_atomic(path, yaml.safe_dump(results, sort_keys=False, default_flow_style=None, width=100))
    return path


def _db(v):
    return "n/a" if v is None else f"{v:+.1f} dB"


# ---------------------------------------------------------------------------------------
# one number per quantity: every value the report, the figures' legends, the terminal and
# results.yaml's recommendation block show goes through these (4 significant digits for a
# gain, 2 for its sigma, 4 for an rms error)
# ---------------------------------------------------------------------------------------
def round_sig(x, digits=4):
    """``x`` rounded to ``digits`` significant digits (None stays None)."""
    if x is None:
        return None
    return float(f"{float(x):.{digits}g}")


def gain_text(x, unit="V"):
    """A gain as shown everywhere: 4 significant digits and its unit ("0.1156 V")."""
    return "n/a" if x is None else f"{round_sig(x):g} {unit}".rstrip()


def sigma_text(x, unit="V"):
    return "n/a" if x is None else f"{round_sig(x, 2):g} {unit}"


def rms_text(x):
    return "n/a" if x is None else f"{round_sig(x):g} rad"


def _object_of(alias):
    """("0x2000:04", EDS name) of the drive parameter ``alias`` (configs/od.yaml)."""
    from fftune.host.odmap import PARAMS
    e = PARAMS[alias]
    return f"0x{e.index:04X}:{e.subindex:02X}", e.eds_name


def torque_constant(results):
    """The torque per input volt (N m/V) when the drive tells it (the simulated plant's
    truth: Coulomb friction in N m over the same in V), else None."""
    truth = (results.get("drive") or {}).get("plant_truth") or {}
    fc_v, fc_nm = truth.get("sim_fc_volt"), truth.get("sim_fc_torque")
    if fc_v and fc_nm and fc_v > 0 and fc_nm > 0:
        return fc_nm / fc_v
    return None


def recommendation(results):
    """What to set on the drive, from the tune step: a dict (results.yaml's
    ``recommendation``; numbers rounded as every output shows them) or None without a tune
    step. Keys: ``set`` (bool: a K_fc to set), ``text`` (the sentence), ``k_fc_v``,
    ``sigma_v`` (1 sigma_total), ``k_fc_object``, ``k_v_v_s_per_rad`` (K_v*, else the K_v
    the search ran with when it had one), ``k_v_object``,
    ``node_id``, ``torque_constant_n_m_per_v`` and ``k_fc_n_m`` / ``k_v_n_m_s_per_rad``
    when the drive tells its torque constant (simulation)."""
    t = results.get("tune")
    if not t:
        return None
    node = ((results.get("drive") or {}).get("identity") or {}).get("node_id")
    on = f" of node {node}" if node is not None else ""
    if t.get("method") == "model":
        return _model_recommendation(t, node, on)
    if not t["search"].get("converged") or t.get("k_fc_star") is None:
        best = t.get("k_fc_best_measured")
        return {"set": False, "node_id": node,
                "text": f"Nothing to set: the search for K_fc* did not converge "
                        f"({t['search'].get('stop_reason')})"
                        + (f"; the best measured K_fc, {gain_text(best)}, is no recommendation"
                           if best is not None else "") + "."}
    kfc, sig = round_sig(t["k_fc_star"]), round_sig(t["search"].get("sigma_v"), 2)
    obj_fc, _ = _object_of("kfc")
    obj_kv, _ = _object_of("kv")
    kv = round_sig((t.get("viscous") or {}).get("k_v_star"))
    # without a K_v step, the K_v the search read K_fc* with (its viscous feed-forward): K_fc*
    # holds with that K_v in the loop, so it is part of what to set
    kv_search = round_sig(t["search"].get("k_v_in_search")) or None
    if kv is None and kv_search:
        kv = kv_search
    km = torque_constant(results)
    rec = {"set": True, "node_id": node, "k_fc_v": kfc, "sigma_v": sig, "k_fc_object": obj_fc,
           "k_v_v_s_per_rad": kv, "k_v_object": obj_kv if kv is not None else None}
    nm = ""
    if km is not None:
        rec.update(torque_constant_n_m_per_v=round_sig(km), k_fc_n_m=round_sig(kfc * km),
                   k_v_n_m_s_per_rad=round_sig(kv * km) if kv is not None else None)
        nm = f" = {round_sig(1e3 * kfc * km):g} mN m at the drive's {round_sig(km):g} N m/V"
    text = (f"Set K_fc = {gain_text(kfc)}{nm} (1 sigma {sigma_text(sig)}) on object {obj_fc}{on}")
    if kv is not None:
        text += (f" and K_v = {gain_text(kv, 'V s/rad')}"
                 + (f" (= {round_sig(1e3 * kv * km):g} mN m s/rad)" if km is not None else "")
                 + f" on object {obj_kv}"
                 + (" (the K_v the search read K_fc* with; tune.viscous.enabled false)"
                    if (t.get("viscous") or {}).get("k_v_star") is None else ""))
    else:
        text += " (K_v not tuned: tune.viscous.enabled false)"
    rec["text"] = text + "."
    return rec


# the drive gains of `tune.method: model` (fftune.analysis.ffmodel.TERM_INFO): alias ->
# (symbol, term, unit)
_MODEL_GAINS = (("kfc", "K_fc", "coulomb", "V"), ("kfa", "K_fa", "asymmetry", "V"),
                ("kv", "K_v", "viscous", "V s/rad"), ("kps", "K_ps", "position", "V"),
                ("kpc", "K_pc", "position", "V"))


def _model_recommendation(t, node, on):
    """:func:`recommendation` of ``tune.method: model``: every gain of the converged model
    (``tune.model.gains``: the viscous one always, the requested terms' others) with its
    object and the 1 sigma of its term (the position term's two gains share the sigma of
    its amplitude). Keys as :func:`recommendation`'s plus ``gains`` ({alias: {symbol,
    term, value, sigma, unit, object}})."""
    m = t.get("model") or {}
    if not m.get("converged") or not m.get("gains"):
        return {"set": False, "node_id": node,
                "text": f"Nothing to set: the feed-forward model did not converge "
                        f"({m.get('stop_reason')})."}
    terms = t.get("terms") or {}
    gains = {}
    for alias, sym, term, unit in _MODEL_GAINS:
        if alias not in m["gains"] or (term not in terms and alias != "kv"):
            continue
        sig = (terms.get(term) or {}).get("sigma")
        gains[alias] = {"symbol": sym, "term": term, "value": round_sig(m["gains"][alias]),
                        "sigma": round_sig(sig, 2), "unit": unit, "object": _object_of(alias)[0]}
    parts = [f"{g['symbol']} = {gain_text(g['value'], g['unit'])}"
             + (f" (1 sigma {sigma_text(g['sigma'], g['unit'])})" if g["sigma"] is not None else "")
             + f" on object {g['object']}" for g in gains.values()]
    text = "Set " + (", ".join(parts[:-1]) + " and " + parts[-1] if len(parts) > 1 else parts[0])
    kfc, kv = gains.get("kfc"), gains.get("kv")
    return {"set": True, "node_id": node, "method": "model",
            "k_fc_v": kfc["value"] if kfc else None, "sigma_v": kfc["sigma"] if kfc else None,
            "k_fc_object": kfc["object"] if kfc else None,
            "k_v_v_s_per_rad": kv["value"] if kv else None, "k_v_object": kv["object"] if kv else None,
            "gains": gains, "text": f"{text}{on} (tune.method: model, every term at once)."}


def loop_comparison(results):
    """The rms tracking errors and odd-harmonic ratios of the tune step, each row with the
    feed-forward that was in the loop: a list of dicts (``what``, ``k_fc_v``, ``k_v``,
    ``rms_error_rad``, ``ratio``; None where not measured). Rows measured with the same K_v
    compare like with like; the table says which K_v each had."""
    t = results.get("tune")
    if not t:
        return []
    if t.get("method") == "model":
        return _model_loop_rows(t)
    s, e = t["search"], t["rms_error_rad"]
    # the K_v the search's runs had in the loop: the evaluation's own (k_v), else the one
    # read at K_fc = 0 (search.budget.viscous; search.k_v_in_search is the corrected value a
    # lag re-read used, not the runs')
    kv_search = (((s.get("budget") or {}).get("viscous") or {}).get("k_v_in_search")
                 or s.get("k_v_in_search") or 0.0)

    def kv_at(k):
        ev = [x for x in s.get("evaluations") or [] if _same_k(x.get("k_fc"), k) and "k_v" in x]
        return ev[0]["k_v"] if ev else (kv_search if k else 0.0)
    rows = [{"what": "no feed-forward", "k_fc_v": 0.0, "k_v": 0.0,
             "rms_error_rad": e.get("k_fc_0"), "ratio": t.get("ratio_at_zero")}]
    ver = s.get("verification_k_fc")
    rows.append({"what": "the search's run nearest K_fc*", "k_fc_v": ver, "k_v": kv_at(ver),
                 "rms_error_rad": e.get("k_fc_star"), "ratio": t.get("ratio_at_k_fc_star")})
    sw = t.get("sweep")
    ratio_min = None
    if sw and sw.get("k_fc") and sw.get("rms_error_rad") and t.get("k_fc_star") is not None:
        i = min(range(len(sw["k_fc"])), key=lambda j: abs(sw["k_fc"][j] - t["k_fc_star"]))
        if sw["k_fc"][i] != e.get("sweep_min_at_k_fc"):     # (else: the smallest row below)
            rows.append({"what": "the sweep's point nearest K_fc*", "k_fc_v": sw["k_fc"][i], "k_v": 0.0,
                         "rms_error_rad": sw["rms_error_rad"][i], "ratio": sw["ratio"][i]})
        else:
            ratio_min = sw["ratio"][i]
    same_as_run = (not sw and _same_k(e.get("sweep_min_at_k_fc"), ver)
                   and e.get("sweep_min") == e.get("k_fc_star"))
    if e.get("sweep_min") is not None and not same_as_run:
        rows.append({"what": "the sweep's smallest rms error" if sw else
                     "the search's smallest rms error",
                     "k_fc_v": e.get("sweep_min_at_k_fc"),
                     "k_v": 0.0 if sw else kv_at(e.get("sweep_min_at_k_fc")),
                     "rms_error_rad": e.get("sweep_min"), "ratio": ratio_min})
    v = t.get("viscous")
    if v:
        rows.append({"what": "recommended: K_fc* and K_v*", "k_fc_v": t.get("k_fc_star"),
                     "k_v": v.get("k_v_star"), "rms_error_rad": v.get("rms_error_rad"), "ratio": None})
    return rows


def _same_k(a, b):
    """The same gain, read once in float64 and once through the drive's float32 (a
    statistics capture): equal to 1e-6 relative."""
    import math
    return a is not None and b is not None and math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-12)


def _model_loop_rows(t):
    """:func:`loop_comparison` of ``tune.method: model``: its first experiment (no
    feed-forward) and every experiment at the verifying one's amplitude, each with the
    K_fc, K_v and amplitude it ran with (rows at another amplitude than the first say so)."""
    exps = (t.get("model") or {}).get("experiments") or []
    if not exps:
        return []
    first = exps[0]
    ver_tag = (t["model"].get("verification") or {}).get("tag")
    same = [i for i, x in enumerate(exps) if i and x.get("amplitude_rad") == first.get("amplitude_rad")]
    ver = [i for i, x in enumerate(exps) if i and x.get("tag") == ver_tag]
    rows = []
    for i, x in enumerate(exps):
        # the first, the last at its amplitude (like for like) and the verifying one
        if i and i not in same[-1:] + ver[-1:]:
            continue
        g = x.get("gains") or {}
        what = ("no feed-forward" if i == 0 and not any(g.values()) else
                f"experiment {i + 1} ({x.get('tag')}), the gains of the estimate before it")
        if x.get("amplitude_rad") != first.get("amplitude_rad"):
            what += f" (at {x['amplitude_rad']:g} rad, not {first['amplitude_rad']:g} rad: not like for like)"
        rows.append({"what": what, "k_fc_v": g.get("kfc"), "k_v": g.get("kv"),
                     "rms_error_rad": x.get("rms_error_rad"), "ratio": x.get("odd_ratio")})
    return rows


def loop_label(row):
    """A row of :func:`loop_comparison` as a legend or table label: what, K_fc, K_v."""
    return (f"{row['what']} (K_fc = {gain_text(row['k_fc_v'])}, "
            f"K_v = {gain_text(row['k_v'], 'V s/rad')})")


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
        rows = {r["what"]: r for r in loop_comparison(results)}
        r0, rs = rows["no feed-forward"], rows["the search's run nearest K_fc*"]
        text = (f"rms error {rms_text(r0['rms_error_rad'])} without feed-forward, "
                f"{rms_text(rs['rms_error_rad'])} at K_fc* (K_v = {gain_text(rs['k_v'], 'V s/rad')})")
        rmin = rows.get("the sweep's smallest rms error")
        near = rows.get("the sweep's point nearest K_fc*")
        if rmin and near:
            text += (f"; with K_v = 0 (like for like) the sweep's smallest is "
                     f"{rms_text(rmin['rms_error_rad'])} at K_fc = {gain_text(rmin['k_fc_v'])}, "
                     f"{rms_text(near['rms_error_rad'])} at its point nearest K_fc*")
        elif rmin:
            text += (f"; with K_v = 0 (like for like) the sweep's smallest is "
                     f"{rms_text(rmin['rms_error_rad'])} at K_fc = {gain_text(rmin['k_fc_v'])}, "
                     f"its point nearest K_fc*")
        rec = rows.get("recommended: K_fc* and K_v*")
        if rec:
            text += f"; {rms_text(rec['rms_error_rad'])} with the recommended K_fc* and K_v*"
        out["figure9"] = text
    return out


def measured_sensitivity(out_dir, results):
    """The loop's sensitivity at each detect level from the detect step's captures with
    samples (``<out_dir>/captures``, :func:`fftune.analysis.loop.sensitivity`): a list of
    (rms, (freq, S)), empty when the captures hold no samples (``capture: stats``) or are
    not there."""
    from fftune.analysis.capture import load_experiment
    from fftune.analysis.errors import InputError
    from fftune.analysis.loop import sensitivity

    d = results.get("detect") or {}
    cap = os.path.join(out_dir, "captures")
    if not d.get("levels") or d.get("capture") == "stats" or not os.path.isdir(cap):
        return []
    out = []
    for i, lv in enumerate(d["levels"]):
        try:
            ex = load_experiment(cap, experiment="detect", level_index=i)
        except (InputError, OSError, KeyError, ValueError):
            return []
        sig, p = ex.signals, ex.record_periods
        try:
            if d.get("inject") == "reference":
                x, r = sig["reference"] - sig["motor_angle"], sig["reference"]
            else:
                x, r = sig["plant_input"], sig["excitation"]
            out.append((lv["rms_requested"], sensitivity(x[:, -p:], r[:, -p:], fs=ex.fs_hz)[:2]))
        except (KeyError, InputError):
            return []
    return out


def save_figure(out_dir, name, fig, caption):
    """``fig`` written atomically as ``<out_dir>/<name>.png``; returns (file name, caption)."""
    fname = f"{name}.png"
    tmp = os.path.join(out_dir, f".tmp-{fname}")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    os.replace(tmp, os.path.join(out_dir, fname))
    return fname, caption


def make_figures(out_dir, detect_levels=None, hos=None, tune_data=None, results=None):
    """The paper's Figures 3 (lowest and highest level), 4, 5, 7 and 9 and the loop plots
    (the measured BLA with its confidence band; the tracking-error spectrum without and with
    the feed-forward) as PNG files via :mod:`fftune.analysis.plots`, each caption "what it
    shows (the paper's Figure N): details" ending with a conclusion computed from the data
    (:func:`figure_conclusions`).

    Returns ``{figure name: (file name, caption)}`` for the figures the data allow.
    """
    import matplotlib
    import numpy as np
    matplotlib.use("Agg")
    from fftune.analysis import plots

    made = {}
    results = results or {}
    concl = figure_conclusions(results, detect_levels, tune_data)

    def save(name, fig, caption, key=None):
        key = key or name.split("_")[0]
        if concl.get(key):
            caption = f"{caption} {concl[key]}."
        made[name] = save_figure(out_dir, name, fig, caption)

    if detect_levels is not None:
        unit_in = "V"
        d = results.get("detect") or {}
        if d.get("inject") == "reference":
            unit_in = "rad"
        for tag, i in (("lowest", 0), ("highest", -1)):
            res = detect_levels.results[i]
            rms = detect_levels.rms[i]
            save(f"figure3_output_spectrum_{tag}",
                 plots.figure3(res, title=f"Output spectrum at the {tag} level "
                                          f"({rms:.3g} {unit_in} rms)", unit="rad"),
                 f"Output spectrum at the {tag} level (the paper's Figure 3): BLA output, "
                 f"nonlinear and noise levels, non-excited odd and even lines and the "
                 f"plant-referred level there.", key=f"figure3_{tag}")
        save("figure4_bla_vs_level", plots.figure4(detect_levels, g_unit=f"rad/{unit_in}",
                                                   level_unit=unit_in),
             "BLA at each excitation level (the paper's Figure 4): magnitude and phase.")
        top = detect_levels.results[-1]
        if top.var_total is not None:
            rms = detect_levels.rms[-1]
            made["bla_confidence"] = save_figure(out_dir, "bla_confidence", plots.figure_bla(
                top, title=f"Measured BLA at {rms:.3g} {unit_in} rms with its 95 % confidence band",
                g_unit=f"rad/{unit_in}", band_p=0.95),
                f"Measured loop element (BLA) with its confidence band: G_BLA at the highest "
                f"level ({rms:.3g} {unit_in} rms), the 95 % band from its total variance "
                f"(noise and nonlinear distortion over the realizations), and the two standard "
                f"deviations.")
        sens = measured_sensitivity(out_dir, results)
        if sens:
            curves = {f"{rms:g} {unit_in} rms": fs_ for rms, fs_ in sens}
            peaks = [20 * np.log10(np.max(np.abs(S))) for _, (_, S) in sens]
            made["sensitivity"] = save_figure(out_dir, "sensitivity", plots.figure_sensitivity(
                curves, title="Measured sensitivity of the loop at each excitation level"),
                f"Measured sensitivity of the loop (the detect step, no feed-forward): "
                + ("|U/D|, the plant input over the excitation added to it (input sensitivity "
                   "1/(1 + C G))" if results["detect"].get("inject") != "reference" else
                   "|E/R|, the tracking error over the reference (1/(1 + G C))")
                + f" at the excited lines; largest |S| {peaks[0]:+.1f} dB at the lowest level, "
                  f"{peaks[-1]:+.1f} dB at the highest (a linear loop: the same at every level)"
                + ("; at the band's lowest line: the peak M_s may lie below the band"
                   if any(np.argmax(np.abs(S)) == 0 for _, (_, S) in sens) else "") + ".")
    if hos is not None:
        q_in = "V" if (results.get("quantify") or {}).get("inject") == "plant_input" else "rad"
        save("figure5_hosidf_vs_amplitude", plots.figure5(hos, unit=q_in, h_unit=f"rad/{q_in}"),
             "Higher-order sinusoidal input describing functions vs amplitude (the paper's "
             "Figure 5): odd and even HOSIDFs at every measured frequency (mean and standard "
             "deviation over repeats).")
    if tune_data is not None:
        save("figure7_tuning", plots.figure7(tune_data["k_sweep"], tune_data["H_sweep"],
                                             tune_data["ratio_sweep"], k_star=tune_data["k_star"],
                                             title="Odd HOSIDFs and the odd-harmonic ratio vs K_fc"),
             "Odd HOSIDFs and the tuning objective vs the Coulomb feed-forward K_fc (the "
             "paper's Figure 7): magnitude, unwrapped phase, odd-harmonic ratio.")
        rows = {r["what"]: r for r in loop_comparison(results)}
        recs = [(rows.get("no feed-forward"), tune_data["p0"]),
                (rows.get("the search's run nearest K_fc*"), tune_data["p_star"]),
                (rows.get("the sweep's smallest rms error") or rows.get("the search's smallest rms error"),
                 tune_data["p_rms"])]
        if tune_data.get("p_kv") is not None:
            recs.append((rows.get("recommended: K_fc* and K_v*"), tune_data["p_kv"]))
        if not results.get("tune") or recs[0][0] is None or recs[1][0] is None:
            return made
        recs = [(r, p) for r, p in recs if r is not None]   # (the smallest: the run itself)
        if any(not p["record"].signals for _, p in recs):
            # capture: stats uploads no samples; the time response needs raw (capture: both)
            return made
        labels = [f"{loop_label(r)}: rms {rms_text(r['rms_error_rad'])}" for r, _ in recs]
        fs = tune_data["fs"]
        save("figure9_time_response", plots.figure9(
            fs, tune_data["p0"]["record"].signals["reference"],
            {lb: p["record"].signals["motor_angle"] for lb, (_, p) in zip(labels, recs)},
            {lb: p["record"].signals["error"] for lb, (_, p) in zip(labels, recs)},
            title="Closed-loop response and tracking error with and without the feed-forward",
            rms_in_legend=False),
            "Closed-loop response and tracking error with and without the feed-forward "
            "(the paper's Figure 9): each line names the K_fc and K_v in the loop.")
        spec = [(loop_label(r), p) for r, p in recs
                if r["what"] in ("no feed-forward", "the search's run nearest K_fc*",
                                 "recommended: K_fc* and K_v*")]
        made["error_spectrum"] = save_figure(out_dir, "error_spectrum", plots.figure_error_spectrum(
            fs, {lb: p["record"].signals["error"] for lb, p in spec},
            title="Tracking-error spectrum without and with the feed-forward",
            f0=results["tune"]["frequency_hz"]),
            "Tracking-error spectrum without and with the feed-forward: the amplitude of "
            "the tracking error at the first 25 harmonics of the tune frequency (the tune "
            "step's records; the odd harmonics are the friction's share).")
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
    """The headline numbers (label, text) of a results dict: the terminal's summary and the
    top of the report's measurements; every rms error with the feed-forward in the loop."""
    rows = []
    t = results.get("tune")
    if t and t.get("method") == "model":       # every term at once (docs/method.md section 5)
        m = t["model"]
        rows.append(("feed-forward terms (tune.method model)", "converged" if m["converged"]
                     else f"not converged: {m['stop_reason']}"))
        for name, term in t["terms"].items():
            rows.append((f"{name} term", f"{gain_text(term['value'], term['unit'])} +- "
                                         f"{sigma_text(term['sigma'], term['unit'])}"))
        rows.append(("on the drive", (results.get("recommendation") or recommendation(results))["text"]))
        rows += [("closed-loop experiments", t["experiments"]),
                 ("odd / even level at the verifying experiment (re |H_1|)",
                  f"{_fmt(t['odd_ratio_at_optimum'], level=True)} / {_fmt(t['even_ratio_at_optimum'], level=True)}"),
                 ("true Coulomb friction (simulation)", _fmt(t["true_coulomb_v"], " V")),
                 ("Coulomb term vs truth", _fmt(t["k_fc_star_error_re_truth"], pct=True))]
        t = None
    if t:
        srch = t["search"]
        rec = results.get("recommendation") or recommendation(results)
        rows.append(("K_fc* (automated search)",
                     f"{gain_text(t['k_fc_star'])} +- {sigma_text(srch.get('sigma_v'))} (1 sigma_total) "
                     f"after {srch['experiments']} experiments" if srch["converged"]
                     else f"not converged: {srch['stop_reason']}"))
        rows.append(("on the drive", rec["text"]))
        if t.get("true_coulomb_v") is not None:
            rows.append(("K_fc* vs the true Coulomb level (simulation)",
                         f"{_fmt(t['k_fc_star_error_re_truth'], pct=True)} (true "
                         f"{gain_text(t['true_coulomb_v'])})"))
        if (t.get("sweep") or {}).get("optimum_k_fc") is not None:
            rows.append(("K_fc* vs the sweep's optimum",
                         f"{_fmt(srch['relative_to_sweep_optimum'], pct=True)} (sweep optimum "
                         f"{gain_text(t['sweep']['optimum_k_fc'])}, K_v = 0)"))
        rows.append(("odd-harmonic ratio re |H_1|",
                     f"{_fmt(t['ratio_at_zero'], level=True)} without feed-forward -> "
                     f"{_fmt(t['ratio_at_k_fc_star'], level=True)} at K_fc* "
                     f"({_fmt(t['ratio_improvement'], 'x')})"))
        for r in loop_comparison(results):
            rows.append((f"rms tracking error, {loop_label(r)}", rms_text(r["rms_error_rad"])))
    d = results.get("detect")
    if d:
        rows.append(("detection verdict", d["verdict"]))
    q = results.get("quantify")
    if q:
        rows.append(("largest HOSIDF level re |H_1|",
                     f"odd {_fmt(q['max_odd_relative_level'], level=True)}, even "
                     f"{_fmt(q['max_even_relative_level'], level=True)}"))
    if results.get("experiments"):
        rows.append(("experiments measured / resumed from captures",
                     f"{results['experiments']['measured']} / {results['experiments']['resumed']}"))
    return rows


def detail_rows(results):
    """The report's further numbers (label, text): the uncertainty's parts, the sweep and
    the detection per level."""
    rows = []
    t = results.get("tune")
    if t:
        s = t["search"]
        rows.append(("sigma_total(K_fc*) parts", ", ".join(f"{k} {sigma_text(v)}" for k, v in
                                                           (s.get("sigma_parts_v") or {}).items()) or "-"))
        if t.get("method") != "model":
            rows.append(("K_v in the loop during the search", _search_kv_text(s)))
        rows.append(("tune amplitude, frequency", f"{t['amplitude_rad']:.3g} rad, {t['frequency_hz']:g} Hz"))
    d = results.get("detect")
    if d:
        for tag, lv in (("lowest", d["levels"][0]), ("highest", d["levels"][-1])):
            s = lv["summary_db"]
            rows.append((f"{tag} level ({lv['rms_requested']:g} rms): nonlinear re output / noise "
                         f"re nonlinear (per-line medians)",
                         f"{_fmt(s.get('line_median_nl_re_output_db'), ' dB')} / "
                         f"{_fmt(s.get('line_median_noise_re_nl_db'), ' dB')}"))
        top = d["levels"][-1]["summary_db"]
        if top.get("parity_classifiable"):
            rows.append(("highest level: odd re even (power ratio)",
                         _fmt(top.get("odd_re_even_db"), " dB")))
    return rows


def _search_kv_text(s):
    runs = ((s.get("budget") or {}).get("viscous") or {}).get("k_v_in_search")
    final = s.get("k_v_in_search") or 0.0
    if runs is None or runs == final:
        return gain_text(final, "V s/rad")
    return (f"{gain_text(runs, 'V s/rad')} (read at K_fc = 0); K_fc* read again with "
            f"{gain_text(final, 'V s/rad')} (the motor's lag corrected)")


def comparison_table(results):
    """The like-for-like table (HTML): each row the feed-forward in the loop and what it gave."""
    rows = loop_comparison(results)
    if not rows:
        return ""
    out = ["<table class='cmp'><tr><th>in the loop</th><th>K_fc</th><th>K_v</th>"
           "<th>rms tracking error</th><th>odd-harmonic ratio re |H_1|</th></tr>"]
    for r in rows:
        out.append("<tr>" + "".join(f"<td>{html.escape(x)}</td>" for x in (
            r["what"], gain_text(r["k_fc_v"]), gain_text(r["k_v"], "V s/rad"),
            rms_text(r["rms_error_rad"]), _fmt(r["ratio"], level=True) if r["ratio"] is not None
            else "-")) + "</tr>")
    if (results["tune"].get("method") == "model"):
        out.append("</table><p class='note'>Compare rows at the same amplitude: each row ran with "
                   "the gains shown (and the position term's) at the amplitude its name says.</p>")
    else:
        out.append("</table><p class='note'>Compare rows with the same K_v: the sweep runs with "
                   "K_v = 0; the search runs with the K_v shown.</p>")
    return "\n".join(out)


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


_CSS = ("body{font-family:sans-serif;max-width:1200px;margin:auto;padding:0 8px;font-size:14px}"
        "h1{font-size:20px;margin:8px 0 2px}h2{font-size:16px;margin:14px 0 4px}"
        "h3{font-size:14px;margin:4px 0 0}p.meta,p.note,.sub,figcaption{color:#555;font-size:12px}"
        "p{margin:3px 0}.rec{border:2px solid #2a7;background:#eefaf2;padding:8px;font-size:15px}"
        "table{border-collapse:collapse;font-size:13px}th,td{border:1px solid #bbb;padding:2px 6px;"
        "text-align:left;vertical-align:top}"
        ".figs{display:grid;grid-template-columns:repeat(auto-fill,minmax(560px,1fr));gap:10px}"
        "figure{margin:0}img{width:100%}.sub{margin:0 0 2px}"
        "pre{background:#f4f4f4;padding:8px;white-space:pre-wrap;overflow-wrap:anywhere;font-size:12px}"
        "details{margin:6px 0}summary{cursor:pointer;font-weight:bold}"
        "ul.rec{padding-left:28px}td details{margin:0}td summary{font-weight:normal;color:#258}")


def _figure_heading(caption):
    """(title, subtitle, text) of a caption "Title (the paper's Figure N ...): text."."""
    import re
    head, _, text = caption.partition(": ")
    m = re.match(r"^(.*?) \((the paper's Figure [^)]*)\)$", head)
    if m:
        return m.group(1), m.group(2), text
    m = re.match(r"^Figure (\d+)\s*(\(([^)]*)\))?$", head)
    if m:      # an older caption "Figure N (detail): text"
        return text.split(".")[0], f"the paper's Figure {m.group(1)}" + (
            f", {m.group(3)}" if m.group(3) else ""), text
    return head, "", text


def _config_text(results):
    path = results.get("config_file")
    if not path or not os.path.isfile(str(path)):
        return None
    try:
        with open(path, "r", encoding="utf-8") as fh:
            return fh.read(200_000)
    except (OSError, UnicodeDecodeError):
        return None


def _figure_html(name, fname, caption):
    head, sub, text = _figure_heading(caption)
    return (f"<figure><h3>{html.escape(head)}</h3>"
            + (f"<p class='sub'>{html.escape(sub)}</p>" if sub else "")
            + f"<a href='{html.escape(fname)}'><img src='{html.escape(fname)}' "
              f"alt='{html.escape(name)}'></a>"
              f"<figcaption>{html.escape(text)}</figcaption></figure>")


# the figures a session's page shows collapsed ("More figures") unless told otherwise: the
# lowest level's output spectrum (the highest level's shows the nonlinearity)
MORE_FIGURES = ("figure3_output_spectrum_lowest",)


def write_html(out_dir, results, figures, title="fftune report", sections=(), first=(),
               more_figures=MORE_FIGURES, collapse_numbers=False):
    """``report.html``, a decision page: ``first`` ((heading, HTML) pairs: a verdict
    before everything, e.g. the paper's reproduction), the recommendation (what to set, on
    which object, :func:`recommendation`), ``sections`` ((heading, HTML) pairs), the
    like-for-like comparison (:func:`loop_comparison`), the key numbers (collapsed with
    ``collapse_numbers``), the figures (titled by what they show, the paper's figure
    number as a subtitle) in a grid, those named in ``more_figures`` collapsed under it,
    then the configuration and the full results (dB floors printed as such) collapsed."""
    ident = results.get("drive", {}).get("identity", {})
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p class='meta'>{html.escape(datetime.datetime.now().isoformat(timespec='seconds'))} &mdash; drive "
        f"{html.escape(str(ident.get('device_name', '?')))}, firmware "
        f"{html.escape(str(ident.get('firmware_version', '?')))}, "
        f"{html.escape(str(ident.get('bus', '')))}; configuration "
        f"{html.escape(str(results.get('config_file', '')))}</p>",
    ]
    for heading, body in first:
        parts += [f"<h2>{html.escape(heading)}</h2>", body]
    rec = results.get("recommendation") or recommendation(results)
    if rec is not None:
        parts.append(f"<h2>Recommendation</h2><p class='rec'>{html.escape(rec['text'])}</p>")
    elif results.get("detect"):
        parts.append(f"<h2>Result</h2><p class='rec'>Detection: "
                     f"{html.escape(results['detect']['verdict'])} (no tune step: nothing to set)</p>")
    for heading, body in sections:
        parts += [f"<h2>{html.escape(heading)}</h2>", body]
    cmp_html = comparison_table(results)
    if cmp_html:
        parts += ["<h2>With and without the feed-forward (like for like)</h2>", cmp_html]
    # (the recommendation and the rms errors are above: not twice)
    keys = [(k, v) for k, v in key_numbers(results)
            if not (cmp_html and k.startswith("rms tracking error")) and k != "on the drive"]
    if collapse_numbers:
        parts += [f"<details><summary>Key numbers ({len(keys) + len(detail_rows(results))} rows)</summary>",
                  _table(keys + detail_rows(results)), "</details>"]
    else:
        parts += ["<h2>Key numbers</h2>", _table(keys + detail_rows(results))]
    main = {k: v for k, v in (figures or {}).items() if k not in more_figures}
    more = {k: v for k, v in (figures or {}).items() if k in more_figures}
    if main:
        parts.append("<h2>Figures</h2><div class='figs'>")
        parts += [_figure_html(name, fname, caption) for name, (fname, caption) in main.items()]
        parts.append("</div>")
    if more:
        parts.append(f"<details><summary>More figures ({len(more)}: "
                     + html.escape(", ".join(_figure_heading(c)[0] for _, c in more.values()))
                     + ")</summary><div class='figs'>")
        parts += [_figure_html(name, fname, caption) for name, (fname, caption) in more.items()]
        parts.append("</div></details>")
    cfg_text = _config_text(results)
    if cfg_text is not None:
        parts.append(f"<details><summary>Configuration ({html.escape(str(results.get('config_file')))})"
                     f"</summary><pre>{html.escape(cfg_text)}</pre></details>")
    parts.append("<details><summary>All results (results.yaml)</summary><pre>")
    parts.append(html.escape(yaml.safe_dump(_floors_readable(_zero_levels_readable(results)), sort_keys=False,
                                            default_flow_style=None, width=90)))
    parts.append("</pre></details></body></html>")
    path = os.path.join(out_dir, "report.html")
    write_atomic(path, "\n".join(parts))
    return path
