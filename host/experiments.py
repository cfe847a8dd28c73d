"""The experiments: detect, quantify, tune, each a function of a drive and a configuration.

Each experiment plans its runs, executes them one at a time through a :class:`Session`
(which captures every run as it arrives and skips runs already captured with the same
request, so an interrupted experiment resumes), and analyses them with the ``analysis``
package. Results are plain dicts of numbers (YAML-ready) plus the analysis objects the
figures need.

The drive is anything with the :class:`fftune.host.drive.DriveClient` interface: the CANopen
client, or :class:`fftune.host.canlog.ReplayDrive` serving the runs of a CAN log.
"""
import math
import time

import numpy as np

from fftune.analysis.hosidf import hosidf as _hosidf_estimate  # (fftune.analysis.hosidf is the function)
from fftune.analysis import stats as _stats
from fftune.analysis.stats import harmonic_stats, hosidf_from_stats
from fftune.analysis import tuning as _tuning
from fftune.analysis.errors import FftuneError
from fftune.analysis.multisine import drive_lines, drive_multisine
from fftune.host.captures import CaptureStore
from fftune.host.odmap import EXC_KINDS, INJECT


def _f(x):
    """A YAML-friendly float (None for NaN/inf)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


class Session:
    """One drive, one configuration, one output directory.

    Parameters
    ----------
    drive : DriveClient-like
    cfg : dict
        Validated configuration (:func:`fftune.host.config.load_config`).
    out_dir : str
        Output directory (captures go to ``out_dir/captures``).
    log : callable
        Receives progress lines (default: print).
    """

    def __init__(self, drive, cfg, out_dir, log=print):
        self.drive, self.cfg, self.out_dir, self.log = drive, cfg, out_dir, log
        self.store = CaptureStore(out_dir)
        self.identity = drive.identity()
        self.truth = drive.plant_truth()
        self.fs_hz = float(drive.get("fs"))
        expected = cfg["drive"].get("fs_hz")
        if expected is not None and abs(expected - self.fs_hz) > 1e-6 * expected:
            raise FftuneError(f"{cfg.get('_source', 'config')}: key 'drive.fs_hz': the drive runs at "
                              f"{self.fs_hz:g} Hz (object 'Controller rate'), the configuration expects "
                              f"{expected:g} Hz")
        self.counts = {"measured": 0, "resumed": 0}
        ctl = {k: v for k, v in cfg["drive"]["controller"].items() if v is not None}
        self.controller = {"tau_d" if k == "tau_d" else k: v for k, v in ctl.items()}

    def capture_mode(self, step):
        """'raw', 'stats' or 'both' for ``step`` (key ``<step>.capture``; unset: statistics
        on a real drive or a simulated bus of limited bitrate, raw samples otherwise)."""
        mode = self.cfg.get(step, {}).get("capture")
        if mode:
            return mode
        bus_model = (self.cfg.get("sim") or {}).get("bitrate")
        return "stats" if (self.truth is None or bus_model) else "raw"

    def run(self, experiment, key, request, level_index=0, realization=0, extra_signals=None,
            stats=None, signals=None, lines=None):
        """The run ``key`` of ``experiment`` with drive parameters ``request``, measured or
        loaded from an earlier capture with the same request. ``extra_signals`` (name ->
        array of the record's length, e.g. the excitation the drive generated but does
        not record) are stored in the capture beside the recorded ones, as float32.
        ``stats`` (``fftune.host.drive.stats_parameters``) asks the drive for its line
        statistics when the step's capture mode is 'stats' or 'both', ``lines`` (DFT
        bins) its multisine line statistics. ``signals``: the
        recorder signals to upload (default: the drive client's), only what the analysis
        reads: every recorded float crosses the bus."""
        request = dict(self.controller, **request)
        rec = self.store.load(key, request)
        if rec is not None:
            self.counts["resumed"] += 1
            return rec
        capture = self.capture_mode(experiment) if (stats or lines is not None) else "raw"
        kwargs = {}
        if capture != "raw":
            kwargs = {"capture": capture, "stats": stats} if stats else {"capture": capture, "lines": lines}
        if signals is not None:
            kwargs["signals"] = tuple(signals)
        rec = self.drive.run(request, desc=key, **kwargs)
        for name, values in (extra_signals or {}).items():
            rec.signals[name] = np.asarray(values, dtype=np.float32).astype(np.float64)
        # the configuration as given (tune may run at a lower frequency than configured: its
        # captures still record the configuration a replay starts from)
        self.store.save(key, rec, experiment=experiment, request=request,
                        config=getattr(self, "cfg_of_record", None) or self.cfg,
                        identity=self.identity, level_index=level_index, realization=realization)
        self.counts["measured"] += 1
        return rec


def _cycles(fs, n, f_hz, where):
    c = f_hz * n / fs
    if abs(c - round(c)) > 1e-9 * max(1.0, c) or round(c) < 1:
        raise FftuneError(f"{where}: {f_hz:g} Hz is not on the DFT grid fs/N = {fs:g}/{n} = "
                          f"{fs / n:g} Hz of the drive")
    if 2 * round(c) >= n:
        raise FftuneError(f"{where}: {f_hz:g} Hz is above fs/2")
    return int(round(c))


def sine_request(*, inject, amplitude_peak, n, cycles, settle, periods, kfc, kv):
    return {"exc_kind": EXC_KINDS["sine"], "exc_inject": INJECT[inject],
            "exc_amplitude": float(amplitude_peak), "exc_offset": 0.0, "exc_period": int(n),
            "exc_sine_cycles": int(cycles), "exc_settle_periods": int(settle),
            "exc_record_periods": int(periods), "kfc": float(kfc), "kv": float(kv)}


def _blocks(x, n):
    return np.asarray(x).reshape(-1, n)


# ---------------------------------------------------------------------------------------
# detect
# ---------------------------------------------------------------------------------------
def _saturation_fraction(u, u_max):
    """Fraction of the plant-input samples at the drive's output limit (|u| >= u_max,
    float32 tolerance); None when u_max is unknown."""
    if u_max is None or not u_max > 0:
        return None
    u = np.abs(np.asarray(u, dtype=float))
    return float(np.mean(u >= u_max * (1 - 1e-6)))


def _run_u_max(session, rec):
    """u_max in V: read back with the run (its parameters), else the configuration's
    controller.u_max, else None (the saturation fraction is then not evaluated)."""
    value = (getattr(rec, "parameters", None) or {}).get("u_max")
    if value is None:
        value = session.controller.get("u_max")
    return None if value is None else float(value)


def _run_setting(session, rec, name):
    """A drive setting during a run: read back with the run's parameters, else the
    configuration's controller value, else None."""
    value = (getattr(rec, "parameters", None) or {}).get(name)
    if value is None:
        value = session.controller.get(name)
    return None if value is None else float(value)


def drive_settings(session):
    """The drive's settings that change the tune criterion (results.yaml tune.drive_settings):
    the controller gains, the feed-forward sign's smoothing width fc_smooth and u_max, read
    from the drive (a setting the drive does not have: None)."""
    out = {}
    for name in ("kp", "kd", "tau_d", "fc_smooth", "u_max"):
        try:
            out[name] = _f(session.drive.get(name))
        except (FftuneError, KeyError, AttributeError, TypeError, ValueError):
            out[name] = _f(session.controller.get(name))
    return out


def detect_analysis(u_lv, y_lv, r_lv, *, fs, excited_bins, rms_levels, unit="V",
                    u_max=None, y_quantisation_step=None, moments_lv=None, n_period=None,
                    saturation_lv=None):
    """Closed-loop and plant-referred detection at each level, with the verdict.

    Parameters
    ----------
    u_lv, y_lv, r_lv : list of ndarray (M, P, N)
        Plant input (after saturation), motor angle and the excitation, per level
        (None with ``moments_lv``).
    fs : float
        Sample rate (Hz).
    excited_bins : ndarray of int
        The design grid.
    rms_levels : sequence of float
        Requested rms per level (``unit``).
    u_max : float, optional
        Drive output limit (V) for the saturation fraction.
    y_quantisation_step : float, optional
        Encoder step (rad); estimated from the recorded angle when None (not with
        ``moments_lv``: no samples).
    moments_lv : list of fftune.analysis.bla.LineMoments, optional
        Instead of the samples: per level the line moments of the M realizations (the
        drive's line statistics, :func:`fftune.analysis.stats.line_moments`), with the
        reference; ``n_period`` (N) is then needed.
    saturation_lv : list of float, optional
        With ``moments_lv``: per level the fraction of samples at u_max, if the drive
        counted it (None: not evaluated).

    Returns
    -------
    results : dict
    levels : fftune.analysis.bla.BLALevels
    """
    # here, not at the top: a tune-only session (and the emulated test guest) skips
    # loading the BLA module and scipy.stats
    from fftune.analysis.bla import bla_levels, estimate_quantisation_step, level_verdict

    q_note = None
    if moments_lv is not None:
        if y_quantisation_step is None:
            q_note = ("not known: the line statistics keep no samples to estimate it from "
                      "(set detect.encoder_step_rad)")
        levels = _bla_levels_from_moments(moments_lv, n_period=n_period, fs=fs,
                                          excited_bins=excited_bins,
                                          y_quantisation_step=y_quantisation_step)
        n_real, n_per = moments_lv[0].U.shape[0], moments_lv[0].n_periods
    else:
        if y_quantisation_step is None:
            y_quantisation_step = estimate_quantisation_step(np.concatenate([y.ravel() for y in y_lv]))
            q_note = "estimated from the recorded motor angle" if y_quantisation_step else \
                "no quantisation step found in the recorded angle (ideal or fine encoder)"
        levels = bla_levels(u_lv, y_lv, r_lv, fs=fs, settle_periods=0, excited_bins=excited_bins,
                            warn_transient=False, y_quantisation_step=y_quantisation_step)
        n_real, n_per = u_lv[0].shape[0], u_lv[0].shape[1]
    per_level = []
    for i, (rms, res) in enumerate(zip(rms_levels, levels.results)):
        if moments_lv is None:
            sat = _saturation_fraction(u_lv[i], u_max)
        else:
            sat = None if saturation_lv is None else saturation_lv[i]
        v = level_verdict(res.summary, sat, f"level {i} ({rms:g} {unit} rms)")
        per_level.append({
            "rms_requested": _f(rms),
            "saturation_fraction": _f(sat),
            "verdict": v["text"], "causes": v["causes"],
            "summary_db": {k: (_f(v) if isinstance(v, float) else v)
                           for k, v in res.summary.items()},
            "notes": list(res.notes),
        })
    names = [f"{rms:g} {unit} rms" for rms in rms_levels]

    def where(cause):
        return [names[i] for i, lv in enumerate(per_level) if cause in lv["causes"]]

    parts = []
    parity = levels.results[0].summary.get("parity_classifiable")
    if parity:
        for kind in ("odd", "even"):
            at = where(f"plant {kind} nonlinearity")
            parts.append(f"{kind} nonlinearity in the plant at {', '.join(at)}" if at
                         else f"no {kind} nonlinearity in the plant")
    else:
        at = where("plant nonlinearity (parity not classifiable with this grid)")
        parts.append((f"plant nonlinearity at {', '.join(at)}" if at else
                      "no plant nonlinearity") + " (odd/even not classifiable with this grid)")
    for cause in ("drive output saturation", "quantisation floor",
                  "loop nonlinearity outside the plant", "nonlinear distortion (excited lines)",
                  "unmeasured inputs", "unmeasured inputs or a scale-free nonlinearity",
                  "cannot tell"):
        at = where(cause)
        if at:
            parts.append(f"{cause} at {', '.join(at)}")
    lin = where("linear")
    if lin:
        parts.append(f"linear at {', '.join(lin)}")
    g = levels.G
    spread_db = float(np.max(20 * np.log10(np.abs(g).max(0) / np.abs(g).min(0)))) if len(g) > 1 else 0.0
    results = {
        "realizations": int(n_real), "periods": int(n_per),
        "excited_lines": int(len(excited_bins)), "grid": levels.results[0].grid,
        "u_max_v": _f(u_max),
        "encoder_step_rad": _f(y_quantisation_step), "encoder_step_source": q_note or "given",
        "levels": per_level,
        "bla_max_change_over_levels_db": _f(spread_db),
        "verdict": "; ".join(parts),
    }
    return results, levels


