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
           "line_stats_bytes", "DriveLimits", "read_drive_limits", "config_limits", "Check",
           "CheckedPlan", "preflight"]

STATS_HEADER_BYTES = 8
FLOAT_BYTES = 4
# the feed-forward gains' drive parameters (0x2000:4, 5, 9, 10, 11)
FF_GAIN_PARAMS = ("KFC", "KV", "KFA", "KPS", "KPC")


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


# ---------------------------------------------------------------------------------------
# preflight: every excitation of the plan against the drive's limits and the config's
# ---------------------------------------------------------------------------------------
@dataclass
class DriveLimits:
    """What the drive allows, as read from it (or what is known without it: None).

    Attributes
    ----------
    fs_hz : float or None
        Controller rate (object 0x2000:8); fs/2 bounds every line.
    u_max_v : float or None
        Output limit (0x2000:7; the configuration's ``drive.controller.u_max`` when set:
        the session writes it with every run).
    rec_capacity : int or None
        Recorder capacity in float values (0x2020:2).
    lines_capacity : int or None
        Lines the line statistics hold (0x2040:9).
    table_capacity : int or None
        Longest excitation period N in samples: the drive's table capacity 0x2004 (a port
        short of RAM holds fewer than the EDS allows: the M4 build 4096), else (a drive
        without 0x2004) the high limit of 0x2001:5 in the drive's EDS.
    amplitude_high : float or None
        High limit of the excitation amplitude object 0x2001:3.
    drive_u_max_v : float or None
        The output limit the drive has (0x2000:7) before the session writes any: the
        configuration's ``drive.controller.u_max`` may lower it, not raise it.
    gain_high : dict or None
        High limits of the feed-forward gains' objects by parameter (KFC, KV, KFA, KPS,
        KPC: 0x2000:4, 5, 9 .. 11) in the drive's EDS, else configs/od.yaml; None: od.yaml.
    source : str
        Where the numbers come from (printed with the plan).
    """

    fs_hz: object = None
    u_max_v: object = None
    rec_capacity: object = None
    lines_capacity: object = None
    table_capacity: object = None
    amplitude_high: object = None
    drive_u_max_v: object = None
    gain_high: object = None
    source: str = "the configuration only (no drive)"


def _od_high(drive, param):
    """High limit of the object carrying ``param``: from the drive's EDS when the client has
    one, else configs/od.yaml (the one source the EDS is generated from)."""
    from fftune.host.config import od_param_high
    from fftune.host.odmap import PARAMS

    entry = PARAMS.get(param.lower())
    od = getattr(getattr(drive, "node", None), "object_dictionary", None)
    if od is not None and entry is not None:
        try:
            obj = od[entry.index]
            var = obj[entry.subindex] if entry.subindex or hasattr(obj, "subindices") else obj
            if var.max is not None:
                return float(var.max)
        except (KeyError, AttributeError, TypeError):
            pass
    return od_param_high(param)


def read_drive_limits(drive, cfg):
    """:class:`DriveLimits` read from ``drive`` (a connected DriveClient-like object); an
    object the drive does not have (or reports as 0) stays None: not checked."""
    from fftune.analysis.errors import FftuneError

    def get(name):
        try:
            value = float(drive.get(name))
        except (FftuneError, KeyError, AttributeError, TypeError, ValueError):
            return None
        return value if value > 0 else None

    u_max = cfg["drive"]["controller"].get("u_max")
    drive_u_max = get("u_max")
    cap = get("rec_capacity")
    lines = get("stat_lines_cap")
    table = get("table_cap")
    describe = getattr(getattr(drive, "opts", None), "describe", None)
    where = f"node {cfg['drive']['node_id']} on {describe()}" if describe else "the drive"
    return DriveLimits(fs_hz=get("fs"), u_max_v=float(u_max) if u_max is not None else drive_u_max,
                       drive_u_max_v=drive_u_max,
                       rec_capacity=None if cap is None else int(cap),
                       lines_capacity=None if lines is None else int(lines),
                       table_capacity=int(min(table, _od_high(drive, "EXC_PERIOD")) if table is not None
                                          else _od_high(drive, "EXC_PERIOD")),
                       amplitude_high=_od_high(drive, "EXC_AMPLITUDE"),
                       gain_high={p: _od_high(drive, p) for p in FF_GAIN_PARAMS},
                       source=f"read from {where}")


