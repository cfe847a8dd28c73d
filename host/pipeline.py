"""The pipeline behind ``fftune detect|quantify|tune|run|demo|import-canlog``.

:func:`run_pipeline` runs the chosen experiments on a drive, then writes ``results.yaml``,
the figures and ``report.html`` into the output directory (captures are written by the
session as the runs arrive).
"""
import datetime
import os
import time

from fftune.host import __version__
from fftune.host import experiments as ex
from fftune.host.report import make_figures, write_html, write_results

STEPS = ("detect", "quantify", "tune")


def run_pipeline(drive, cfg, out_dir, steps=STEPS, log=print, figures=True):
    """Run ``steps`` in order; returns the results dict (also written to ``out_dir``)."""
    t0 = time.monotonic()
    session = ex.Session(drive, cfg, out_dir, log=log)
    results = {
        "fftune_version": __version__,
        "config_file": cfg.get("_source"),
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
        "drive": {"identity": session.identity, "fs_hz": session.fs_hz,
                  "plant_truth": session.truth},
    }
    detect_levels = hos = tune_data = None
    for step in steps:
        if not cfg[step]["enabled"]:
            log(f"{step}: disabled in the configuration")
            continue
        t = time.monotonic()
        before = session.counts["measured"] + session.counts["resumed"]
        if step == "detect":
            results["detect"], detect_levels = ex.detect(session)
            log(f"detect: {results['detect']['verdict']}")
        elif step == "quantify":
            results["quantify"], hos = ex.quantify(session)
            log(f"quantify: largest odd HOSIDF level re H_1 "
                f"{results['quantify']['max_odd_relative_level']:.3g}")
        elif step == "tune":
            results["tune"], tune_data = ex.tune(session)
            tr = results["tune"]
            log(f"tune: K_fc* = {tr['k_fc_star']:.4g} V after {tr['search']['experiments']} "
                f"experiments (sweep optimum {tr['sweep']['optimum_k_fc']:.4g} V); ratio "
                f"{tr['ratio_at_zero']:.3g} -> {tr['ratio_at_k_fc_star']:.3g}")
        n_runs = session.counts["measured"] + session.counts["resumed"] - before
        results.setdefault("timing_s", {})[step] = round(time.monotonic() - t, 2)
        results.setdefault("runs", {})[step] = n_runs
    results["experiments"] = dict(session.counts)
    results["finished"] = datetime.datetime.now().isoformat(timespec="seconds")
    results["wall_time_s"] = round(time.monotonic() - t0, 2)
    write_results(out_dir, results)
    figs = {}
    if figures:
        figs = make_figures(out_dir, detect_levels, hos, tune_data, results)
    write_html(out_dir, results, figs)
    return results


def summary_lines(results, out_dir):
    """A short text summary for the terminal."""
    from fftune.host.report import key_numbers
    lines = [f"fftune results in {os.path.relpath(out_dir)}/ (results.yaml, report.html, captures/)"]
    for label, text in key_numbers(results):
        lines.append(f"  {label}: {text}")
    return lines