def detect_lines(c, fs, src="config"):
    """The detect step's DFT lines at the drive's rate ``fs`` (Hz): k_min, k_max of the
    band, the design (:func:`fftune.analysis.multisine.drive_lines`) and the lines of the
    drive's line statistics: every line from the lowest to the highest excited one (the
    excited lines and the detection lines between them)."""
    n = c["period_samples"]
    k_min = max(1, int(math.ceil(c["band_hz"][0] * n / fs - 1e-9)))
    k_max = int(math.floor(c["band_hz"][1] * n / fs + 1e-9))
    if k_max >= n // 2:     # never clipped: the verdict would be of another band
        raise FftuneError(f"{src}: key 'detect.band_hz': {c['band_hz'][1]:g} Hz is at or above "
                          f"fs/2 = {fs / 2:g} Hz of the drive")
    if k_min > k_max:
        raise FftuneError(f"{src}: key 'detect.band_hz': no DFT line of fs/N = {fs / n:g} Hz "
                          f"in {c['band_hz']}")
    lines = drive_lines(n, k_min, k_max, c["group"], c["seed"])
    if len(lines.excited) == 0:
        raise FftuneError(f"{src}: key 'detect.band_hz': no excited line in the band")
    return k_min, k_max, lines, np.arange(lines.excited[0], lines.excited[-1] + 1)


def _bla_levels_from_moments(moments_lv, *, n_period, fs, excited_bins, y_quantisation_step):
    """:class:`fftune.analysis.bla.BLALevels` from per-level line moments."""
    from fftune.analysis.bla import BLALevels, robust_bla_moments

    if not n_period:
        raise FftuneError("detect from line statistics: the period N is needed")
    n = int(n_period)
    results, rms = [], []
    for mom in moments_lv:
        # Floors the noise estimate cannot see (the same error in every period):
        # - the float32 record: the rounding of y, from a bound of its amplitude (the sum of
        #   its line amplitudes; the position offset is not in the statistics);
        # - the drive's float32 FFT of period 0 (the base of every mean): rms error per bin
        #   about eps sqrt(log2 N) ||y||_2, ||y||_2^2 = (2/N) sum |Y_k|^2 over the lines;
        #   4x that, as the same per-line floor (the uniform rounding floor of
        #   robust_bla_spectra: y_rounding = error x sqrt(3 / N)).
        eps = 2.0 ** -24
        y_bound = float(np.max(np.sum(np.abs(mom.Y), axis=1))) * 2.0 / n
        y_norm = float(np.sqrt(np.max((2.0 / n) * np.sum(np.abs(mom.Y) ** 2, axis=1))))
        fft_error = 4.0 * eps * np.sqrt(np.log2(n)) * y_norm
        y_rounding = float(np.hypot(y_bound * eps, fft_error * np.sqrt(3.0 / n)))
        results.append(robust_bla_moments(mom, n_period=n, fs=fs, excited_bins=excited_bins,
                                          y_quantisation_step=y_quantisation_step,
                                          y_rounding=y_rounding))
        # Parseval over the lines (the excitation has no DC and no Nyquist line)
        rms.append(float(np.sqrt(np.mean(2.0 * np.sum(np.abs(mom.R) ** 2, axis=1))) / n))
    return BLALevels(rms=np.array(rms), results=results, freq=results[0].freq,
                     G=np.stack([res.G for res in results]))


def detect(session):
    """Random odd multisines at L rms levels, M realizations; known-reference robust BLA.

    Returns
    -------
    results : dict
        Per level: rms, saturation fraction, summary (``fftune.analysis.bla``), verdict
        naming the cause (:func:`detect_analysis`); the overall verdict.
    levels : fftune.analysis.bla.BLALevels
    """
    c = session.cfg["detect"]
    fs, n = session.fs_hz, c["period_samples"]
    k_min, k_max, lines, band = detect_lines(c, fs, session.cfg.get("_source", "config"))
    capture = session.capture_mode("detect")
    capture_note = None
    if capture != "raw" and c.get("capture") is None:
        # chosen by default, not asked for: raw samples where the drive cannot hold the lines
        try:
            cap = int(session.drive.get("stat_lines_cap"))
        except (FftuneError, KeyError, AttributeError):
            cap = None
        if cap is None or band.size > cap:
            capture_note = (f"raw samples: the band's {band.size} lines exceed the "
                            f"{cap} lines the drive's line statistics hold (object 0x2040:9)"
                            if cap is not None else
                            "raw samples: the drive has no line statistics (object 0x2040:9)")
            session.log(f"detect: {capture_note}")
            capture = "raw"
    u_lv, y_lv, r_lv, mom_lv, sat_lv = [], [], [], [], []
    # what the robust BLA reads (the excitation added at the plant input is regenerated
    # here, not recorded): 2 of the 4 signals, half the upload
    detect_signals = ("plant_input", "motor_angle") + (("reference",) if c["inject"] == "reference" else ())
    u_max = None
    for li, rms in enumerate(c["rms_levels"]):
        u_m, y_m, r_m, st_m, ref_m = [], [], [], [], []
        for m in range(c["realizations"]):
            req = {"exc_kind": EXC_KINDS["multisine"], "exc_inject": INJECT[c["inject"]],
                   "exc_amplitude": float(rms), "exc_offset": 0.0, "exc_period": n,
                   "exc_settle_periods": c["settle_periods"], "exc_record_periods": c["periods"],
                   "ms_k_min": k_min, "ms_k_max": k_max, "ms_group": c["group"],
                   "ms_seed": c["seed"], "ms_realization": m, "kfc": c["k_fc"], "kv": c["k_v"]}
            # The drive does not record the disturbance it adds at the plant input; it is the
            # same design (docs/multisine.md), regenerated here: stored with a raw capture as
            # 'excitation' (so that `fftune analyze` repeats the known-reference estimate),
            # and the reference of the line statistics.
            one = drive_multisine(n, k_min, k_max, c["group"], c["seed"], m, rms)
            extra = None
            if c["inject"] == "plant_input" and capture != "stats":
                extra = {"excitation": np.tile(one, c["periods"])}
            rec = session.run("detect", f"detect-L{li:02d}-M{m:02d}", req, level_index=li,
                              realization=m, extra_signals=extra, signals=detect_signals,
                              lines=band if capture != "raw" else None)
            u_max = _run_u_max(session, rec)
            if capture != "raw":
                if rec.line_stats is None:
                    raise FftuneError(f"detect run L{li:02d} M{m:02d}: capture {capture} but no line "
                                      f"statistics from the drive (nor in its capture)")
                st_m.append(rec.line_stats)
                ref_m.append(np.fft.rfft(np.asarray(one, dtype=np.float64))[band])
            if capture != "stats":
                u_m.append(_blocks(rec.signals["plant_input"], n))
                y_m.append(_blocks(rec.signals["motor_angle"], n))
                r_name = "reference" if c["inject"] == "reference" else "excitation"
                r_m.append(_blocks(rec.signals[r_name], n))
        if capture != "stats":
            u_lv.append(np.stack(u_m))
            y_lv.append(np.stack(y_m))
            r_lv.append(np.stack(r_m))
        if capture != "raw":
            mom_lv.append(_stats.line_moments(st_m, reference=np.stack(ref_m)))
            counts = [st.saturated_samples for st in st_m]
            sat_lv.append(None if any(k is None for k in counts) else
                          sum(counts) / float(len(counts) * c["periods"] * n))
    kwargs = dict(fs=fs, excited_bins=lines.excited, rms_levels=c["rms_levels"],
                  unit="V" if c["inject"] == "plant_input" else "rad", u_max=u_max,
                  y_quantisation_step=c.get("encoder_step_rad"))
    if capture == "stats":
        results, levels = detect_analysis(None, None, None, moments_lv=mom_lv, n_period=n,
                                          saturation_lv=sat_lv, **kwargs)
    else:
        results, levels = detect_analysis(u_lv, y_lv, r_lv, **kwargs)
    if capture == "both":
        # the audit: the drive's float32 statistics against the samples' float64 estimate
        stats_res, from_stats = detect_analysis(None, None, None, moments_lv=mom_lv, n_period=n,
                                                saturation_lv=sat_lv, **kwargs)
        results["stats_vs_raw"] = dict(
            _stats_vs_raw(levels, from_stats),
            same_causes=all(a["causes"] == b["causes"] for a, b in
                            zip(results["levels"], stats_res["levels"])),
            max_abs_diff_saturation_fraction=max(
                (abs(a["saturation_fraction"] - b["saturation_fraction"]) for a, b in
                 zip(results["levels"], stats_res["levels"])
                 if a["saturation_fraction"] is not None and b["saturation_fraction"] is not None),
                default=None))
    head = {"inject": c["inject"], "fs_hz": fs, "period_samples": n, "k_min": k_min,
            "k_max": k_max, "capture": capture}
    if capture_note:
        head["capture_note"] = capture_note
    return dict(head, **results), levels


def _stats_vs_raw(raw, stats):
    """Largest relative differences over levels between the estimate from the drive's line
    statistics and from the samples: G (re max |G|), var_total, var_noise (re max of each)."""
    out = {}
    for name in ("G", "var_total", "var_noise"):
        worst = 0.0
        for a, b in zip(raw.results, stats.results):
            x, y = getattr(a, name), getattr(b, name)
            if x is None or y is None:
                continue
            worst = max(worst, float(np.max(np.abs(np.asarray(y) - x)) / max(np.max(np.abs(x)), 1e-300)))
        out[f"max_rel_diff_{name}"] = worst
    return out