def config_limits(cfg):
    """:class:`DriveLimits` known without a drive: fs from ``drive.fs_hz``, u_max from
    ``drive.controller.u_max``, the period and amplitude limits of the EDS source."""
    from fftune.host.config import od_param_high

    u_max = cfg["drive"]["controller"].get("u_max")
    return DriveLimits(fs_hz=cfg["drive"].get("fs_hz"), u_max_v=u_max,
                       table_capacity=int(od_param_high("EXC_PERIOD")),
                       amplitude_high=od_param_high("EXC_AMPLITUDE"),
                       gain_high={p: od_param_high(p) for p in FF_GAIN_PARAMS})


@dataclass
class Check:
    """One checked quantity of the plan: ``value`` against ``limit`` (None: not known)."""

    step: str
    key: str
    what: str
    value: float
    limit: object
    unit: str
    limit_name: str
    hard: bool = True       # a violation refuses the plan (False: a note, e.g. saturation)
    text: str = None        # the error's wording after the key (default: value, limit, name)

    @property
    def ok(self):
        return None if self.limit is None else self.value <= self.limit * (1 + 1e-9)


@dataclass
class CheckedPlan:
    """:func:`preflight`'s result: the checks, the runs per step, the notes, the limits."""

    limits: DriveLimits
    checks: list
    steps: list
    notes: list

    def lines(self, src):
        """The plan as terminal lines (``fftune plan``)."""
        lim = self.limits
        out = [f"fftune plan: {src}", f"drive limits: {lim.source}"]

        def val(v, unit):
            if v is None:
                return "not known"
            return f"{v} {unit}" if isinstance(v, int) else f"{v:g} {unit}"
        out.append(f"  fs = {val(lim.fs_hz, 'Hz')}" + (f" (fs/2 = {lim.fs_hz / 2:g} Hz)" if lim.fs_hz else ""))
        out.append(f"  u_max = {val(lim.u_max_v, 'V')}")
        out.append(f"  recorder capacity = {val(lim.rec_capacity, 'float values')}")
        out.append(f"  line statistics capacity = {val(lim.lines_capacity, 'lines')}")
        out.append(f"  period N <= {val(lim.table_capacity, 'samples')} (table capacity 0x2004, else the EDS), "
                   f"excitation amplitude <= {val(lim.amplitude_high, '')}".rstrip())
        for st in [{"step": "drive", "text": "controller parameters written with every run"}] + self.steps:
            if st["step"] == "drive" and not any(c.step == "drive" for c in self.checks):
                continue
            out.append(f"{st['step']}: {st['text']}")
            for c in self.checks:
                if c.step != st["step"]:
                    continue
                state = "not checked (limit not known)" if c.ok is None else \
                    "ok" if c.ok else ("REFUSED" if c.hard else "note: above")
                limit = "-" if c.limit is None else f"{c.limit:.4g} {c.unit}"
                out.append(f"  {c.key:<30} {c.what:<22} {c.value:>10.4g} {c.unit:<6} "
                           f"limit {limit:<14} ({c.limit_name}) {state}")
        for note in self.notes:
            out.append(f"note: {note}")
        return out


def _multisine_peaks(d, fs, k_min, k_max):
    """Largest |x| and |dx/dt| (per unit rms, per s at ``fs``) over the detect design's
    realizations."""
    import numpy as np

    from fftune.analysis.multisine import drive_multisine

    n = d["period_samples"]
    w = 2 * np.pi * np.fft.rfftfreq(n, 1.0 / fs)
    peak = vel = 0.0
    for m in range(d["realizations"]):
        x = drive_multisine(n, k_min, k_max, d["group"], d["seed"], m, 1.0)
        peak = max(peak, float(np.max(np.abs(x))))
        v = np.fft.irfft(1j * w * np.fft.rfft(x), n)
        vel = max(vel, float(np.max(np.abs(v))))
    return peak, vel


