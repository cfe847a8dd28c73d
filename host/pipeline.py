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
from fftune.host.report import _fmt, gain_text, make_figures, sigma_text, write_html, write_results

STEPS = ("detect", "quantify", "tune")
BUDGET_KEYS = ("excitation", "bus", "host", "wall", "drive_wait")


def time_budget(account_before, account_after, wall_s):
    """Where a step's wall time went, from two snapshots of ``DriveClient.time_account``.

    Returns a dict (seconds, rounded to ms): ``excitation`` = settle + recorded periods at
    fs of the runs measured (the physical minimum, whatever the drive's speed); ``bus`` =
    SDO transfers outside the runs (parameters, read-back, uploads); ``host`` = the rest
    (analysis, files, polling latency): ``wall - bus - min(excitation, drive_wait)``;
    ``wall``; ``drive_wait`` = measured time from each start command to the run's end
    (shorter than ``excitation`` when the simulated drive free-runs faster than real time,
    longer by the polling latency on a real-time drive). Runs resumed from captures
    cost neither excitation nor bus.
    """
    d = {k: account_after.get(k, 0.0) - account_before.get(k, 0.0)
         for k in ("excitation_s", "transfer_s", "run_wait_s")}
    host = wall_s - d["transfer_s"] - min(d["excitation_s"], d["run_wait_s"])
    out = {"excitation": d["excitation_s"], "bus": d["transfer_s"], "host": max(0.0, host),
           "wall": wall_s, "drive_wait": d["run_wait_s"]}
    return {k: round(v, 3) for k, v in out.items()}


def check_plan(drive, cfg, steps=STEPS, session=None):
    """:func:`fftune.host.plan.preflight` with the limits read from ``drive`` and the capture
    modes the session will use; raises on the first violation, returns the checked plan."""
    from fftune.host.plan import preflight, read_drive_limits

    session = session or ex.Session(drive, cfg, "", log=lambda s: None)
    return preflight(cfg, read_drive_limits(drive, cfg), steps=[s for s in steps if s in STEPS],
                     capture_mode=session.capture_mode)


def run_pipeline(drive, cfg, out_dir, steps=STEPS, log=print, figures=True, preflight=True,
                 before_figures=None, data=None, after_step=None):
    """Run ``steps`` in order; returns the results dict (also written to ``out_dir``).
    ``data``: a dict that receives the analysis objects behind the figures
    (``detect_levels``, ``hos``, ``tune_data``; None for a step not run) and the figures
    made (``figures``: name -> (file name, caption)).

    With ``preflight`` (default; not for a CAN-log replay: its runs happened) every
    excitation of the plan is first checked against the drive's limits and the
    configuration's (:func:`fftune.host.plan.preflight`): a violation raises before any
    experiment and before anything is written. ``out_dir`` is created when the first
    capture is written.

    ``before_figures``: called (no arguments) after the experiments, before the figures are
    drawn: a machine's axis stops and disables its drive there (it has measured); a machine
    draws its axes' figures in a separate process (``figures=False`` here).

    ``after_step``: called ``after_step(step, results, obj)`` after each step that ran, with
    the analysis object behind its figures (``detect_levels``, ``hos`` or ``tune_data``): a
    machine has the step's figures drawn while the axis' next step measures."""
    t0 = time.monotonic()
    session = ex.Session(drive, cfg, out_dir, log=log)
    if preflight:
        check_plan(drive, cfg, steps, session=session)
    results = {
        "fftune_version": __version__,
        "config_file": cfg.get("_source"),
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
        "drive": {"identity": session.identity, "fs_hz": session.fs_hz,
                  "plant_truth": session.truth},
    }
    detect_levels = hos = tune_data = None
    account = getattr(drive, "time_account", None)  # a live drive client (not a CAN-log replay)
    budgets = {}
    if "tune" in steps and cfg["tune"]["enabled"]:
        ex.check_tune_plan(session)      # before any experiment: the tune keys vs the drive
    for step in steps:
        if not cfg[step]["enabled"]:
            log(f"{step}: disabled in the configuration")
            continue
        t = time.monotonic()
        account_before = dict(account) if account is not None else None
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
            srch = tr["search"]
            if srch["converged"]:
                # (the report's rounding: one value per quantity in every output)
                log(f"tune: K_fc* = {gain_text(tr['k_fc_star'])} +- {sigma_text(srch['sigma_v'])} (sigma_total: "
                    "noise and the measured systematic parts, results.yaml tune.search.sigma_parts_v) "
                    f"after {srch['experiments']} experiments at {tr['amplitude_rad']:.3g} rad; "
                    f"odd-harmonic ratio {_fmt(tr['ratio_at_zero'], level=True)} -> "
                    f"{_fmt(tr['ratio_at_k_fc_star'], level=True)}")
            else:
                log(f"tune: not converged after {srch['experiments']} experiments: "
                    f"{srch['stop_reason']}")
        if after_step is not None:
            after_step(step, results, {"detect": detect_levels, "quantify": hos, "tune": tune_data}[step])
        n_runs = session.counts["measured"] + session.counts["resumed"] - before
        results.setdefault("timing_s", {})[step] = round(time.monotonic() - t, 2)
        results.setdefault("runs", {})[step] = n_runs
        if account is not None:
            budgets[step] = time_budget(account_before, account, time.monotonic() - t)
    if budgets:
        total = {k: round(sum(b[k] for b in budgets.values()), 3) for k in BUDGET_KEYS}
        results["time_budget_s"] = dict(budgets, total=total)
    results["experiments"] = dict(session.counts)
    results["finished"] = datetime.datetime.now().isoformat(timespec="seconds")
    results["wall_time_s"] = round(time.monotonic() - t0, 2)
    os.makedirs(out_dir, exist_ok=True)
    write_results(out_dir, results)
    if data is not None:
        data.update(detect_levels=detect_levels, hos=hos, tune_data=tune_data)
    figs = {}
    if before_figures is not None:
        before_figures()
    if figures:
        figs = make_figures(out_dir, detect_levels, hos, tune_data, results)
    if data is not None:
        data["figures"] = figs
    write_html(out_dir, results, figs)
    return results


def summary_lines(results, out_dir):
    """A short text summary for the terminal."""
    from fftune.host.report import key_numbers
    lines = [f"fftune results in {os.path.relpath(out_dir)}/ (results.yaml, report.html, captures/)"]
    for label, text in key_numbers(results):
        lines.append(f"  {label}: {text}")
    lines += time_budget_lines(results)
    return lines


def time_budget_lines(results):
    """The time budget of results.yaml as terminal lines (none without one)."""
    budget = results.get("time_budget_s")
    if not budget:
        return []
    lines = ["  time budget [s]       excitation      bus     host     wall  (drive waited)"]
    for step, b in budget.items():
        lines.append(f"    {step:<18} {b['excitation']:>9.1f} {b['bus']:>8.1f} {b['host']:>8.1f} "
                     f"{b['wall']:>8.1f}  ({b['drive_wait']:.1f})")
    return lines