# ---------------------------------------------------------------------------------------
# quantify
# ---------------------------------------------------------------------------------------
def quantify(session):
    """HOSIDFs vs frequency and amplitude, ``repeats`` sine experiments each.

    Returns
    -------
    results : dict
    hos : fftune.analysis.hosidf.HosidfResult, leading axes (amplitude, frequency)
    """
    c = session.cfg["quantify"]
    fs, n = session.fs_hz, c["period_samples"]
    src = session.cfg.get("_source", "config")
    cycles = [_cycles(fs, n, f, f"{src}: key 'quantify.frequencies_hz'") for f in c["frequencies_hz"]]
    if max(cycles) * c["harmonics"] * 2 >= n:
        raise FftuneError(f"{src}: key 'quantify.harmonics': {c['harmonics']} x "
                          f"{max(c['frequencies_hz']):g} Hz is above fs/2 = {fs / 2:g} Hz")
    in_name = "reference" if c["inject"] == "reference" else "plant_input"
    shape = (len(c["rms_levels"]), len(cycles), c["repeats"])
    want = {"harmonics": c["harmonics"], "signals": [in_name, "motor_angle"]}
    recs = np.empty(shape, dtype=object)
    for ai, rms in enumerate(c["rms_levels"]):
        for fi, cyc in enumerate(cycles):
            for rep in range(c["repeats"]):
                req = sine_request(inject=c["inject"], amplitude_peak=rms * math.sqrt(2), n=n,
                                   cycles=cyc, settle=c["settle_periods"], periods=c["periods"],
                                   kfc=c["k_fc"], kv=c["k_v"])
                recs[ai, fi, rep] = session.run("quantify", f"quantify-A{ai:02d}-F{fi:03d}-R{rep:02d}",
                                                req, level_index=ai, realization=rep, stats=want)
    f0 = np.broadcast_to(np.asarray(c["frequencies_hz"])[None, :], shape[:2])
    if any(r.stats is not None for r in recs.flat):
        # the drive's line statistics (runs resumed from raw captures: the same numbers
        # from their samples, fftune.analysis.stats.harmonic_stats)
        st = np.empty(shape, dtype=object)
        for idx, r in np.ndenumerate(recs):
            st[idx] = r.stats if r.stats is not None else harmonic_stats(
                {k: r.signals[k] for k in want["signals"]}, n=n, cycles=cycles[idx[1]],
                harmonics=c["harmonics"])
        cyc_arr = np.broadcast_to(np.asarray(cycles)[None, :], shape[:2])
        hos = hosidf_from_stats(st, st, u_name=in_name, y_name="motor_angle", fs=fs, n=n,
                                cycles=cyc_arr, n_harmonics=c["harmonics"])
    else:
        U = np.stack([_blocks(r.signals[in_name], n) for r in recs.flat]).reshape(shape + (-1, n))
        Y = np.stack([_blocks(r.signals["motor_angle"], n) for r in recs.flat]).reshape(shape + (-1, n))
        hos = _hosidf_estimate(U, Y, fs=fs, n_harmonics=c["harmonics"], f0=f0)
    # the one definition of the harmonic levels (results.yaml, quantify and tune alike)
    odd_rel = np.asarray(_tuning.odd_ratio(hos.H, _tuning.harmonic_orders(c["harmonics"], "odd")))
    even_rel = (np.asarray(_tuning.odd_ratio(hos.H, _tuning.harmonic_orders(c["harmonics"], "even")))
                if c["harmonics"] >= 2 else np.zeros(hos.H.shape[:-1]))
    results = {
        "inject": c["inject"], "input_signal": in_name, "output_signal": "motor_angle",
        "frequencies_hz": [_f(f) for f in c["frequencies_hz"]],
        "rms_levels": [_f(a) for a in c["rms_levels"]], "repeats": c["repeats"],
        "level_definition": _tuning.ODD_LEVEL_DEFINITION + "; even: the same over k = 2, 4, .. K",
        "odd_relative_level": [[_f(v) for v in row] for row in odd_rel],
        "even_relative_level": [[_f(v) for v in row] for row in even_rel],
        "max_odd_relative_level": _f(np.max(odd_rel)),
        "max_even_relative_level": _f(np.max(even_rel)),
    }
    q = session.cfg["detect"].get("encoder_step_rad")
    if q and c["harmonics"] >= 2:
        # one encoder count in one sample of one block, relative to the output's fundamental
        # (|H_1| x amplitude), averaged over the repeats' blocks: what "0" means
        y1 = np.abs(hos.H[..., 0]) * np.asarray(hos.amplitude)
        with np.errstate(divide="ignore"):
            floor = 2.0 * q / (n * c["periods"] * c["repeats"] * y1)
        results["even_relative_level_floor"] = [[_f(v) for v in row] for row in floor]
    if np.any(even_rel == 0.0):
        results["even_relative_level_note"] = (
            "an exact 0.0 is no measurement of zero distortion but exact half-wave symmetry: the "
            "recorded angle satisfies y(t + T/2) = -y(t) to the last bit (a symmetric, "
            "deterministic plant in steady state, quantised by the encoder), so every even DFT "
            "line is exactly zero: the even level is below the resolution of the record "
            "(even_relative_level_floor: one encoder count in one sample)")
    return results, hos


# ---------------------------------------------------------------------------------------
# tune
# ---------------------------------------------------------------------------------------
class _TuneProbe:
    """One closed-loop sine experiment at (K_fc, K_v, amplitude): HOSIDF reference -> motor
    angle per recorded period, odd-harmonic objective, rms tracking error, and the checks
    of every tune experiment: the share of samples at u_max and the motion (|H_1|)."""

    def __init__(self, session):
        self.s = session
        c = session.cfg["tune"]
        self.c = c
        src = session.cfg.get("_source", "config")
        self.n = c["period_samples"]
        self.cycles = _cycles(session.fs_hz, self.n, c["frequency_hz"], f"{src}: key 'tune.frequency_hz'")
        if self.cycles * c["harmonics"] * 2 >= self.n:
            raise FftuneError(f"{src}: key 'tune.harmonics': harmonic {c['harmonics']} of "
                              f"{c['frequency_hz']:g} Hz is above fs/2 = {session.fs_hz / 2:g} Hz")
        self.harmonics = _tuning.harmonic_orders(c["harmonics"])
        self.amplitude = c["amplitude_rad"] if c["amplitude_rad"] != "auto" else None
        self.points = {}
        # what the drive accumulates with capture stats/both: the HOSIDF lines of the
        # reference, the angle and the plant input (its fundamental: the viscous estimate),
        # the power of the tracking error and of the plant input (saturation)
        self.stats_request = {"harmonics": c["harmonics"],
                              "signals": ["reference", "motor_angle", "plant_input"],
                              "power": ["error", "plant_input"]}
        if session.capture_mode("tune") != "raw" and c["harmonics"] > _stats.STAT_K_MAX:
            raise FftuneError(f"{src}: key 'tune.harmonics': {c['harmonics']} harmonics with "
                              f"tune.capture {session.capture_mode('tune')}: the drive's statistics "
                              f"hold at most {_stats.STAT_K_MAX} (set tune.capture: raw or "
                              f"tune.harmonics <= {_stats.STAT_K_MAX})")

    def measure(self, tag, kfc, kv=0.0, amplitude=None, repeat=False):
        """One experiment; ``repeat``: measured again even when the same (K_fc, K_v,
        amplitude) was measured before (a repeated point: did the plant change?)."""
        amplitude = self.amplitude if amplitude is None else amplitude
        key = f"tune-{tag}-kfc{kfc:.9g}-kv{kv:.9g}"
        if getattr(self.s, "tune_f0", self.c["frequency_hz"]) != self.c["frequency_hz"]:
            key += f"-f{self.c['frequency_hz']:.6g}"      # a lower frequency than configured
        if amplitude != self.c["amplitude_rad"]:
            key += f"-a{amplitude:.6g}"
        if repeat:
            key += "-repeat"
        c = self.c
        cache = (round(float(np.float32(kfc)), 12), round(float(np.float32(kv)), 12), float(amplitude))
        if cache in self.points and not repeat:   # the same experiment under another tag
            return self.points[cache]
        req = sine_request(inject="reference", amplitude_peak=amplitude, n=self.n,
                           cycles=self.cycles, settle=c["settle_periods"], periods=c["periods"],
                           kfc=kfc, kv=kv)
        rec = self.s.run("tune", key, req, stats=self.stats_request)
        u_max = _run_u_max(self.s, rec)
        sat = u_rms_re_max = u_over_y = lines = None
        if rec.stats is not None:
            # the drive's line statistics: the mean HOSIDFs and their period-to-period
            # variance (the search propagates it; fftune.analysis.tuning.KfcSearch.tell_moments)
            H, H_var, n_periods = _stats.period_hosidf_moments(
                rec.stats, u_name="reference", y_name="motor_angle", n_harmonics=c["harmonics"])
            H_periods = None
            rms_error = rec.stats.rms("error")
            if "plant_input" in rec.stats.mean:
                lines = (np.asarray(rec.stats.mean["plant_input"]), np.asarray(rec.stats.mean["motor_angle"]))
            if "plant_input" in rec.stats.mean and "plant_input" in rec.stats.power_msq:
                y1 = rec.stats.mean["motor_angle"][0]
                u_over_y = complex(rec.stats.mean["plant_input"][0] / y1) if abs(y1) > 0 else None
                if u_max:
                    u_rms_re_max = rec.stats.rms("plant_input") / u_max
        else:
            # each recorded period as a repeat: H_repeats are the per-period HOSIDFs
            r = _blocks(rec.signals["reference"], self.n)[:, None, :]
            y = _blocks(rec.signals["motor_angle"], self.n)[:, None, :]
            hos = _hosidf_estimate(r, y, fs=self.s.fs_hz, n_harmonics=c["harmonics"],
                                   f0=c["frequency_hz"])
            H, H_periods, H_var, n_periods = hos.H, hos.H_repeats, None, y.shape[0]
            rms_error = float(np.sqrt(np.mean(rec.signals["error"] ** 2)))
            if "plant_input" in rec.signals:
                sat = _saturation_fraction(rec.signals["plant_input"], u_max)
                bins = self.cycles * np.arange(1, c["harmonics"] + 1)
                lines = (np.fft.fft(_blocks(rec.signals["plant_input"], self.n).mean(axis=0))[bins],
                         np.fft.fft(_blocks(rec.signals["motor_angle"], self.n).mean(axis=0))[bins])
                u1, y1 = lines[0][0], lines[1][0]
                u_over_y = complex(u1 / y1) if abs(y1) > 0 else None
        if "motor_angle" in rec.signals:
            # measurement noise of the angle: its spread over the recorded periods
            y_p = _blocks(rec.signals["motor_angle"], self.n)
            noise_rad = float(np.sqrt(np.sum((y_p - y_p.mean(axis=0)) ** 2) / (y_p.size - self.n)))
        else:
            # statistics only: from the line variances (an upper bound, see the check in tune)
            noise_rad = _stats.period_noise_rms(rec.stats, "motor_angle", self.n)
        h1 = float(np.abs(H[0]))
        check = _tuning.check_experiment(h1, saturated_fraction=sat, u_rms_re_max=u_rms_re_max,
                                         amplitude_rad=float(amplitude), u_max_v=u_max)
        moving = h1 > 1e-6 and check["cause"] != "no motion"
        point = {
            "kfc": float(np.float32(kfc)), "kv": float(np.float32(kv)), "amplitude": float(amplitude),
            "H": H, "H_periods": H_periods, "H_var": H_var, "n_periods": n_periods,
            "ratio": float(_tuning.odd_ratio(H, self.harmonics)) if moving else math.inf,
            "rms_error": rms_error,
            "angle_noise_rad": noise_rad,
            "u_over_y": u_over_y,
            "lines": lines,          # DFT lines k = 1 .. K of the plant input and the angle
            "check": check,
            "record": rec,
            # the motor's lag behind the reference at the fundamental (deg; < 0: a lead)
            "lag_deg": float(-np.degrees(np.angle(H[0]))) if h1 > 0 else math.nan,
            # the drive's sign smoothing during this run (read back with the run's parameters)
            "fc_smooth": _run_setting(self.s, rec, "fc_smooth"),
        }
        if not repeat:
            self.points[cache] = point
        self.s.tune_experiments = getattr(self.s, "tune_experiments", 0) + 1
        return point

    def search_point(self, p):
        """The :class:`fftune.analysis.tuning.SearchPoint` of a measured experiment."""
        if p["H_periods"] is not None:
            return _tuning.make_point(p["kfc"], H_periods=p["H_periods"], harmonics=self.harmonics)
        return _tuning.make_point(p["kfc"], H=p["H"], H_var=p["H_var"], n_periods=p["n_periods"],
                                  harmonics=self.harmonics)


