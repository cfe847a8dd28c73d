"""``report.html`` of ``fftune track`` / ``demo-track``: the gains the tracker left on the
drive first, a note on every update of K_fc larger than 2 sigma of its estimate, the K_fc
path with the tracking-error panel, the run's figures, results.yaml collapsed.

The rows are those of :func:`fftune.host.track.track_session` (results.yaml ``track``);
this module only reads them.
"""
import datetime
import html
import math
import os

import yaml

from fftune.host.atomic import write_atomic

# an update of K_fc larger than this many sigma of the estimate it came from is noted
LARGE_UPDATE_SIGMA = 2.0


def large_updates(rows, n_sigma=LARGE_UPDATE_SIGMA):
    """The updates of K_fc larger than ``n_sigma`` sigma: a list of dicts (``task``,
    ``t_s``, ``from_v``, ``to_v``, ``step_rel`` (fraction of ``from_v``; None from 0),
    ``sigmas``, ``off_truth_rel`` (the new value re the simulated truth, None without),
    ``action``). An update is the change from the K_fc the task ran with to the one the
    tracker set after it (``k_fc_next``); its size in sigma is re the task's estimate's
    ``k_fc_sigma`` (a task without an estimate has no sigma: not judged)."""
    out = []
    for r in rows:
        k0, k1, sig = r.get("k_fc"), r.get("k_fc_next"), r.get("k_fc_sigma")
        if k0 is None or k1 is None or not sig or not math.isfinite(sig) or sig <= 0:
            continue
        step = k1 - k0
        if abs(step) > n_sigma * sig:
            truth = r.get("k_fc_true")
            out.append({"task": r["task"], "t_s": r.get("t_s"), "from_v": k0, "to_v": k1,
                        "step_rel": step / k0 if k0 else None, "sigmas": abs(step) / sig,
                        "off_truth_rel": (k1 / truth - 1) if truth else None,
                        "action": r.get("action")})
    return out


def _pct(x):
    """A relative value in % to 0.1 % (no "-0.0 %")."""
    v = round(100 * x, 1)
    return f"{v + 0.0:+.1f} %"


def note_text(u):
    """One note line of :func:`large_updates`' item."""
    rel = f" ({_pct(u['step_rel'])})" if u["step_rel"] is not None else ""
    truth = (f"; the new value is {_pct(u['off_truth_rel'])} off the simulated truth"
             if u["off_truth_rel"] is not None else "")
    from fftune.host.report import gain_text

    return (f"task {u['task']} (t {u['t_s']:.1f} s): K_fc moved from {gain_text(u['from_v'])} to "
            f"{gain_text(u['to_v'])}{rel}, {u['sigmas']:.1f} sigma of its estimate"
            f" ({u['action']}){truth}")


