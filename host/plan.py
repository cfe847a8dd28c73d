"""What a configuration's experiments cost before they run: runs, excitation time and the
bytes each capture mode uploads, per step (``detect``, ``quantify``, ``tune``).

The excitation time is the physical minimum (settle + recorded periods at fs for every
run); the bytes are the recorder's float32 samples (raw) or the drive's line statistics
(stats, the layout of object 0x2041, docs/firmware.md). With a measured cost per run and
per byte on a bus (:func:`bus_rates` from a session's ``time_budget_s``), :func:`project`
turns a plan into the time budget of results.yaml (excitation, bus, host) before a single
experiment: `make bench` prints it for configs/paper.yaml at 1 Mbit/s.
"""
from dataclasses import dataclass

from fftune.analysis.stats import LSTAT_LINE_FLOATS, LSTAT_LINES_MAX, STAT_K_MAX

__all__ = ["StepPlan", "experiment_plan", "bus_rates", "project", "STATS_HEADER_BYTES",
           "line_stats_bytes"]

STATS_HEADER_BYTES = 8
FLOAT_BYTES = 4


def stats_bytes(harmonics, n_harmonic_signals, n_power_signals):
    """Bytes of one run's line statistics (object 0x2041): header, 3 float32 per line and
    harmonic signal, 2 per power signal."""
    return STATS_HEADER_BYTES + 12 * int(harmonics) * n_harmonic_signals + 8 * n_power_signals


@dataclass
class StepPlan:
    """The runs of one step.

    Attributes
    ----------
    step : str
    runs : int
        Closed-loop runs (for tune: at most, the search stops earlier).
    excitation_s : float
        Settle + recorded periods at fs, summed over the runs (s).
    raw_bytes : int
        The recordings the analysis reads (float32).
    stats_bytes : int or None
        The line statistics instead; None where the drive has none for this step.
    note : str
    """

    step: str
    runs: int
    excitation_s: float
    raw_bytes: int
    stats_bytes: object
    note: str = ""


def line_stats_bytes(n_lines):
    """Bytes of one multisine run's line statistics (object 0x2043): header, per line its
    bin and 10 float32."""
    return STATS_HEADER_BYTES + (4 + 4 * LSTAT_LINE_FLOATS) * int(n_lines)


def experiment_plan(cfg, fs_hz, lines_capacity=LSTAT_LINES_MAX):
    """The :class:`StepPlan` of each enabled step of a validated configuration.

    Parameters
    ----------
    cfg : dict
        :func:`fftune.host.config.load_config` output.
    fs_hz : float
        The drive's controller rate (Hz).
    lines_capacity : int
        Lines the drive's line statistics hold (object 0x2040:9; default: drive_sim's).

    Returns
    -------
    list of StepPlan
    """
    fs = float(fs_hz)
    out = []
    d = cfg["detect"]
    if d["enabled"]:
        runs = len(d["rms_levels"]) * d["realizations"]
        from fftune.host.experiments import detect_lines
        n_sig = 3 if d["inject"] == "reference" else 2
        band = detect_lines(d, fs, cfg.get("_source", "config"))[3]
        fits = band.size <= lines_capacity
        out.append(StepPlan(
            "detect", runs, runs * (d["settle_periods"] + d["periods"]) * d["period_samples"] / fs,
            runs * d["periods"] * d["period_samples"] * n_sig * FLOAT_BYTES,
            runs * line_stats_bytes(band.size) if fits else None,
            f"line statistics of {band.size} lines" if fits else
            f"{band.size} lines > the {lines_capacity} the drive holds: raw only"))
    q = cfg["quantify"]
    if q["enabled"]:
        runs = len(q["rms_levels"]) * len(q["frequencies_hz"]) * q["repeats"]
        k_ok = q["harmonics"] <= STAT_K_MAX
        out.append(StepPlan(
            "quantify", runs, runs * (q["settle_periods"] + q["periods"]) * q["period_samples"] / fs,
            runs * q["periods"] * q["period_samples"] * 2 * FLOAT_BYTES,
            runs * stats_bytes(q["harmonics"], 2, 0) if k_ok else None,
            "" if k_ok else f"harmonics {q['harmonics']} > {STAT_K_MAX}: raw only"))
    t = cfg["tune"]
    if t["enabled"]:
        runs = t["sweep"]["points"] + t["search"]["max_experiments"]
        if t["amplitude_rad"] == "auto":
            runs += 4
        if t["viscous"]["enabled"]:
            runs += t["viscous"]["max_experiments"] + 2
        runs += 4      # the uncertainty budget: lag correction (<= 2), second amplitude (<= 2)
        k_ok = t["harmonics"] <= STAT_K_MAX
        out.append(StepPlan(
            "tune", runs, runs * (t["settle_periods"] + t["periods"]) * t["period_samples"] / fs,
            runs * t["periods"] * t["period_samples"] * 3 * FLOAT_BYTES,
            runs * stats_bytes(t["harmonics"], 3, 2) if k_ok else None,
            "runs: at most (sweep + search + viscous + probes + budget)"))
    return out


def bus_rates(raw_step, stats_step):
    """Cost per run and per uploaded byte on a bus, from two measured steps.

    Parameters
    ----------
    raw_step : (runs, bytes, bus_s)
        A step that uploaded recordings (e.g. the demo's detect).
    stats_step : (runs, bytes, bus_s)
        A step of small uploads (e.g. the demo's quantify on statistics): its bus time is
        almost all per-run cost (parameter writes and read-back, the run's start).

    Returns
    -------
    (s_per_run, s_per_byte)
    """
    runs_s, bytes_s, bus_s = stats_step
    runs_r, bytes_r, bus_r = raw_step
    if runs_s <= 0 or bytes_r <= bytes_s / max(runs_s, 1) * runs_r:
        raise ValueError("bus_rates: need a step with runs and a step with larger uploads")
    # two equations bus = runs a + bytes b
    det = runs_r * bytes_s - runs_s * bytes_r
    a = (bus_r * bytes_s - bus_s * bytes_r) / det
    b = (runs_r * bus_s - runs_s * bus_r) / det
    if a < 0 or b <= 0:     # noise: fall back to all per-run on the small step
        a = bus_s / runs_s
        b = max(bus_r - runs_r * a, 0.0) / bytes_r
    return a, b


def project(plan, s_per_run, s_per_byte, host_s_per_run, capture):
    """Time budget (s) of a plan: {step: {excitation, bus, host, wall}} and ``total``.

    ``capture`` 'raw' or 'stats' (steps without statistics stay raw)."""
    out, tot = {}, {"excitation": 0.0, "bus": 0.0, "host": 0.0, "wall": 0.0}
    for p in plan:
        nbytes = p.stats_bytes if capture == "stats" and p.stats_bytes is not None else p.raw_bytes
        row = {"excitation": p.excitation_s, "bus": p.runs * s_per_run + nbytes * s_per_byte,
               "host": p.runs * host_s_per_run}
        row["wall"] = sum(row.values())
        out[p.step] = row
        for k in tot:
            tot[k] += row[k]
    out["total"] = tot
    return out