def _viscous_estimate(probe, p):
    """K_v (V s/rad) of the plant from one experiment's harmonics, and the share of the
    viscous term in the plant input's fundamental; (0, 0) when it cannot be read."""
    if p["lines"] is None or p["check"]["cause"] is not None or not math.isfinite(p["ratio"]):
        return 0.0, 0.0
    U, Y = p["lines"]
    omega = 2 * math.pi * probe.c["frequency_hz"]
    kv, _ = _tuning.viscous_from_harmonics(U, Y, omega, probe.n, probe.cycles)
    if not (math.isfinite(kv) and kv > 0):
        return 0.0, 0.0
    return float(kv), float(kv * omega * abs(Y[0]) / max(abs(U[0]), 1e-300))


def _check_block(p):
    """The per-experiment checks for results.yaml."""
    ck = p["check"]
    return {"saturated_fraction": _f(ck["saturated_fraction"]), "saturation_basis": ck["saturation_basis"],
            "motion_h1": _f(ck["motion_h1"]), "cause": ck["cause"]}


# Out of stick-slip: at K_fc = 0 the motor follows the sine (|H_1| >= 0.5: a stuck motor has
# |H_1| ~ 0; a loop with much viscous or load-side damping follows with |H_1| 0.7 at every
# amplitude, so a higher limit only climbs into saturation) and the odd harmonics stay
# below 5 % of it; below that the odd HOSIDF phases rotate with K_fc.
AUTO_AMPLITUDE_MAX_RATIO = 0.05
AUTO_AMPLITUDE_MIN_H1 = 0.5
# Angle noise dithers the friction and moves the objective's zero: at 6 % of the amplitude
# K_fc* came out 8 % low on configs/plant_twomass.yaml, at 2 % within 0.5 %
# (tests/bench/bench_tune.py, rows "noise"). Above this the result is refused.
MAX_NOISE_RE_AMPLITUDE = 0.02
# A probe whose criteria lie within this relative margin of their limits (or within two
# standard errors of the ratio) is near the threshold: a noise seed could flip the choice.
# It is taken, and the amplitude the other answer gives is named as the alternative (and
# measured by the second-amplitude experiment of the budget).
AUTO_AMPLITUDE_MARGIN = 0.25
# The encoder's quantisation offsets the criterion's optimum through the loop (steps of
# kp q next to the friction) by an amount that falls with the amplitude (256 counts: +2.9 %
# at 0.5 rad, +0.9 % at 2 rad, +0.1 % at 4 rad on configs/plant_twomass.yaml): auto raises the
# amplitude until the step is at most this share of it (the demo's 2000 counts: 0.6 % at
# 0.5 rad).
MAX_STEP_RE_AMPLITUDE = 0.01


def _next_amplitude(a, h1, ratio, noise, max_rad):
    # r(0) falls about as 1/amplitude out of stick-slip; a stuck motor needs a big step
    factor = 4.0 if not math.isfinite(ratio) or h1 < 0.5 else \
        min(8.0, max(2.0, ratio / (0.8 * AUTO_AMPLITUDE_MAX_RATIO), 1.2 * noise / MAX_NOISE_RE_AMPLITUDE))
    return min(max_rad, a * factor)


def amplitude_verdict(h1, ratio, ratio_std, noise_re_amplitude, margin=AUTO_AMPLITUDE_MARGIN):
    """``"pass"``, ``"fail"`` or ``"near"`` (a noise seed could flip it) for one auto probe.

    The ratio criterion r(0) <= 0.05 is near when r(0) lies within ``margin`` (relative) or
    two standard errors of the limit; |H_1| >= 0.5 within a fifth of ``margin``; the noise
    criterion (also checked after the search) is passed only with the full margin below it.
    """
    rel = [(AUTO_AMPLITUDE_MIN_H1 - h1) / AUTO_AMPLITUDE_MIN_H1,
           (ratio - AUTO_AMPLITUDE_MAX_RATIO) / AUTO_AMPLITUDE_MAX_RATIO if math.isfinite(ratio) else math.inf]
    band = [margin / 5, max(margin, (2 * ratio_std / AUTO_AMPLITUDE_MAX_RATIO)
                            if math.isfinite(ratio_std) else 0.0)]
    noise = (noise_re_amplitude - MAX_NOISE_RE_AMPLITUDE) / MAX_NOISE_RE_AMPLITUDE
    if noise > -margin or any(r > b for r, b in zip(rel, band)):
        return "fail"
    if all(r < -b for r, b in zip(rel, band)):
        return "pass"
    return "near"


def choose_amplitude(probe, start_rad, max_rad, max_probes=4):
    """``tune.amplitude_rad: auto``: the sine amplitude (rad) for the search, from probes
    at K_fc = 0, raised until the loop is out of stick-slip.

    A probe near a limit (``amplitude_verdict`` "near") is taken, with the amplitude the
    other answer would have given as ``alternative_rad``. A probe that saturates the drive
    or a motor that does not move while the output sits at u_max ends the choice with that
    cause (``stop``).

    Returns
    -------
    amplitude : float
    block : dict
        The choice, its reason, the alternative and the probes (for results.yaml).
    p0 : dict
        The probe at the chosen amplitude (the search's K_fc = 0 experiment).
    stop : dict or None
        The check (:func:`fftune.analysis.tuning.check_experiment`) that ended the choice.
    """
    a = float(start_rad)
    probes = []
    q_step, q_source = None, None
    for _ in range(max_probes):
        p = probe.measure("amplitude", 0.0, amplitude=a)
        h1 = float(np.abs(p["H"][0]))
        noise = p["angle_noise_rad"] / a
        ratio_std = probe.search_point(p).ratio_std if math.isfinite(p["ratio"]) else math.inf
        verdict = amplitude_verdict(h1, p["ratio"], ratio_std, noise)
        probes.append({"amplitude_rad": _f(a), "h1": _f(h1), "ratio_at_zero": _f(p["ratio"]),
                       "angle_noise_re_amplitude": _f(noise), "verdict": verdict, **_check_block(p)})
        ck = p["check"]
        if ck["cause"] == "saturation" or (ck["cause"] == "no motion" and (ck["saturated_fraction"] or 0)
                                           > _tuning.SATURATION_MAX_FRACTION):
            return a, {"chosen_rad": _f(a), "alternative_rad": None, "probes": probes,
                       "reason": f"stopped: {ck['text']}"}, p, ck
        if len(probes) >= 2 and noise > MAX_NOISE_RE_AMPLITUDE and probes[-2]["angle_noise_re_amplitude"] \
                and (probes[-2]["h1"] or 0) >= AUTO_AMPLITUDE_MIN_H1 and h1 >= AUTO_AMPLITUDE_MIN_H1 \
                and noise * a > 2 * probes[-2]["angle_noise_re_amplitude"] * probes[-2]["amplitude_rad"]:
            # the spread over the recorded periods grew with the amplitude: not measurement
            # noise but motion that differs between periods (a slow transient, a loop near its
            # resonance, a limit cycle); a larger amplitude does not help
            ck = {"cause": "unsettled", "saturated_fraction": ck["saturated_fraction"], "text": (
                f"the motor angle differs between the recorded periods by {100 * noise:.2g} % of the "
                f"amplitude at {a:g} rad and {100 * probes[-2]['angle_noise_re_amplitude']:.2g} % at "
                f"{probes[-2]['amplitude_rad']:g} rad: not measurement noise (it grows with the "
                "amplitude) but a loop that has not settled or does not repeat (near its resonance?); "
                "raise tune.settle_periods or lower tune.frequency_hz")}
            return a, {"chosen_rad": _f(a), "alternative_rad": None, "probes": probes,
                       "reason": f"stopped: {ck['text']}"}, p, ck
        nxt = _next_amplitude(a, h1, p["ratio"], noise, max_rad)
        if q_step is None and p["record"] is not None:
            q_step, q_source = _encoder_step(probe.s, p)
        probes[-1]["encoder_step_re_amplitude"] = _f(q_step / a) if q_step else None
        if verdict != "fail" and q_step and q_step / a > MAX_STEP_RE_AMPLITUDE and a < max_rad:
            # the quantisation offset falls with the amplitude: go where the step is small
            verdict = probes[-1]["verdict"] = "fail"
            probes[-1]["encoder_note"] = (f"encoder step {q_step:.3g} rad ({q_source}) is "
                                          f"{100 * q_step / a:.2g} % of the amplitude (> "
                                          f"{100 * MAX_STEP_RE_AMPLITUDE:g} %)")
            nxt = min(max_rad, max(nxt, 1.05 * q_step / MAX_STEP_RE_AMPLITUDE))
        if verdict != "fail":
            near = verdict == "near"
            alt = nxt if near and nxt > a else None
            return a, {"chosen_rad": _f(a), "alternative_rad": _f(alt), "probes": probes, "reason": (
                f"at K_fc = 0 the motor follows the sine (|H_1| = {h1:.3g} >= "
                f"{AUTO_AMPLITUDE_MIN_H1:g}), the odd-harmonic ratio {p['ratio']:.3g} is <= "
                f"{AUTO_AMPLITUDE_MAX_RATIO:g} (out of stick-slip) and the angle noise is "
                f"{100 * noise:.2g} % of the amplitude (<= {100 * MAX_NOISE_RE_AMPLITUDE:g} %)"
                + (f"; the encoder step is {100 * q_step / a:.2g} % of it (<= "
                   f"{100 * MAX_STEP_RE_AMPLITUDE:g} %, else the amplitude is raised: the "
                   "quantisation offset falls with it)" if q_step and q_step / a <= MAX_STEP_RE_AMPLITUDE
                   else f"; the encoder step is {100 * q_step / a:.2g} % of it, above "
                   f"{100 * MAX_STEP_RE_AMPLITUDE:g} %, at tune.amplitude_max_rad" if q_step else "")
                + (f"; near a limit (within {100 * AUTO_AMPLITUDE_MARGIN:g} % or 2 standard errors): "
                   f"another noise seed may choose {alt:.3g} rad, measured as the second amplitude"
                   if alt else ""))}, p, None
        if a >= max_rad:
            break
        a = nxt
    return a, {"chosen_rad": _f(a), "alternative_rad": None, "probes": probes, "reason": (
        f"stick-slip at every amplitude up to tune.amplitude_max_rad = {max_rad:g} rad "
        f"(|H_1| = {probes[-1]['h1']:.3g}, ratio at K_fc = 0 {probes[-1]['ratio_at_zero']}); "
        "the search runs there and may rely on the ratio minimiser: raise "
        "tune.amplitude_max_rad if the set-up allows")}, p, None