def _track_checks(cfg, lim, check, amplitude_checks, kfc_check, src):
    """``fftune track``'s part of the preflight: the task (its travel per repetition and its
    speed against ``limits:``), the initial gains, and the odd-ratio check's sine (amplitude,
    peak velocity, frequency and harmonics below fs/2) when it is enabled."""
    import math

    from fftune.analysis.errors import FftuneError

    tc = cfg["track"]
    task = tc["task"]
    user = cfg["limits"]
    check("track", "track.task.distance_rad", "travel", task["distance_rad"], user["max_amplitude_rad"],
          "rad", "limits.max_amplitude_rad")
    check("track", "track.task.v_max", "speed", task["v_max"], user["max_velocity_rad_s"], "rad/s",
          "limits.max_velocity_rad_s")
    if tc["initial"]["k_fc"] is not None:
        kfc_check("track", "track.initial.k_fc", tc["initial"]["k_fc"])
    c = tc["check"]
    if not c["enabled"]:
        return
    amp, f = c["amplitude_rad"], c["frequency_hz"]
    amplitude_checks("track", "track.check.amplitude_rad", "reference", None, amp, 2 * math.pi * f * amp)
    check("track", "track.check.period_samples", "period N", c["period_samples"], lim.table_capacity,
          "samples", "the drive's period limit 0x2001:5")
    check("track", "track.check.periods", "recorded floats", 2 * c["periods"] * c["period_samples"],
          lim.rec_capacity, "floats", "recorder capacity 0x2020:2, 2 signals")
    fs = lim.fs_hz
    if fs:
        if f >= fs / 2:
            raise FftuneError(f"{src}: key 'track.check.frequency_hz': {f:g} Hz is at or above fs/2 = "
                              f"{fs / 2:g} Hz of the drive; nothing was run")
        cycles = max(1, round(f * c["period_samples"] / fs))
        if 2 * cycles * c["harmonics"] >= c["period_samples"]:
            raise FftuneError(f"{src}: key 'track.check.frequency_hz': harmonic {c['harmonics']} of "
                              f"{cycles * fs / c['period_samples']:g} Hz is at or above fs/2 = {fs / 2:g} Hz "
                              f"of the drive; nothing was run")
        check("track", "track.check.settle_periods", "run length",
              (c["settle_periods"] + c["periods"]) * c["period_samples"] / fs,
              cfg["drive"]["run_timeout_s"], "s", "drive.run_timeout_s")


