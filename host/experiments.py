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
from fftune.analysis import tune_strategy as _ts
from fftune.analysis.tune_strategy import (  # noqa: F401  (the names tests and scripts read here)
    AUTO_AMPLITUDE_MAX_RATIO, LAG_MIN_DEG, MAX_FREQUENCY_HALVINGS, MAX_SIGMA_RE_K_FC, _blocks, _cycles,
    _saturation_fraction, amplitude_verdict, sweep_optimum)
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


def sine_request(*, inject, amplitude_peak, n, cycles, settle, periods, kfc, kv):
    return {"exc_kind": EXC_KINDS["sine"], "exc_inject": INJECT[inject],
            "exc_amplitude": float(amplitude_peak), "exc_offset": 0.0, "exc_period": int(n),
            "exc_sine_cycles": int(cycles), "exc_settle_periods": int(settle),
            "exc_record_periods": int(periods), "kfc": float(kfc), "kv": float(kv)}


# ---------------------------------------------------------------------------------------
# detect
# ---------------------------------------------------------------------------------------
def _run_u_max(session, rec):
    """u_max in V: read back with the run (its parameters), else the configuration's
    controller.u_max, else None (the saturation fraction is then not evaluated)."""
    value = (getattr(rec, "parameters", None) or {}).get("u_max")
    if value is None:
        value = session.controller.get("u_max")
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
        _ts.check_model_lines(c, session.fs_hz, src)
    else:
        _ts.check_plan(session.cfg, session.fs_hz, session.capture_mode("tune"))
    k_hi = c["search"]["k_fc_max"] or c["sweep"]["k_fc_max"]
    limit = k_fc_limit(session)
    if k_hi > limit:
        key = "tune.search.k_fc_max" if c["search"]["k_fc_max"] else "tune.sweep.k_fc_max"
        raise FftuneError(f"{src}: key '{key}': {k_hi:g} V is above what the drive allows "
                          f"(its output limit u_max = {limit:g} V)")




def _strategy(session, max_halvings):
    """The :class:`fftune.analysis.tune_strategy.SearchTune` of the session's tune."""
    return _ts.SearchTune(session.cfg, fs_hz=session.fs_hz, k_fc_limit_v=k_fc_limit(session),
                          capture=session.capture_mode("tune"), drive_settings=drive_settings(session),
                          max_halvings=max_halvings, log=session.log)


def tune_request(request):
    """The drive parameters of a tune :class:`fftune.analysis.tune_strategy.ExperimentRequest`."""
    g = request.gains
    req = sine_request(inject="reference", amplitude_peak=request.amplitude_rad, n=request.period_samples,
                       cycles=request.cycles, settle=request.settle_periods, periods=request.periods,
                       kfc=g["kfc"], kv=g["kv"])
    req.update({k: float(v) for k, v in g.items() if k not in ("kfc", "kv")})
    return req


def execute(session, strategy):
    """Run what a tune strategy asks on the drive, one experiment at a time: ask, run (the
    session records the capture, or loads it when a resumed tune has it), tell. Returns the
    strategy's result."""
    while (request := strategy.ask()) is not None:
        rec = session.run("tune", request.key, tune_request(request), stats=request.stats)
        session.tune_experiments = request.index + 1
        strategy.tell(request, _ts.measurement_from_record(rec, session.controller))
    return strategy.result()


def _finish(session, results):
    """results['tune'] with the plant's truth (a simulated drive; it may drift during the tune)."""
    fc_start = (session.truth or {}).get("sim_fc_volt")
    fc_end = fc_start
    if fc_start is not None:
        try:
            fc_end = (session.drive.plant_truth() or {}).get("sim_fc_volt", fc_start)
        except (FftuneError, AttributeError):
            pass
    return _ts.with_truth(results, fc_start, fc_end)


def tune(session):
    """K_fc* by the strategy :class:`fftune.analysis.tune_strategy.SearchTune` (``tune.method:
    search``; the frequency halved at most ``MAX_FREQUENCY_HALVINGS`` times when the loop cannot
    follow the sine), or the model-based tune (``tune.method: model``,
    :mod:`fftune.host.ffmodel_tune`). The host executes and records; every decision is the
    strategy's.

    Returns
    -------
    results : dict
    data : dict
        Sweep (or search) HOSIDFs, the records at K_fc = 0, K_fc* and at the smallest rms
        error (for the paper's Figures 7 and 9).
    """
    return _tune(session, MAX_FREQUENCY_HALVINGS)


def tune_at_frequency(session):
    """As :func:`tune` at ``tune.frequency_hz`` only (no frequency change)."""
    return _tune(session, 0)


def _tune(session, max_halvings):
    check_tune_plan(session)
    if session.cfg["tune"].get("method") == "model":   # every term at once (issue 35): fftune.analysis.ffmodel
        from fftune.host.ffmodel_tune import run_model_tune
        return run_model_tune(session)
    session.cfg_of_record = session.cfg
    session.tune_experiments = 0
    results, data = execute(session, _strategy(session, max_halvings))
    return _finish(session, results), data