def _std_over_periods(points):
    """Per point the standard deviation of the HOSIDFs over the recorded periods, (n, K)
    (from the per-period HOSIDFs, or the drive's period-to-period variance); None when a
    point has neither."""
    out = []
    for p in points:
        if p.get("H_periods") is not None:
            out.append(np.std(np.asarray(p["H_periods"]), axis=0, ddof=1).reshape(-1)[:len(p["H"])])
        elif p.get("H_var") is not None:
            out.append(np.sqrt(np.asarray(p["H_var"], dtype=float)))
        else:
            return None
    return np.stack(out)


def sweep_optimum(k, ratio, signed):
    """K_fc optimum of a sweep: the zero crossing of the signed objective next to the
    ratio minimum, linearly interpolated between the two sweep points around it; the grid
    minimum of the ratio when the signed objective does not change sign there.

    Returns
    -------
    k_opt : float
        NaN when the ratio is smallest at an end of the grid (the optimum may lie outside).
    note : str
    """
    i = int(np.argmin(ratio))
    if i == len(k) - 1 or (i == 0 and k[0] > 0):
        return math.nan, (f"the ratio is smallest at the end of the sweep (K_fc = {k[i]:.4g}): "
                          "the optimum may lie outside; widen tune.sweep.k_fc_max")
    for j in (i - 1, i):
        if 0 <= j < len(k) - 1 and signed[j] > 0 >= signed[j + 1]:
            return (float(k[j] + (k[j + 1] - k[j]) * signed[j] / (signed[j] - signed[j + 1])),
                    "zero crossing of the signed objective next to the ratio minimum")
    return float(k[i]), "grid minimum of the ratio (no sign change of the signed objective there)"


def k_fc_limit(session):
    """The largest K_fc the drive allows: its output limit u_max (a feed-forward above it
    only saturates), at most the object's own range (100 V)."""
    u_max = session.controller.get("u_max")
    if u_max is None:
        try:
            u_max = float(session.drive.get("u_max"))
        except (FftuneError, KeyError, AttributeError):   # e.g. a CAN-log replay without it
            u_max = 100.0
    return float(min(u_max, 100.0))


def check_tune_plan(session):
    """The tune keys against the drive (sine on the DFT grid, harmonics below fs/2, the
    bracket within what the drive allows), before any experiment is made."""
    c = session.cfg["tune"]
    src = session.cfg.get("_source", "config")
    if c.get("method") == "model":       # the lines the model tune reads (not tune.harmonics)
        from fftune.host.ffmodel_tune import check_model_lines
        check_model_lines(c, session.fs_hz, src)
    else:
        _TuneProbe(session)
    k_hi = c["search"]["k_fc_max"] or c["sweep"]["k_fc_max"]
    limit = k_fc_limit(session)
    if k_hi > limit:
        key = "tune.search.k_fc_max" if c["search"]["k_fc_max"] else "tune.sweep.k_fc_max"
        raise FftuneError(f"{src}: key '{key}': {k_hi:g} V is above what the drive allows "
                          f"(its output limit u_max = {limit:g} V)")


# The uncertainty budget after a converged search (fftune.analysis.tuning.uncertainty_budget).
# A motor lagging the reference by more than this at K_fc* gets the viscous feed-forward
# estimate in the loop before K_fc* is read (the lag moves the criterion's optimum). A motor
# that LEADS by more than this (the K_v read at K_fc = 0 was too large: brief sticking at the
# reversals reads as viscous friction there; 0.157 V s/rad on configs/plant_paper.yaml for
# the plant's 0.066, a lead of 8.5 deg that put K_fc* 2.5 % low) is corrected the same way.
LAG_MIN_DEG = 1.5
# The amplitude part: K_fc* at a second amplitude A2 (the auto choice's alternative, else 2 A,
# else A / 2), combined by fftune.analysis.tuning.amplitude_combination with this rule.
AMPLITUDE_RULE = "trend"
# The viscous feed-forward goes into the search when its share of the plant input's
# fundamental (K_v w |Y_1| / |U_1|) at K_fc = 0 is at least this. At K_fc = 0 the motor
# sticks briefly at each reversal, which the sliding-relay fit reads as viscous friction:
# on the matrix's plants without much viscous friction the share came out 0.07-0.17, with
# it (demo, load-side damping) 0.4-0.7 (tests/bench/bench_tune_matrix.py). A smaller
# viscous share is corrected after the search, from the lag at K_fc* (LAG_MIN_DEG).
KV_MIN_SHARE = 0.25
# The search's relative stopping tolerance: the experiments of the budget (the second
# amplitude, the lag correction) read K_fc* again along the measured slope, so the search
# only needs to land within this of it (fewer experiments than KfcSearch's default 0.5 %).
SEARCH_RTOL = 0.02
# At the second amplitude a root step along the scaled slope longer than this share of K_fc*
# gets a second experiment there and the secant through both.
SECOND_POINT_STEP = 0.05
# K_fc* at the second amplitude beyond twice the noise, or more than this share of K_fc*
# away (a noisy second experiment: a friction step inside it), brings a repeat of the first
# amplitude's experiment: did the plant change during the tune (issue 32)?
REPEAT_STEP = 0.05
# ... or when the search's noise part exceeds this many times the second amplitude's (one
# experiment's period spread) and this share of K_fc*: the search's points (and periods)
# disagree more than one experiment's noise, as when the friction drifts during the search
# (a -30 % ramp over 30 s: 1.5 % and 770 times; the noise-free matrix rows 0.1 .. 0.6 %)
REPEAT_NOISE_RATIO = 10.0
REPEAT_NOISE_REL = 0.01
# A repeated experiment differs when its s moved by more than 3 times the noise and this
# share of its first value (the loop's periodic states: a stationary plant repeats within it)
REPEAT_FLOOR = 0.01
# A search that did not converge while the motor moved more than this times the reference,
# or less than its inverse, at its best point: the loop near its resonance (issue 32).
LOOP_GAIN_MAX = 1.4
# A tune refused for the loop's lag is tried again at half the frequency, at most this often.
MAX_FREQUENCY_HALVINGS = 2
# The causes a lower frequency can remove: the loop's lag, a loop near its resonance whose
# motion does not repeat from period to period.
HALVE_FOR = ("loop lag", "unsettled")
# Unconverged for these, the first experiment is repeated: a plant that changed during the
# tune looks like stick-slip, a rotating phase, an amplitude dependence or a large budget.
REPEAT_FOR = ("stick-slip", "amplitude dependence", "budget", "flatness")
# A budget above this share of K_fc* is no tuning result: converged false, with the largest
# part and what would shrink it.
MAX_SIGMA_RE_K_FC = 0.1
_BUDGET_ADVICE = {
    "amplitude": "K_fc* depends on the sine amplitude (stick-slip, Stribeck, a loop that does not "
                 "repeat): raise tune.amplitude_rad / tune.amplitude_max_rad, or lower tune.frequency_hz",
    "encoder": "the encoder is coarse for this friction: a larger amplitude (tune.amplitude_max_rad) or a "
               "finer encoder",
    "noise": "raise tune.periods or the amplitude",
    "flatness": "the objective is flat near its zero: raise the amplitude",
    "viscous": "the viscous feed-forward estimate did not settle: check the plant's damping",
}


def _amplitude_allowed(session, a):
    """A sine amplitude above the chosen one only within what the configuration allows
    (tune.amplitude_max_rad, limits.max_amplitude_rad, limits.max_velocity_rad_s) and the
    drive's amplitude range (1000 rad): the preflight checked those, not the larger sine."""
    c = session.cfg["tune"]
    lim = session.cfg.get("limits") or {}
    if a > c["amplitude_max_rad"] or a > 1000.0:
        return False
    if lim.get("max_amplitude_rad") is not None and a > lim["max_amplitude_rad"]:
        return False
    v_max = lim.get("max_velocity_rad_s")
    return v_max is None or 2 * math.pi * c["frequency_hz"] * a <= v_max


def probe_limit(session):
    """The largest K_fc an experiment after the search may ask for (the drive's limit)."""
    return k_fc_limit(session)


def _encoder_step(session, p):
    q = session.cfg["detect"].get("encoder_step_rad")
    if q:
        return float(q), "detect.encoder_step_rad"
    y = p["record"].signals.get("motor_angle")
    if y is not None:
        q = _tuning.encoder_step_estimate(y, p["angle_noise_rad"])
        if q:
            return float(q), "estimated from the recorded motor angle"
        return 0.0, ("not found in the recorded motor angle (no steps, or noise above a sixth of a "
                     "step dithers the quantiser): no encoder part")
    return None, "unknown: no samples (tune.capture stats) and detect.encoder_step_rad unset"


def _phases_and_slope(probe, outcome, by_k):
    """The reference phases and ds/dK at K_fc*: the search's (signed root), else from the
    ends of its last bracket (ratio minimiser); (None, nan) when s does not change sign there."""
    if outcome.phases is not None and np.isfinite(outcome.slope) and outcome.slope < 0:
        return np.asarray(outcome.phases), float(outcome.slope)
    a, b = outcome.bracket
    if not (np.isfinite(a) and np.isfinite(b) and a in by_k and b in by_k and b > a):
        return None, math.nan
    pa, pb = probe.search_point(by_k[a]), probe.search_point(by_k[b])
    phases = _tuning.reference_phases(pa.H - pb.H, probe.harmonics)
    sa = _tuning.signed_point(pa, phases, probe.harmonics)[0]
    sb = _tuning.signed_point(pb, phases, probe.harmonics)[0]
    if not (sa > 0 > sb):
        return None, math.nan
    return phases, (sb - sa) / (b - a)


def _at(probe, tag, k, kv, amplitude, phases, slope, repeat=False):
    """One experiment after the search: (point, s, se, root along the slope) or the check
    that stopped it."""
    p = probe.measure(tag, float(k), float(kv), amplitude=amplitude, repeat=repeat)
    if p["check"]["cause"] is not None:
        return p, None
    s_k, se = _tuning.signed_point(probe.search_point(p), phases, probe.harmonics)
    return p, (s_k, se, _tuning.root_at_slope(float(np.float32(k)), s_k, slope))