def track_figure(rows, title=None):
    """The K_fc path (applied, estimates +- sigma, the truth where known, the large updates
    circled) over the tracking-error panel (rms error per task): a Figure (no pyplot)."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    t = np.array([r["t_s"] for r in rows], dtype=float)
    k = np.array([r["k_fc"] for r in rows], dtype=float)
    est = np.array([np.nan if r.get("k_fc_estimate") is None else r["k_fc_estimate"] for r in rows])
    sig = np.array([np.nan if r.get("k_fc_sigma") is None else r["k_fc_sigma"] for r in rows])
    err = np.array([np.nan if r.get("rms_error") is None else r["rms_error"] for r in rows])
    fig = Figure(figsize=(9.0, 5.5), layout="constrained")
    FigureCanvasAgg(fig)
    a1, a2 = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
    a1.fill_between(t, est - sig, est + sig, color="C0", alpha=0.15, label="estimate +- sigma")
    a1.plot(t, est, ".", color="C0", ms=3, label="estimate per task")
    a1.step(t, k, where="pre", color="C1", label="K_fc applied (during the task)")
    if any(r.get("k_fc_true") is not None for r in rows):
        a1.plot(t, [np.nan if r.get("k_fc_true") is None else r["k_fc_true"] for r in rows],
                "k--", lw=1, label="truth (simulated plant)")
    big = large_updates(rows)
    if big:
        a1.plot([u["t_s"] for u in big], [u["to_v"] for u in big], "o", mfc="none", mec="tab:red",
                ms=9, label=f"update > {LARGE_UPDATE_SIGMA:g} sigma")
    a1.set_ylabel("K_fc (V)")
    a2.plot(t, err, "-", color="C2", lw=1, marker=".", ms=3, label="rms tracking error per task")
    a2.set_ylabel("rms tracking error (rad)")
    a2.set_xlabel("time (s, task end)")
    for ax in (a1, a2):
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=8)
    a1.set_title(title or "K_fc tracked from the repeated task, and the tracking error")
    return fig


def write_track_report(out, results, cfg=None, figures=True):
    """``<out>/report.html`` (and ``<out>/track_path.png`` with ``figures``) of a track
    session's results; returns the page's path."""
    from fftune.host.report import _CSS, _object_of, gain_text, rms_text, round_sig

    rows = results["track"]
    s = results["track_summary"]
    parts = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>fftune track</title>",
             f"<style>{_CSS}</style></head><body><h1>fftune track</h1>",
             f"<p class='meta'>{html.escape(datetime.datetime.now().isoformat(timespec='seconds'))}"
             f" &mdash; {s['tasks']} tasks of {s['task_s']} s"
             + (f"; configuration {html.escape(str(cfg.get('_source')))}" if cfg and cfg.get("_source") else "")
             + "</p>"]
    node = (cfg or {}).get("drive", {}).get("node_id")
    obj_fc, _ = _object_of("kfc")
    obj_kv, _ = _object_of("kv")
    on = f" of node {node}" if node is not None else ""
    truth = (f" (simulated truth {gain_text(s['k_fc_true_final'])})"
             if s.get("k_fc_true_final") is not None else "")
    if s["stop"]:
        head = (f"Tracking stopped at task {s['stop']['task']} ({s['stop']['cause']}): "
                f"{s['stop']['reason']}. The drive holds K_fc = {gain_text(s['k_fc_final'])} on "
                f"object {obj_fc}{on}.")
    else:
        head = (f"The drive runs K_fc = {gain_text(s['k_fc_final'])}{truth} on object {obj_fc}{on} "
                f"and K_v = {gain_text(s['k_v_final'], 'V s/rad')} on object {obj_kv}, written by "
                f"the tracker after task {rows[-1]['task'] if rows else '-'}.")
    parts.append(f"<h2>On the drive</h2><p class='rec'>{html.escape(head)}</p>")
    big = large_updates(rows)
    parts.append(f"<h2>Updates larger than {LARGE_UPDATE_SIGMA:g} sigma ({len(big)})</h2>")
    if big:
        parts.append("<ul>" + "".join(f"<li>{html.escape(note_text(u))}</li>" for u in big) + "</ul>")
    else:
        parts.append("<p>none: every update of K_fc stayed within "
                     f"{LARGE_UPDATE_SIGMA:g} sigma of its estimate.</p>")
    errs = [r["rms_error"] for r in rows if r.get("rms_error") is not None]
    facts = [("tasks", s["tasks"]),
             ("rms tracking error, first / last task",
              f"{round_sig(errs[0]):g} / {rms_text(errs[-1])}" if errs else "n/a"),
             ("rollbacks", sum(1 for r in rows if r.get("action") == "rollback")),
             ("bus: largest task", f"{s['bus']['bits_per_task_max']} bits = "
                                   f"{100 * s['bus']['task_traffic_load']:.2f} % of {s['bus']['bitrate']} bit/s")]
    if s.get("check"):
        facts.append(("odd-harmonic ratio re |H_1| (check at the tracked gains)",
                      f"{100 * s['check']['odd_ratio']:.3g} % at K_fc = {gain_text(s['check']['k_fc'])}"))
    parts.append("<h2>Key numbers</h2><table>" + "".join(
        f"<tr><th>{html.escape(str(a))}</th><td>{html.escape(str(b))}</td></tr>" for a, b in facts)
        + "</table>")
    if figures and rows:
        fig = track_figure(rows)
        tmp = os.path.join(out, ".tmp-track_path.png")
        fig.savefig(tmp, dpi=100)
        os.replace(tmp, os.path.join(out, "track_path.png"))
        parts.append("<h2>Figures</h2><figure><h3>K_fc path and tracking error</h3>"
                     "<a href='track_path.png'><img src='track_path.png' alt='K_fc path'></a>"
                     "<figcaption>K_fc applied per task (step), its estimates with sigma, the "
                     "simulated truth where known, the updates larger than "
                     f"{LARGE_UPDATE_SIGMA:g} sigma circled; below, the rms tracking error of each "
                     "task.</figcaption></figure>")
    parts.append("<details><summary>All results (results.yaml)</summary><pre>"
                 + html.escape(yaml.safe_dump(results, sort_keys=False, width=100)) + "</pre></details>")
    parts.append("</body></html>")
    path = os.path.join(out, "report.html")
    write_atomic(path, "\n".join(parts))
    return path