def preflight(cfg, limits=None, steps=("detect", "quantify", "tune"), capture_mode=None):
    """Check every excitation of the plan against the drive's limits and the
    configuration's ``limits:`` before anything moves.

    Parameters
    ----------
    cfg : dict
        Validated configuration.
    limits : DriveLimits, optional
        :func:`read_drive_limits`; default :func:`config_limits` (what is known without
        the drive; the rest is reported as not checked).
    steps : sequence of str
        The steps that will run (enabled ones only are checked).
    capture_mode : callable, optional
        ``step -> 'raw' | 'stats' | 'both'`` (``Session.capture_mode``); default: the
        step's ``capture`` key, unset counted as raw (the recorder must hold it).

    Returns
    -------
    CheckedPlan

    Raises
    ------
    FftuneError
        The first violation, one line naming the key, the value and the limit.
    """
    import math

    from fftune.analysis.errors import FftuneError
    from fftune.host.config import od_param_high
    from fftune.host.experiments import _cycles, detect_lines
    from fftune.host.ffmodel_tune import check_model_lines, model_plan

    lim = limits or config_limits(cfg)
    src = cfg.get("_source", "config")
    user = cfg["limits"]
    fs = lim.fs_hz
    checks, notes, step_rows = [], [], []
    u_max = lim.u_max_v
    v_limit = min([x for x in (u_max, user["max_rms_v"]) if x is not None], default=None)
    v_name = ("limits.max_rms_v" if user["max_rms_v"] is not None and
              (u_max is None or user["max_rms_v"] <= u_max) else "the drive's u_max")
    a_limit, a_name = user["max_amplitude_rad"], "limits.max_amplitude_rad"
    vel_limit, vel_name = user["max_velocity_rad_s"], "limits.max_velocity_rad_s"
    if cfg["drive"]["controller"].get("u_max") is not None:
        # written before every run: it may lower the drive's output limit, never raise it
        checks.append(Check("drive", "drive.controller.u_max", "output limit",
                            float(cfg["drive"]["controller"]["u_max"]), lim.drive_u_max_v, "V",
                            "the drive's own u_max 0x2000:7; fftune lowers it, never raises it"))

    def mode(step):
        if capture_mode is not None:
            return capture_mode(step)
        return cfg[step].get("capture") or "raw"

    def check(step, key, what, value, limit, unit, limit_name, hard=True, text=None):
        checks.append(Check(step, key, what, float(value), limit, unit, limit_name, hard, text))

    def amplitude_checks(step, key, inject, rms, peak, vel):
        """One level: voltage (plant input) or position (reference) excitation."""
        if inject == "plant_input":
            check(step, key, "rms", rms, v_limit, "V", v_name)
        elif peak is None:      # (the multisine's crest factor needs fs: rms <= peak)
            check(step, key, "rms (peak not known)", rms, a_limit, "rad", a_name)
        else:
            check(step, key, "peak", peak, a_limit, "rad", a_name)
            if vel is not None:
                check(step, key, "peak velocity", vel, vel_limit, "rad/s", vel_name)
        check(step, key, "excitation amplitude", rms if step == "detect" else peak,
              lim.amplitude_high, "", "the range of the drive's object 0x2001:3")

    def run_checks(step, c, n_signals):
        n = c["period_samples"]
        check(step, f"{step}.period_samples", "period N", n, lim.table_capacity, "samples",
              "the drive's period limit 0x2001:5")
        if n_signals:
            check(step, f"{step}.periods", "recorded floats", c["periods"] * n * n_signals,
                  lim.rec_capacity, "floats", f"recorder capacity 0x2020:2, {n_signals} signals")
        if fs:
            check(step, f"{step}.settle_periods", "run length", (c["settle_periods"] + c["periods"]) * n / fs,
                  cfg["drive"]["run_timeout_s"], "s", "drive.run_timeout_s")

    def gain_high(param):
        return (lim.gain_high or {}).get(param) or od_param_high(param)

    def kfc_check(step, key, value):
        high = gain_high("KFC")
        if u_max is not None and u_max <= high:
            check(step, key, "feed-forward", value, u_max, "V", "the drive's u_max",
                  text=f"{value:g} V is above what the drive allows (its output limit u_max = {u_max:g} V)")
        else:
            check(step, key, "feed-forward", value, high, "V", "the range of the drive's object 0x2000:4")

    # the rule of every command that moves an axis: the drive's consumer watches the host
    hb = cfg["drive"].get("heartbeat_ms")
    if not hb:
        raise FftuneError(f"{src}: key 'drive.heartbeat_ms': 0 (no host heartbeat): a drive that "
                          f"moves needs its consumer (0x1016) armed for the host's heartbeat "
                          f"(1 .. {0xFFFF // 4} ms); nothing was run")
    if "track" in steps:
        _track_checks(cfg, lim, check, amplitude_checks, kfc_check, src)
    if not fs and any(cfg[s]["enabled"] for s in steps if s in ("quantify", "tune")):
        notes.append("fs not known (no drive, no drive.fs_hz): quantify's and tune's "
                     "frequencies (DFT grid, harmonics below fs/2) and run lengths not checked")
    d = cfg.get("detect")
    if "detect" in steps and d["enabled"]:
        n = d["period_samples"]
        if fs:
            if d["band_hz"][1] >= fs / 2:
                raise FftuneError(f"{src}: key 'detect.band_hz': {d['band_hz'][1]:g} Hz is at or above "
                                  f"fs/2 = {fs / 2:g} Hz of the drive (lines are never clipped: "
                                  f"lower the band's upper end)")
            k_min, k_max, lines, band = detect_lines(d, fs, src)
            peak1, vel1 = _multisine_peaks(d, fs, k_min, k_max)
            m = mode("detect")
            if m != "raw" and lim.lines_capacity is not None and band.size > lim.lines_capacity:
                if d.get("capture"):
                    check("detect", "detect.band_hz", "statistics lines", band.size, lim.lines_capacity,
                          "lines", "line statistics capacity 0x2040:9")
                else:
                    notes.append(f"detect: the band's {band.size} lines exceed the drive's line "
                                 f"statistics ({lim.lines_capacity}): raw samples")
                    m = "raw"
            sig = 3 if m != "raw" or d["inject"] == "reference" else 2
        else:
            peak1 = vel1 = None
            sig = 3
            notes.append("detect: fs not known (no drive, no drive.fs_hz): the band against "
                         "fs/2, the multisine's peak and peak velocity not checked")
        for i, rms in enumerate(d["rms_levels"]):
            peak = None if peak1 is None else rms * peak1
            vel = None if vel1 is None else rms * vel1
            amplitude_checks("detect", f"detect.rms_levels[{i}]", d["inject"], rms, peak, vel)
            if d["inject"] == "plant_input" and peak is not None and u_max is not None and peak > u_max:
                check("detect", f"detect.rms_levels[{i}]", "multisine peak", peak, u_max, "V",
                      "u_max: the output saturates, detect reports it", hard=False)
        kfc_check("detect", "detect.k_fc", d["k_fc"])
        run_checks("detect", d, sig)     # (line statistics are computed from the recorder)
        runs = len(d["rms_levels"]) * d["realizations"]
        step_rows.append({"step": "detect", "text": (
            f"{runs} runs ({len(d['rms_levels'])} levels x {d['realizations']} realizations), "
            f"N = {d['period_samples']}, {d['settle_periods']} + {d['periods']} periods each"
            + (f", {runs * (d['settle_periods'] + d['periods']) * n / fs:.1f} s of excitation" if fs else ""))})

    q = cfg.get("quantify")
    if "quantify" in steps and q["enabled"]:
        n = q["period_samples"]
        if fs:
            for f in q["frequencies_hz"]:
                _cycles(fs, n, f, f"{src}: key 'quantify.frequencies_hz'")
            top = max(q["frequencies_hz"])
            if top * q["harmonics"] >= fs / 2:
                raise FftuneError(f"{src}: key 'quantify.harmonics': harmonic {q['harmonics']} of "
                                  f"{top:g} Hz is at or above fs/2 = {fs / 2:g} Hz of the drive")
        for i, rms in enumerate(q["rms_levels"]):
            peak = rms * math.sqrt(2)
            amplitude_checks("quantify", f"quantify.rms_levels[{i}]", q["inject"], rms, peak,
                             2 * math.pi * max(q["frequencies_hz"]) * peak)
            if q["inject"] == "plant_input":
                check("quantify", f"quantify.rms_levels[{i}]", "sine peak", peak, u_max, "V",
                      "the drive's u_max (a sine above it is clipped)")
        kfc_check("quantify", "quantify.k_fc", q["k_fc"])
        m = mode("quantify")
        if m != "raw" and q["harmonics"] > STAT_K_MAX and q.get("capture"):
            check("quantify", "quantify.harmonics", "harmonics", q["harmonics"], STAT_K_MAX, "",
                  "the drive's statistics")
        run_checks("quantify", q, 0 if m == "stats" else 4)
        runs = len(q["rms_levels"]) * len(q["frequencies_hz"]) * q["repeats"]
        step_rows.append({"step": "quantify", "text": (
            f"{runs} runs ({len(q['rms_levels'])} levels x {len(q['frequencies_hz'])} frequencies "
            f"x {q['repeats']} repeats), N = {n}, {q['settle_periods']} + {q['periods']} periods each"
            + (f", {runs * (q['settle_periods'] + q['periods']) * n / fs:.1f} s of excitation" if fs else ""))})

    t = cfg.get("tune")
    if "tune" in steps and t["enabled"]:
        n = t["period_samples"]
        # tune.method model (issue 35): the same rules for what it asks for (its sines'
        # amplitudes, the lines it reads, its gains), fftune.host.ffmodel_tune.model_plan
        model = t["method"] == "model"
        if fs:
            if model:
                check_model_lines(t, fs, src)
            else:
                cyc = _cycles(fs, n, t["frequency_hz"], f"{src}: key 'tune.frequency_hz'")
                if cyc * t["harmonics"] * 2 >= n:
                    raise FftuneError(f"{src}: key 'tune.harmonics': harmonic {t['harmonics']} of "
                                      f"{t['frequency_hz']:g} Hz is above fs/2 = {fs / 2:g} Hz")
        if model:
            amplitudes = model_plan(t)["checked"]
        elif t["amplitude_rad"] == "auto":
            amplitudes = [("tune.amplitude_max_rad", t["amplitude_max_rad"])]
        else:
            amplitudes = [("tune.amplitude_rad", t["amplitude_rad"])]
        for key, a in amplitudes:
            amplitude_checks("tune", key, "reference", None, a, 2 * math.pi * t["frequency_hz"] * a)
        amp = max(a for _, a in amplitudes)
        k_hi = t["search"]["k_fc_max"] or t["sweep"]["k_fc_max"]
        kfc_check("tune", "tune.search.k_fc_max" if t["search"]["k_fc_max"] else "tune.sweep.k_fc_max", k_hi)
        if t["viscous"]["enabled"] or model:        # (the model tune always sets K_v)
            check("tune", "tune.viscous.k_v_max", "viscous gain", t["viscous"]["k_v_max"], gain_high("KV"),
                  "V s/rad", "the range of the drive's object 0x2000:5")
            if u_max is not None:
                check("tune", "tune.viscous.k_v_max", "K_v x peak velocity",
                      t["viscous"]["k_v_max"] * 2 * math.pi * t["frequency_hz"] * amp, u_max, "V",
                      "u_max: the feed-forward saturates", hard=False)
        run_checks("tune", t, 0 if mode("tune") == "stats" else 4)
        if model:
            runs = t["model"]["max_experiments"]
        else:
            runs = t["sweep"]["points"] + t["search"]["max_experiments"] + \
                (4 if t["amplitude_rad"] == "auto" else 0) + \
                (t["viscous"]["max_experiments"] + 2 if t["viscous"]["enabled"] else 0) + \
                4       # the uncertainty budget: lag correction (<= 2), second amplitude (<= 2)
        plan = [StepPlan("tune", runs, runs * (t["settle_periods"] + t["periods"]) * n / fs, 0, None)] \
            if fs else []
        if model:
            top = dict(amplitudes).get("tune.amplitude_max_rad")
            what = (f"tune.method model ({', '.join(t['terms'])}), amplitude {amplitudes[0][1]:g} rad"
                    + (f" (doubled up to {top:g} rad)" if top else ""))
        else:
            what = (f"amplitude {t['amplitude_rad'] if t['amplitude_rad'] == 'auto' else f'{amp:g} rad'}"
                    + (f" (probes up to {amp:g} rad)" if t["amplitude_rad"] == "auto" else ""))
        step_rows.append({"step": "tune", "text": (
            f"at most {runs} runs at {t['frequency_hz']:g} Hz, {what}, K_fc 0 .. {k_hi:g} V"
            + (f", {plan[0].excitation_s:.1f} s of excitation at most" if plan else ""))})

    for c in checks:
        if c.hard and c.ok is False and c.text:
            raise FftuneError(f"{src}: key '{c.key}': {c.text}; nothing was run")
        if c.hard and c.ok is False:
            what = f"{c.what} " if c.what not in ("rms", "peak") else ""
            raise FftuneError(f"{src}: key '{c.key}': {what}{c.value:.4g} {c.unit}"
                              f"{' rms' if c.what == 'rms' else ' peak' if c.what == 'peak' else ''} "
                              f"is above {c.limit:.4g} {c.unit} ({c.limit_name}); nothing was run"
                              .replace("  ", " "))
    return CheckedPlan(limits=lim, checks=checks, steps=step_rows, notes=notes)