def _budget(session, probe, outcome, by_k, amp_block):
    """After a converged search at amplitude A1: (1) the viscous feed-forward in the loop when
    the motor lags the reference (the lag moves the criterion's optimum off the Coulomb
    level: corrected), (2) K_fc* at a second amplitude (the amplitude dependence: the
    reported K_fc* is extrapolated to 1/A -> 0 and the part is the size of that step),
    (3) the encoder floor and the flatness of s near the root. Returns a dict with
    ``k_fc``, ``sigma_total``, ``parts`` and ``cause`` (not None: cannot tell, why)."""
    c = session.cfg["tune"]
    a1 = float(probe.amplitude)
    omega = 2 * math.pi * c["frequency_hz"]
    out = {"cause": None, "k_v_in_search": 0.0, "experiments": 0}
    phases, slope = _phases_and_slope(probe, outcome, by_k)
    if phases is None:
        out["cause_key"] = "stick-slip"
        out["cause"] = ("cannot tell the uncertainty: the signed objective has no sign change "
                        f"around K_fc = {outcome.k_fc:.4g} V (the odd phases rotate), so K_fc* at a "
                        "second amplitude cannot be read; raise the amplitude (out of stick-slip)")
        return out
    n0 = session.tune_experiments
    k1 = float(outcome.k_fc)
    sig_noise = float(outcome.sigma)
    p_star = min(by_k.items(), key=lambda kp: abs(kp[0] - k1))[1]
    h1 = complex(p_star["H"][0])
    lag_deg = float(-np.degrees(np.angle(h1)))
    kv_search = float(getattr(probe, "kv_search", 0.0))
    kv, _ = _viscous_estimate(probe, p_star)
    if kv == 0.0 and p_star["u_over_y"] is not None:
        y1 = h1 * a1
        kv = _tuning.viscous_feedforward_estimate(p_star["u_over_y"] * y1, y1, omega, k1)
    visc = {"lag_deg": _f(lag_deg), "k_v_in_search": _f(kv_search), "k_v_estimate": _f(kv),
            "applied": False, "steps": []}
    visc_part = 0.0
    k = k1
    if abs(lag_deg) > LAG_MIN_DEG and kv > 0 and abs(kv - kv_search) > 0.1 * kv:
        last = None
        for i in range(2):
            p, r = _at(probe, "lag", k, kv, a1, phases, slope)
            if r is None:
                out["cause"] = f"{p['check']['cause']}: {p['check']['text']}"
                out["cause_key"] = p["check"]["cause"]
                return out
            s_k, se, k_new = r
            if not math.isfinite(k_new):
                break
            visc["steps"].append({"k_fc": _f(k), "s": _f(s_k), "s_std": _f(se), "root": _f(k_new)})
            step = abs(k_new - k)
            # one experiment: the root along the search's slope, its linearity unverified
            # (half the step is the part); a second when the step exceeds 2 %
            k, last = k_new, (p, se, step / 2 if i == 0 else step)
            if step <= max(2 * se / abs(slope), 0.02 * abs(k)):
                break
        if last is not None:
            lag_new = float(-np.degrees(np.angle(last[0]["H"][0])))
            visc["lag_after_deg"] = _f(lag_new)
            if abs(lag_new) < abs(lag_deg):
                visc["applied"] = True
                visc_part = last[2]
                sig_noise = math.hypot(sig_noise, last[1] / abs(slope))
            else:
                visc_part = abs(k - k1)
                k = k1
    if not visc["applied"]:
        kv = kv_search
    visc["note"] = (
        (f"the viscous feed-forward K_v = {kv_search:.4g} V s/rad (read from the K_fc = 0 experiment) "
         "was in the loop during the search; " if kv_search else "")
        + (f"the motor {'lagged' if lag_deg > 0 else 'led'} the reference by {abs(lag_deg):.3g} deg at "
           f"K_fc*: K_fc* read again with K_v = {kv:.4g} V s/rad in the loop (corrected)"
           if visc["applied"] else
           f"lag {lag_deg:.3g} deg at K_fc* (|lag| <= {LAG_MIN_DEG:g} deg, or no better K_v estimate): no "
           "further correction" if visc_part == 0 else
           "the new K_v estimate did not reduce the lag: not applied; the shift it gave is a part "
           "of the budget"))
    out["k_v_in_search"] = kv
    # (1b) the lag K_v did not remove: the loop's own (its bandwidth at this frequency)
    lag_res = visc.get("lag_after_deg") if visc["applied"] else lag_deg
    visc["lag_residual_deg"] = _f(lag_res)
    lag_part = _tuning.loop_lag_part(lag_res, k)
    out["viscous"] = visc
    if not math.isfinite(lag_part):
        out["cause"] = _loop_lag_text(c["frequency_hz"], lag_res, kv)
        out["cause_key"] = "loop lag"
        return out
    # (1c) the drive's sign smoothing (fc_smooth) at the smaller amplitude of the two below
    width = p_star.get("fc_smooth") or 0.0
    # (2) a second amplitude
    amax = c["amplitude_max_rad"]
    alt = (amp_block or {}).get("alternative_rad")
    candidates = [alt] if alt else []
    candidates += [x for x in (2 * a1, a1 / 2) if x <= max(amax, a1) and x not in candidates]
    candidates = [x for x in candidates if x <= a1 or _amplitude_allowed(session, x)]
    p2 = r2 = None
    tried = []
    for a2 in candidates:
        p2, r2 = _at(probe, "amplitude2", k, kv, a2, phases,
                     slope * a1 * abs(h1) / a2 / max(abs(h1), 1e-12))
        tried.append(f"{a2:.3g} rad: {p2['check']['cause'] or 'ok'}")
        if r2 is not None:
            break
    if r2 is None or not math.isfinite(r2[2]):
        out["cause_key"] = next((t.split(": ")[1] for t in tried if not t.endswith(": ok")), "budget")
        out["cause"] = ("cannot tell the amplitude dependence of K_fc*: no second amplitude gave a "
                        f"usable experiment ({'; '.join(tried)})")
        return out
    a2 = float(p2["amplitude"])
    smooth_rel = _tuning.smoothed_sign_bias(width, omega * min(a1, a2), probe.harmonics)
    h1_2 = abs(complex(p2["H"][0]))
    slope2 = slope * a1 * abs(h1) / (a2 * h1_2)
    s2, se2, _ = r2
    k_a = float(np.float32(k))
    k2 = _tuning.root_at_slope(k_a, s2, slope2)
    sigma2 = se2 / abs(slope2) * _tuning._t_factor(max(1, p2["n_periods"] - 1))
    second = None
    if math.isfinite(k2) and abs(k2 - k_a) > SECOND_POINT_STEP * abs(k_a) and 0 < k2 <= probe_limit(session):
        # a long step along a scaled slope (the slope at A2 need not be the scaled one, e.g. in
        # stick-slip): one more experiment at the root, then the secant through both
        p3, r3 = _at(probe, "amplitude2", k2, kv, a2, phases, slope2)
        if r3 is not None and r3[0] != s2:
            s3, se3 = r3[0], r3[1]
            k_b = float(np.float32(k2))
            slope_m = (s3 - s2) / (k_b - k_a)
            if slope_m < 0:
                second = {"k_fc": _f(k_b), "s": _f(s3), "s_std": _f(se3), "slope_measured": _f(slope_m)}
                k2 = _tuning.root_at_slope(k_b, s3, slope_m)
                sigma2 = math.hypot(se3, se2) / abs(slope_m) * _tuning._t_factor(max(1, p3["n_periods"] - 1))
    repeat = None
    if math.isfinite(k2) and (abs(k2 - k) > 2 * math.hypot(sig_noise, sigma2)
                              or abs(k2 - k) > REPEAT_STEP * abs(k)
                              or sig_noise > max(REPEAT_NOISE_RATIO * sigma2, REPEAT_NOISE_REL * abs(k))):
        # (2b) K_fc* differs at the two amplitudes (or the search's points disagree): before
        # it is read as amplitude dependence, the first amplitude's experiment again (after the
        # second): a plant that changed during the tune moves it, the amplitude does not
        # the search's first experiment again, at the end: a plant that changed during the
        # tune moves it (and made the search's slope and root describe no one plant)
        repeat = _repeat_first(probe, by_k)
        if repeat and repeat["changed"]:
            out["cause"] = _repeat_text(repeat, f", after the one at {a2:.3g} rad,") + (
                f"; the difference to {a2:.3g} rad ({k2:.5g} V against {k:.5g} V) is no amplitude "
                "dependence")
            out["cause_key"] = "non-stationary"
            out["repeat"] = repeat
            return out
    k_est, noise_est, amp_part, how = _tuning.amplitude_combination(
        k, sig_noise, a1, k2, sigma2, a2, rule=AMPLITUDE_RULE)
    q, q_source = _encoder_step(session, p_star)
    if q is None:
        out["cause_key"] = "encoder"
        out["cause"] = ("cannot tell the encoder part of the uncertainty: the encoder step is "
                        f"{q_source}; set detect.encoder_step_rad (2 pi / counts per revolution, from "
                        "the encoder's data sheet) or use tune.capture: both")
        return out
    enc = _tuning.encoder_floor_v(q, min(a1, a2), p_star["angle_noise_rad"], slope * (a1 / min(a1, a2)))
    total, parts = _tuning.uncertainty_budget({
        "noise": noise_est, "amplitude": amp_part, "encoder": enc,
        "flatness": float(outcome.sigma_fit), "viscous": visc_part,
        "loop_lag": _tuning.loop_lag_part(lag_res, k_est),
        "smoothed_sign": smooth_rel * abs(k_est) if width > 0 else 0.0})
    out.update({
        "k_fc": float(k_est), "sigma_total": total, "parts": parts,
        "k_fc_at_amplitude": {"amplitude_rad": [_f(a1), _f(a2)], "k_fc": [_f(k), _f(k2)],
                              "sigma_noise": [_f(sig_noise), _f(sigma2)],
                              "s_at_second": _f(s2), "s_std_at_second": _f(se2),
                              "secant_at_second": second},
        "rule": how,
        "k_fc_search": _f(k1), "viscous": visc,
        "encoder_step_rad": _f(q), "encoder_step_source": q_source,
        "experiments": session.tune_experiments - n0,
        "repeat": repeat,
        "fc_smooth": {"width_rad_s": _f(width), "velocity_peak_rad_s": _f(omega * min(a1, a2)),
                      "bias_bound_rel": _f(smooth_rel),
                      "note": ("pure sign (fc_smooth 0)" if not width > 0 else
                               "the drive smooths the feed-forward's sign over +-fc_smooth: its odd "
                               "harmonics are smaller than the friction's relay, the criterion's "
                               "optimum moves up; the bound of that offset is the smoothed_sign part")},
    })
    return out


def _loop_lag_text(f_hz, lag_deg, kv):
    """The refusal of a tune whose motor lags the reference because of the loop itself."""
    return (f"the loop cannot follow the {f_hz:g} Hz sine closely enough: the motor "
            f"{'lags' if lag_deg > 0 else 'leads'} the reference by {abs(lag_deg):.3g} deg at K_fc* "
            f"with the viscous feed-forward K_v = {kv:.4g} V s/rad in the loop (more than "
            f"{_tuning.LOOP_LAG_MAX_DEG:g} deg; the loop's own bandwidth, which no K_v removes): the "
            "feed-forward switches with the reference, the friction with the motor, so the "
            "criterion's optimum is off the Coulomb level by an amount that is no longer bounded; "
            "lower tune.frequency_hz (the lag falls with it) or raise the loop gains")


def _diagnose_search(probe, outcome, by_k, kv):
    """The real cause of a search that did not converge (not stopped by a check): the
    loop's lag, the drive's smoothed sign, a plant that changed (the first experiment
    repeated), else the search's own (noise, or not verified). Returns (cause, text)."""
    pts = [p for _, p in sorted(by_k.items()) if math.isfinite(p["ratio"])]
    if not pts:
        return outcome.cause or "not verified", None
    best = min(pts, key=lambda p: p["ratio"])
    lag = best["lag_deg"]
    if math.isfinite(lag) and abs(lag) > _tuning.LOOP_LAG_MAX_DEG:
        return "loop lag", _loop_lag_text(probe.c["frequency_hz"], lag, kv).replace(
            "at K_fc*", f"at K_fc = {best['kfc']:.4g} V (the smallest ratio)")
    gain = abs(complex(best["H"][0]))
    if not 1 / LOOP_GAIN_MAX <= gain <= LOOP_GAIN_MAX:
        return "loop lag", (
            f"the loop cannot follow the {probe.c['frequency_hz']:g} Hz sine: the motor moves {gain:.3g} "
            f"times the reference at K_fc = {best['kfc']:.4g} V (the smallest ratio; |H_1| "
            f"{abs(complex(pts[0]['H'][0])):.3g} .. {abs(complex(pts[-1]['H'][0])):.3g} over the search): "
            "the loop is near its resonance there, the criterion does not measure the friction alone; "
            "lower tune.frequency_hz or change the loop gains")
    width = best.get("fc_smooth") or 0.0
    omega = 2 * math.pi * probe.c["frequency_hz"]
    bias = _tuning.smoothed_sign_bias(width, omega * probe.amplitude, probe.harmonics)
    if bias > MAX_SIGMA_RE_K_FC:
        return "smoothed sign", (
            f"the drive smooths the feed-forward's sign over fc_smooth = {width:g} rad/s, "
            f"{100 * width / (omega * probe.amplitude):.2g} % of the sine's peak velocity: its odd "
            f"harmonics are not the friction's relay (offset bound {100 * min(bias, 9.99):.3g} %), so "
            "the criterion cannot find the Coulomb level; set fc_smooth to 0 for the tune or raise "
            "the amplitude")
    why = _repeat_check(probe, by_k, kv)
    if why:
        return "non-stationary", why
    return outcome.cause or "not verified", None


def _repeat_first(probe, by_k):
    """The search's first experiment (the top of its bracket, over-compensated: s is linear
    in the friction there) repeated at the end of the tune. Returns None when it cannot be
    compared, else a dict: ``k_fc``, ``k_v``, ``s_then``, ``s_now``, ``noise`` and
    ``changed`` (|s_now - s_then| above 3 times their combined noise and REPEAT_FLOOR of
    |s_then|: the plant changed during the tune; the search's points, measured at different
    times, then describe no one plant)."""
    k_top = max(by_k)
    first = by_k[k_top]
    if not (k_top > 0 and math.isfinite(first["ratio"]) and 0.0 in by_k
            and math.isfinite(by_k[0.0]["ratio"])):
        return None
    rep = probe.measure("repeat", k_top, first["kv"], amplitude=first["amplitude"], repeat=True)
    if rep["check"]["cause"] is not None or not math.isfinite(rep["ratio"]):
        return None
    phases = _tuning.reference_phases(np.asarray(by_k[0.0]["H"]) - np.asarray(first["H"]), probe.harmonics)
    s1, se1 = _tuning.signed_point(probe.search_point(first), phases, probe.harmonics)
    s2, se2 = _tuning.signed_point(probe.search_point(rep), phases, probe.harmonics)
    noise = math.hypot(se1, se2)
    return {"k_fc": _f(k_top), "k_v": _f(first["kv"]), "s_then": _f(s1), "s_now": _f(s2),
            "noise": _f(noise), "changed": bool(abs(s2 - s1) > 3 * noise + REPEAT_FLOOR * abs(s1))}


def _repeat_text(rep, after=""):
    return (f"the plant changed during the tune: the search's first experiment (K_fc = {rep['k_fc']:.4g} V) "
            f"repeated at the end{after} reads s = {rep['s_now']:.3g} instead of {rep['s_then']:.3g} "
            f"(noise {rep['noise']:.2g}): the friction drifts between the experiments (warming up, wear, "
            "a load change), which no search can follow; tune again in a steady state, or follow the "
            "drift with fftune track")


def _repeat_check(probe, by_k, kv):
    """The text naming a change of the plant during the tune (:func:`_repeat_first`), or None."""
    rep = _repeat_first(probe, by_k)
    return _repeat_text(rep) if rep and rep["changed"] else None


def tune(session):
    """K_fc* (:func:`tune_at_frequency`) at ``tune.frequency_hz``; when the loop cannot follow
    that sine (cause ``loop lag``: its own lag, which no K_v removes, moves the criterion's
    optimum), again at half the frequency (on the drive's DFT grid, N <= 8192), at most
    ``MAX_FREQUENCY_HALVINGS`` times; ``frequency_changes`` in the results says so.

    Returns
    -------
    results, data : dict, dict
        As :func:`tune_at_frequency`.
    """
    cfg0 = session.cfg
    session.tune_f0 = cfg0["tune"]["frequency_hz"]
    session.cfg_of_record = cfg0
    changes, experiments = [], 0
    try:
        results, data = tune_at_frequency(session)
        while results["search"]["cause"] in HALVE_FOR and len(changes) < MAX_FREQUENCY_HALVINGS:
            c = session.cfg["tune"]
            src = session.cfg.get("_source", "config")
            cyc = _cycles(session.fs_hz, c["period_samples"], c["frequency_hz"], f"{src}: key 'tune.frequency_hz'")
            nxt = _tuning.halved_frequency(c["period_samples"], cyc, n_max=8192)
            if nxt is None:
                break
            n2, c2 = nxt
            f2 = c2 * session.fs_hz / n2
            changes.append({"from_hz": _f(c["frequency_hz"]), "to_hz": _f(f2), "period_samples": int(n2),
                            "reason": results["search"]["stop_reason"]})
            session.log(f"tune: the loop cannot follow {c['frequency_hz']:g} Hz; again at {f2:g} Hz")
            experiments += results["search"]["experiments"] + results["search"]["amplitude_probes"]
            session.cfg = dict(session.cfg, tune=dict(c, frequency_hz=f2, period_samples=n2))
            results, data = tune_at_frequency(session)
    finally:
        session.cfg = cfg0
    if changes:
        results["frequency_changes"] = changes
        results["search"]["experiments_at_other_frequencies"] = experiments
        results["search"]["experiments"] += experiments      # every experiment of the tune
    return results, data


def tune_at_frequency(session):
    """K_fc: (a) the paper's sweep (optional), (b) the automated search, then (c) K_v.

    Returns
    -------
    results : dict
    data : dict
        Sweep (or search) HOSIDFs, the records at K_fc = 0, K_fc* and at the smallest rms
        error (for the paper's Figures 7 and 9).
    """
    c = session.cfg["tune"]
    check_tune_plan(session)
    if c.get("method") == "model":       # every term at once (issue 35): fftune.analysis.ffmodel
        from fftune.host.ffmodel_tune import run_model_tune
        return run_model_tune(session)
    probe = _TuneProbe(session)
    session.tune_experiments = 0
    settings = drive_settings(session)
    cause = None
    # (0) amplitude
    amp_block = stop = None
    if c["amplitude_rad"] == "auto":
        probe.amplitude, amp_block, _, stop = choose_amplitude(probe, c["amplitude_start_rad"],
                                                               c["amplitude_max_rad"])
    n_amplitude_probes = session.tune_experiments
    # (b) automated search, one experiment at a time; saturation or no motion ends it
    k_hi = c["search"]["k_fc_max"] or c["sweep"]["k_fc_max"]
    limit = k_fc_limit(session)
    search = _tuning.KfcSearch(0.0, k_hi, k_limit=limit, harmonics=probe.harmonics,
                               max_experiments=c["search"]["max_experiments"],
                               xtol=c["search"]["xtol_v"] or 0.0, rtol=SEARCH_RTOL)
    by_k = {}
    # the viscous feed-forward in the loop from the start when the plant's viscous friction
    # is a noticeable share of the input (it makes the motor lag the reference, which moves
    # the criterion's optimum off the Coulomb level); read from the K_fc = 0 experiment,
    # which stays at K_v = 0 (the reference point of the search)
    kv_pre, kv_share = 0.0, 0.0
    if stop is None:
        p_zero = probe.measure("search", 0.0)
        if p_zero["check"]["cause"] is not None:
            stop = p_zero["check"]
            by_k[0.0] = p_zero
        else:
            kv_pre, kv_share = _viscous_estimate(probe, p_zero)
            if kv_share < KV_MIN_SHARE:
                kv_pre = 0.0
    probe.kv_search = kv_pre
    while not search.done and stop is None:
        k = search.ask()
        p = probe.measure("search", float(k), kv_pre if k != 0.0 else 0.0)
        by_k[float(k)] = p
        if p["check"]["cause"] is not None:
            stop = p["check"]
            break
        if p["H_periods"] is not None:
            search.tell(k, p["H_periods"])
        else:
            search.tell_moments(k, p["H"], p["H_var"], p["n_periods"])
    outcome = search.result
    if stop is not None:
        outcome.converged = False
        outcome.reason = f"{stop['cause']}: {stop['text']}"
        outcome.sigma = math.nan
        cause = stop["cause"]
        if not by_k:                       # stopped in the amplitude choice
            by_k[0.0] = probe.measure("amplitude", 0.0)
        if not math.isfinite(outcome.k_fc):
            outcome.k_fc = min(by_k)
    elif not outcome.converged:
        cause, why = _diagnose_search(probe, outcome, by_k, kv_pre)
        if why:
            outcome.reason = f"{why} ({outcome.reason})"
    p_lo = by_k.get(0.0)
    if outcome.converged and p_lo is not None and \
            p_lo["angle_noise_rad"] > MAX_NOISE_RE_AMPLITUDE * probe.amplitude:
        outcome.converged = False
        cause = "noise"
        from_lines = "motor_angle" not in p_lo["record"].signals
        outcome.reason = (
            f"the angle noise ({p_lo['angle_noise_rad']:.2g} rad, "
            + ("from the period-to-period variance at the harmonic lines (drive statistics: it "
               "also counts motion that differs between periods, a settling transient or "
               "stick-slip)" if from_lines else "spread over the recorded periods")
            + f") is {100 * p_lo['angle_noise_rad'] / probe.amplitude:.2g} % of the sine amplitude "
            f"{probe.amplitude:g} rad: it dithers the friction and biases K_fc* (here "
            f"{outcome.k_fc:.4g} V); raise tune.amplitude_rad to >= "
            f"{p_lo['angle_noise_rad'] / MAX_NOISE_RE_AMPLITUDE:.2g} rad or set it to auto"
            + ("; if the loop settles slowly, raise tune.settle_periods or use tune.capture: both"
               if from_lines else ""))
    k_search = float(outcome.k_fc)
    search_converged = bool(outcome.converged)
    budget = None
    kv_search = 0.0
    if outcome.converged:
        budget = _budget(session, probe, outcome, by_k, amp_block)
        if budget["cause"] is not None:
            outcome.converged = False
            outcome.reason = budget["cause"]
            outcome.sigma = math.nan
            cause = budget.get("cause_key", "budget")
        elif not budget["sigma_total"] <= MAX_SIGMA_RE_K_FC * abs(budget["k_fc"]):
            part, value = max(budget["parts"].items(), key=lambda kv: kv[1])
            cause = _tuning.PART_CAUSES.get(part, "budget")
            outcome.converged = False
            outcome.sigma = math.nan
            outcome.k_fc = budget["k_fc"]
            outcome.reason = (
                f"cannot tell K_fc* better than +-{100 * budget['sigma_total'] / abs(budget['k_fc']):.3g} % "
                f"(sigma_total {budget['sigma_total']:.3g} V at K_fc = {budget['k_fc']:.4g} V, more than "
                f"{100 * MAX_SIGMA_RE_K_FC:g} %); the largest part is '{part}' ({value:.3g} V): "
                + _BUDGET_ADVICE.get(part, "see tune.search.budget"))
        else:
            outcome.k_fc, outcome.sigma = budget["k_fc"], budget["sigma_total"]
            kv_search = budget["k_v_in_search"]
    if not outcome.converged and cause in REPEAT_FOR:
        # before an unconverged tune blames the plant's shape or the budget: did it change?
        why = _repeat_check(probe, by_k, kv_pre)
        if why:
            cause, outcome.reason = "non-stationary", f"{why} ({outcome.reason})"
    n_search = session.tune_experiments
    pts = sorted(by_k.items())
    p0 = by_k.get(0.0) or probe.measure("verify", 0.0)
    k_star = float(outcome.k_fc)
    # the verification experiment: the measured point nearest K_fc* (within the tolerance
    # when converged)
    k_ver, p_star = min(pts, key=lambda kp: abs(kp[0] - k_star))
    # (a) the paper's sweep, the figure step (skipped with tune.sweep.points: 0)
    sweep = []
    k_sweep_opt, sweep_note = None, "skipped (tune.sweep.points: 0)"
    if c["sweep"]["points"]:
        ks = np.linspace(0.0, c["sweep"]["k_fc_max"], c["sweep"]["points"])
        sweep = [probe.measure("sweep", float(k)) for k in ks]
    fig_pts = sweep if sweep else [p for _, p in pts]
    H_fig = np.stack([p["H"] for p in fig_pts])
    ratio_fig = np.array([p["ratio"] for p in fig_pts])
    kfc_fig = np.array([p["kfc"] for p in fig_pts])
    phases_fig = _tuning.reference_phases(H_fig[0] - H_fig[-1], probe.harmonics)
    with np.errstate(divide="ignore", invalid="ignore"):   # a motor that did not move: |H_1| = 0
        signed_fig = np.asarray(_tuning.signed_odd_ratio(H_fig, phases_fig, probe.harmonics))
    if sweep:
        k_sweep_opt, sweep_note = sweep_optimum(kfc_fig, ratio_fig, signed_fig)
    # rms error minimum (the paper's +25 %): over the sweep, else over the search
    p_rms = min(fig_pts, key=lambda p: p["rms_error"])
    # (c) viscous feed-forward K_v at K_fc*
    kv_block = p_kv = None
    if c["viscous"]["enabled"] and outcome.converged:
        kv_eval = []

        def rms_at(kv):
            p = probe.measure("viscous", k_star, float(kv))
            kv_eval.append(p)
            return p["rms_error"]

        p_star_exact = probe.measure("verify", k_star) if abs(k_ver - k_star) > 0 else p_star
        # Brent's minimiser of fftune.analysis.tuning on the rms error instead of the ratio.
        mini = _tuning.RatioMinimizer(0.0, c["viscous"]["k_v_max"],
                                      max_evaluations=c["viscous"]["max_experiments"])
        kv_star = float(mini.run(rms_at).k_fc)
        p_kv = probe.measure("verify", k_star, kv_star)
        if p_kv["rms_error"] > p_star_exact["rms_error"]:
            # Brent never evaluates the bracket ends; K_v = 0 (the K_fc* run) is better.
            kv_star, p_kv = 0.0, p_star_exact
        kv_block = {
            "k_v_star": _f(kv_star), "experiments": len(kv_eval),
            "rms_error_rad": _f(p_kv["rms_error"]),
            "evaluations": [{"k_v": _f(p["kv"]), "rms_error_rad": _f(p["rms_error"])} for p in kv_eval],
        }
    truth = session.truth or {}
    fc_true = truth.get("sim_fc_volt")
    fc_true_start = fc_true
    if fc_true is not None:
        # the plant's truth when the tune ends (a simulated plant may drift during it)
        try:
            fc_true = (session.drive.plant_truth() or {}).get("sim_fc_volt", fc_true)
        except (FftuneError, AttributeError):
            pass
    # what the unconverged search leaves: an estimate whose budget is too large, or only
    # the experiment with the smallest ratio, which is no estimate of K_fc*
    is_estimate = outcome.converged or (budget is not None and budget.get("cause") is None
                                        and "k_fc" in budget)
    sigma = _f(outcome.sigma) if outcome.converged else None
    results = {
        "frequency_hz": c["frequency_hz"], "amplitude_rad": _f(probe.amplitude),
        "amplitude": amp_block or {"chosen_rad": _f(probe.amplitude), "reason": "tune.amplitude_rad"},
        "objective": f"odd-harmonic ratio r = {_tuning.ODD_LEVEL_DEFINITION}, harmonics "
                     f"{list(probe.harmonics)}, reference -> motor angle",
        "sweep": None if not sweep else {
            "k_fc": [_f(k) for k in kfc_fig], "ratio": [_f(r) for r in ratio_fig],
            "rms_error_rad": [_f(p["rms_error"]) for p in sweep],
            "optimum_k_fc": _f(k_sweep_opt), "optimum_note": sweep_note, "experiments": len(sweep),
        },
        "search": {
            "method": "bracketed root of the signed objective, ratio minimiser where the odd "
                      "phases rotate (fftune.analysis.tuning.KfcSearch)",
            "k_fc_star": _f(k_star), "sigma_v": sigma, "uncertainty": sigma,
            "sigma_parts_v": None if not (budget and "parts" in budget) else
            {k: _f(v) for k, v in budget["parts"].items()},
            "sigma_total_v": None if not (budget and "parts" in budget) else _f(budget["sigma_total"]),
            "budget": None if not (budget and "parts" in budget) else {
                k: budget[k] for k in ("k_fc_search", "k_fc_at_amplitude", "rule", "viscous",
                                       "encoder_step_rad", "encoder_step_source", "experiments",
                                       "repeat", "fc_smooth")},
            "k_v_in_search": _f(kv_search),
            # the search's own root (before the budget's corrections), and the lag of the motor
            # behind the reference left at it with the viscous feed-forward (the loop's own)
            "k_fc_search_v": _f(k_search) if search_converged else None,
            "loop_lag_deg": (budget or {}).get("viscous", {}).get("lag_residual_deg"),
            "converged": bool(outcome.converged), "stop_reason": outcome.reason,
            "cause": None if outcome.converged else (cause or "not verified"),
            "regime": outcome.regime,
            "bracket_v": [_f(x) for x in outcome.bracket],
            "bracket_extended": None if outcome.extended_to is None else {
                "from_v": _f(k_hi), "to_v": _f(outcome.extended_to),
                "reason": f"the ratio was smallest at the configured upper end {k_hi:g} V "
                          f"(tune.search.k_fc_max / tune.sweep.k_fc_max too small); doubled, "
                          f"capped at the drive's limit {limit:g} V"},
            "signed_objective_std": _f(outcome.sigma_signed),
            "signed_objective_slope_per_v": _f(outcome.slope),
            "verification_k_fc": _f(k_ver),
            "experiments": n_search,
            "amplitude_probes": n_amplitude_probes,
            "relative_to_sweep_optimum": _f(k_star / k_sweep_opt - 1) if k_sweep_opt else None,
            "evaluations": [{"k_fc": _f(p["kfc"]), "k_v": _f(p["kv"]), "ratio": _f(p["ratio"]),
                             "ratio_std": _f(probe.search_point(p).ratio_std) if math.isfinite(p["ratio"])
                             else None, **_check_block(p)}
                            for _, p in pts],
        },
        "k_fc_star": _f(k_star) if outcome.converged else None,
        "k_fc_best_measured": _f(k_star) if is_estimate else None,
        "k_fc_best_measured_note": (
            "K_fc*" if outcome.converged else
            "an estimate whose uncertainty is too large (tune.search.sigma_total_v)" if is_estimate else
            f"none: the search did not converge ({cause or 'not verified'}); the experiment with the "
            f"smallest odd-harmonic ratio was at K_fc = {k_star:.5g} V, which is no estimate of K_fc*"),
        "drive_settings": settings,
        "ratio_at_zero": _f(p0["ratio"]), "ratio_at_k_fc_star": _f(p_star["ratio"]),
        "ratio_improvement": _f(p0["ratio"] / p_star["ratio"]) if p_star["ratio"] > 0 else None,
        "rms_error_rad": {"k_fc_0": _f(p0["rms_error"]), "k_fc_star": _f(p_star["rms_error"]),
                          "sweep_min": _f(p_rms["rms_error"]), "sweep_min_at_k_fc": _f(p_rms["kfc"])},
        "viscous": kv_block,
        "true_coulomb_v": _f(fc_true),
        "true_coulomb_v_at_start": _f(fc_true_start),
        "k_fc_star_error_re_truth": _f(k_star / fc_true - 1) if fc_true and outcome.converged else None,
    }
    if kv_block:
        results["rms_error_rad"]["k_fc_star_k_v_star"] = kv_block["rms_error_rad"]
    data = {"k_sweep": kfc_fig, "H_sweep": H_fig, "ratio_sweep": ratio_fig,
            "H_std_sweep": _std_over_periods(fig_pts),
            "signed_sweep": signed_fig, "k_star": k_star, "p0": p0, "p_star": p_star, "p_rms": p_rms,
            "p_kv": p_kv, "n": probe.n, "fs": session.fs_hz}
    return results, data
