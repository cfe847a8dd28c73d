"""The tune strategy of `tune.method: search` as an ask/tell object (issue 35): it asks for
the next experiment (a closed-loop sine at the reference: amplitude, frequency, the
feed-forward gains) and is told what the drive recorded; every decision of the tune lives
here, the host only executes and records.

:class:`SearchTune` holds the amplitude choice (``tune.amplitude_rad: auto``), the root
search of K_fc (:class:`fftune.analysis.tuning.KfcSearch`), the viscous feed-forward in the
search, the uncertainty budget (a second amplitude, the lag correction, the encoder, the
smoothed sign), the repeat that tells a plant that changed during the tune, the paper's
sweep, K_v by Brent's minimiser on the rms error, and the halving of the frequency when the
loop cannot follow the sine. :class:`fftune.analysis.ffmodel.FeedForwardModelTune`
(`tune.method: model`) follows the same protocol (:class:`ModelTune`).

The protocol::

    strategy = SearchTune(cfg, fs_hz=..., k_fc_limit_v=..., capture="raw")
    while (request := strategy.ask()) is not None:
        record = ...                 # run request on the drive, record the capture
        strategy.tell(request, Measurement(record, u_max_v, fc_smooth))
    results, data = strategy.result()

:func:`replay` drives a strategy from recorded captures alone (no drive): the same requests,
the same result.
"""
import dataclasses
import math

import numpy as np

from fftune.analysis import ffmodel as _ffmodel
from fftune.analysis import stats as _stats
from fftune.analysis import tuning as _tuning
from fftune.analysis.errors import FftuneError
from fftune.analysis.hosidf import hosidf as _hosidf_estimate  # (fftune.analysis.hosidf is the function)


def _f(x):
    """A YAML-friendly float (None for NaN/inf)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def cycles_on_grid(fs, n, f_hz, where):
    """Sine periods in one record period of ``n`` samples at ``fs`` Hz; FftuneError naming
    ``where`` when ``f_hz`` is not on the drive's DFT grid or not below fs/2."""
    c = f_hz * n / fs
    if abs(c - round(c)) > 1e-9 * max(1.0, c) or round(c) < 1:
        raise FftuneError(f"{where}: {f_hz:g} Hz is not on the DFT grid fs/N = {fs:g}/{n} = "
                          f"{fs / n:g} Hz of the drive")
    if 2 * round(c) >= n:
        raise FftuneError(f"{where}: {f_hz:g} Hz is above fs/2")
    return int(round(c))


_cycles = cycles_on_grid


def _blocks(x, n):
    return np.asarray(x).reshape(-1, n)


def saturation_fraction(u, u_max):
    """Fraction of the plant-input samples at the drive's output limit (|u| >= u_max,
    float32 tolerance); None when u_max is unknown."""
    if u_max is None or not u_max > 0:
        return None
    u = np.abs(np.asarray(u, dtype=float))
    return float(np.mean(u >= u_max * (1 - 1e-6)))


_saturation_fraction = saturation_fraction


@dataclasses.dataclass
class ExperimentRequest:
    """One experiment a tune strategy asks for: a closed-loop sine at the reference.

    Attributes
    ----------
    key : str
        The capture's name (the run is recorded, and resumed, under it).
    tag : str
        What the experiment is for (``search``, ``amplitude``, ``lag``, ``verify``, ...).
    amplitude_rad : float
        Peak of the reference sine.
    gains : dict
        The feed-forward gains during the run (``kfc`` in V, ``kv`` in V s/rad; the model
        tune also ``kfa``, ``kps``, ``kpc``).
    frequency_hz, period_samples, cycles, settle_periods, periods
        The sine: frequency, samples per record period, sine periods in it, settling and
        recorded periods.
    stats : dict
        The line statistics asked of the drive when the tune captures statistics.
    index : int
        The experiment's number in the tune (0 first).
    """
    key: str
    tag: str
    amplitude_rad: float
    gains: dict
    frequency_hz: float
    period_samples: int
    cycles: int
    settle_periods: int
    periods: int
    stats: dict
    index: int = 0


@dataclasses.dataclass
class Measurement:
    """What the host tells a strategy about one executed experiment.

    Attributes
    ----------
    record : object
        The drive's record (``signals``: name -> samples; ``stats``: the line statistics
        or None; ``parameters``: the drive's settings read back with the run).
    u_max_v : float or None
        The drive's output limit during the run (saturation check).
    fc_smooth : float or None
        The feed-forward sign's smoothing width (rad/s) during the run.
    """
    record: object
    u_max_v: float = None
    fc_smooth: float = None


def measurement_from_record(record, controller=None):
    """The :class:`Measurement` of a record: u_max and fc_smooth read back with the run's
    parameters, else the configuration's ``controller`` values, else None."""
    controller = controller or {}

    def setting(name):
        value = (getattr(record, "parameters", None) or {}).get(name)
        if value is None:
            value = controller.get(name)
        return None if value is None else float(value)

    return Measurement(record, setting("u_max"), setting("fc_smooth"))


class _Context:
    """What the search tune knows of its set-up (no drive): the configuration (its
    ``tune``, ``detect``, ``limits`` sections), the drive's sample rate, the tune's capture
    mode, the largest K_fc the drive allows and the drive's settings (for results)."""

    def __init__(self, cfg, fs_hz, capture, k_fc_limit, drive_settings):
        self.cfg, self.fs_hz, self.capture = cfg, float(fs_hz), capture
        self.k_fc_limit = float(k_fc_limit)
        self.drive_settings = drive_settings
        self.tune_experiments = 0
        self.tune_f0 = cfg["tune"]["frequency_hz"]

    def capture_mode(self, step):
        return self.capture


# ---------------------------------------------------------------------------------------
# the search tune (moved from fftune.host.experiments)
# ---------------------------------------------------------------------------------------
class _TuneProbe:
    """One closed-loop sine experiment at (K_fc, K_v, amplitude): HOSIDF reference -> motor
    angle per recorded period, odd-harmonic objective, rms tracking error, and the checks
    of every tune experiment: the share of samples at u_max and the motion (|H_1|)."""

    def __init__(self, ctx):
        self.s = ctx
        c = ctx.cfg["tune"]
        self.c = c
        src = ctx.cfg.get("_source", "config")
        self.n = c["period_samples"]
        self.cycles = _cycles(ctx.fs_hz, self.n, c["frequency_hz"], f"{src}: key 'tune.frequency_hz'")
        if self.cycles * c["harmonics"] * 2 >= self.n:
            raise FftuneError(f"{src}: key 'tune.harmonics': harmonic {c['harmonics']} of "
                              f"{c['frequency_hz']:g} Hz is above fs/2 = {ctx.fs_hz / 2:g} Hz")
        self.harmonics = _tuning.harmonic_orders(c["harmonics"])
        self.amplitude = c["amplitude_rad"] if c["amplitude_rad"] != "auto" else None
        self.points = {}
        # what the drive accumulates with capture stats/both: the HOSIDF lines of the
        # reference, the angle and the plant input (its fundamental: the viscous estimate),
        # the power of the tracking error and of the plant input (saturation)
        self.stats_request = {"harmonics": c["harmonics"],
                              "signals": ["reference", "motor_angle", "plant_input"],
                              "power": ["error", "plant_input"]}
        if ctx.capture_mode("tune") != "raw" and c["harmonics"] > _stats.STAT_K_MAX:
            raise FftuneError(f"{src}: key 'tune.harmonics': {c['harmonics']} harmonics with "
                              f"tune.capture {ctx.capture_mode('tune')}: the drive's statistics "
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
        measured = yield ExperimentRequest(
            key=key, tag=tag, amplitude_rad=float(amplitude), gains={"kfc": float(kfc), "kv": float(kv)},
            frequency_hz=float(c["frequency_hz"]), period_samples=int(self.n), cycles=int(self.cycles),
            settle_periods=int(c["settle_periods"]), periods=int(c["periods"]), stats=self.stats_request,
            index=self.s.tune_experiments)
        rec = measured.record
        u_max = measured.u_max_v
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
            "fc_smooth": measured.fc_smooth,
        }
        if not repeat:
            self.points[cache] = point
        self.s.tune_experiments += 1
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


def _resonance_check(probe, p):
    """The check of an experiment without feed-forward whose motor moves more than
    LOOP_GAIN_MAX times the reference (cause ``loop lag``), else None. Friction only holds the
    motor back: such motion is the loop's resonance at this frequency (it also drives the output
    into u_max: kp 5, kd 0.01 at 3.75 Hz, |H_1| 5.8 and 57 % of the samples at u_max, which
    read as saturation)."""
    h1 = float(np.abs(p["H"][0]))
    if p["kfc"] != 0.0 or p["kv"] != 0.0 or not h1 > LOOP_GAIN_MAX:
        return None
    ck = p["check"]
    return dict(ck, cause="loop lag", text=(
        f"the loop cannot follow the {probe.c['frequency_hz']:g} Hz sine: without feed-forward the "
        f"motor moves {h1:.3g} times the reference at {p['amplitude']:g} rad (more than {LOOP_GAIN_MAX:g}; "
        "the friction only holds it back): the loop is near its resonance at this frequency"
        + (f", its output at u_max in {100 * ck['saturated_fraction']:.0f} % of the samples"
           if (ck["saturated_fraction"] or 0) > _tuning.SATURATION_MAX_FRACTION else "")
        + "; lower tune.frequency_hz or change the loop gains"))


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
        The probe at the chosen amplitude (the search's K_fc = 0 experiment); when the
        probes ran out below ``max_rad``, the last probe (the chosen amplitude, the next
        step, was not probed: the reason says so).
    stop : dict or None
        The check (:func:`fftune.analysis.tuning.check_experiment`) that ended the choice.
    """
    a = float(start_rad)
    probes = []
    q_step, q_source = None, None
    for _ in range(max_probes):
        p = yield from probe.measure("amplitude", 0.0, amplitude=a)
        h1 = float(np.abs(p["H"][0]))
        noise = p["angle_noise_rad"] / a
        ratio_std = probe.search_point(p).ratio_std if math.isfinite(p["ratio"]) else math.inf
        verdict = amplitude_verdict(h1, p["ratio"], ratio_std, noise)
        probes.append({"amplitude_rad": _f(a), "h1": _f(h1), "ratio_at_zero": _f(p["ratio"]),
                       "angle_noise_re_amplitude": _f(noise), "verdict": verdict, **_check_block(p)})
        ck = p["check"]
        resonance = _resonance_check(probe, p)
        if resonance is not None:
            ck = resonance
            probes[-1]["cause"] = "loop lag"
            return a, {"chosen_rad": _f(a), "alternative_rad": None, "probes": probes,
                       "reason": f"stopped: {ck['text']}"}, p, ck
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
        prev = probes[-2] if len(probes) >= 2 else None
        linear = prev is not None and ((ck["cause"] == "no motion" and prev["cause"] == "no motion") or (
            h1 < AUTO_AMPLITUDE_MIN_H1 and (prev["h1"] or 0) < AUTO_AMPLITUDE_MIN_H1
            and math.isfinite(p["ratio"]) and p["ratio"] <= AUTO_AMPLITUDE_MAX_RATIO))
        if linear and not (ck["saturated_fraction"] or 0) > _tuning.SATURATION_MAX_FRACTION and \
                not (prev["saturated_fraction"] or 0) > _tuning.SATURATION_MAX_FRACTION and \
                prev["h1"] and h1 > 0 and 1 / LINEAR_H1_FACTOR <= h1 / prev["h1"] <= LINEAR_H1_FACTOR:
            ck = {"cause": "loop lag", "saturated_fraction": ck["saturated_fraction"], "text": (
                f"the loop cannot follow the {probe.c['frequency_hz']:g} Hz sine: the motor moves "
                f"{h1:.3g} times the reference at {a:g} rad and {prev['h1']:.3g} times at "
                f"{prev['amplitude_rad']:g} rad, with no sample at u_max: the same share at both, so "
                "no friction holds it (a held motor breaks free as the amplitude grows) but the "
                "loop's own dynamics at this frequency (a load anti-resonance near it); lower "
                "tune.frequency_hz or change the loop gains")}
            probes[-1]["cause"] = "loop lag"
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
    last = f"(|H_1| = {probes[-1]['h1']:.3g}, ratio at K_fc = 0 {probes[-1]['ratio_at_zero']})"
    if probes[-1]["amplitude_rad"] < max_rad:
        # the probes ran out below the ceiling: the search runs at the next step, which no
        # probe measured (its own K_fc = 0 experiment is the first it makes there)
        return a, {"chosen_rad": _f(a), "alternative_rad": None, "probes": probes, "reason": (
            f"stick-slip at all {len(probes)} probed amplitudes up to {probes[-1]['amplitude_rad']:g} rad "
            f"{last}, below tune.amplitude_max_rad = {max_rad:g} rad: the search runs at the "
            f"next step, {a:g} rad, not probed, and may rely on the ratio minimiser")}, p, None
    return a, {"chosen_rad": _f(a), "alternative_rad": None, "probes": probes, "reason": (
        f"stick-slip at every amplitude up to tune.amplitude_max_rad = {max_rad:g} rad "
        f"{last}; the search runs there and may rely on the ratio minimiser: raise "
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
# An unconverged tune whose motor moves outside this band of the reference's amplitude at its
# best point (|H_1| at K_fc*, feed-forward in the loop): the loop's own dynamics at the tuning
# frequency (a load resonance or anti-resonance near it) shape the motion, and the parts that
# stopped the tune (the amplitude dependence, the viscous fit) describe the loop, not the
# friction. On the matrix's plants that follow the sine |H_1| is 0.95 .. 1.1 at K_fc*; near a
# two-mass anti-resonance 0.63 .. 0.75 (tests/bench/bench_tune_matrix.py --hidden, "two-mass
# resonance"). The cause is the loop's, and a lower frequency is tried.
LOOP_GAIN_BAND = (0.8, 1.25)
# A motor that does not move at two amplitudes (|H_1| < MOTION_MIN_H1, no sample at u_max), or
# follows at both less than AUTO_AMPLITUDE_MIN_H1 with small odd harmonics at the larger (no
# stick-slip), with the same |H_1| within this factor, is no friction that holds it (a held
# motor's |H_1| rises with the amplitude as it breaks free) but a linear loop that cannot make
# it follow the sine at this frequency (a two-mass anti-resonance: k 0.03 at 1.875 Hz, |H_1|
# 0.39 and 0.43 at 0.5 and 2 rad, then 8 rad into u_max).
LINEAR_H1_FACTOR = 1.5
# A drift of the friction during the tune shows within each experiment as a change of the
# signed objective from one recorded period to the next, of the same sign in every
# experiment; a stationary plant's changes (noise, settling) alternate in sign. When at least
# DRIFT_MIN_EXPERIMENTS experiments change the same way, by more than DRIFT_MIN_REL of K_fc*
# per period on average (through the search's slope), the first experiment is repeated before
# the result is accepted: an exponential -40 % drift with tau 15 s ended a tune +8.9 % off
# its final level with sigma 1.9 % (the second amplitude agreed within its noise).
DRIFT_MIN_EXPERIMENTS = 4
DRIFT_MIN_REL = 2e-3
# The search stops for the loop's lag as soon as its experiments on either side of the root
# bound the lag at K_fc* (lag_bound_deg) above this many times LOOP_LAG_MAX_DEG, without
# finding K_fc* first: the budget's K_v estimate lowers the lag by up to about 1.5 deg (kp 0.35
# on configs/plant_twomass.yaml: bounded 7.9 deg, 6.5 deg after K_v), so a bound just above the
# limit is left to the budget. On the matrix's slow loops this ends the try at a frequency the
# loop cannot follow after 2 .. 4 experiments instead of 8 .. 11 (tests/bench/bench_tune_matrix.py).
LAG_BOUND_MARGIN = 1.25
LAG_BOUND_STOP = False
# The angle's spread over the recorded periods at the chosen amplitude more than this many
# times its smallest over the auto probes (in rad): motion that differs between periods, not
# measurement noise (the same in rad at every amplitude): `unsettled`, not `noise` (with the
# drive's statistics a loop near a two-mass resonance read 0.56 rad "noise" at 8 rad).
UNSETTLED_SPREAD_GROWTH = 2.0
# With the drive's statistics (no samples) the spread comes from the line variances: white
# measurement noise gives about equal variances at every harmonic line (two recorded periods:
# the largest of seven above 10 times their median in about 1 % of the cases); above it the
# spread is motion at some lines, `unsettled`.
LINE_VARIANCE_MAX_RATIO = 10.0
# With samples: the share of the spread's power in 1 % of its frequencies (spread_concentration;
# white noise about 5.6 %) above which it is motion at a few frequencies, `unsettled`.
SPREAD_MAX_SHARE = 0.5
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


def _amplitude_allowed(ctx, a):
    """A sine amplitude above the chosen one only within what the configuration allows
    (tune.amplitude_max_rad, limits.max_amplitude_rad, limits.max_velocity_rad_s) and the
    drive's amplitude range (1000 rad): the preflight checked those, not the larger sine."""
    c = ctx.cfg["tune"]
    lim = ctx.cfg.get("limits") or {}
    if a > c["amplitude_max_rad"] or a > 1000.0:
        return False
    if lim.get("max_amplitude_rad") is not None and a > lim["max_amplitude_rad"]:
        return False
    v_max = lim.get("max_velocity_rad_s")
    return v_max is None or 2 * math.pi * c["frequency_hz"] * a <= v_max


def probe_limit(ctx):
    """The largest K_fc an experiment after the search may ask for (the drive's limit)."""
    return ctx.k_fc_limit


def _encoder_step(ctx, p):
    q = ctx.cfg["detect"].get("encoder_step_rad")
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
    p = yield from probe.measure(tag, float(k), float(kv), amplitude=amplitude, repeat=repeat)
    if p["check"]["cause"] is not None:
        return p, None
    s_k, se = _tuning.signed_point(probe.search_point(p), phases, probe.harmonics)
    return p, (s_k, se, _tuning.root_at_slope(float(np.float32(k)), s_k, slope))


def _budget(ctx, probe, outcome, by_k, amp_block):
    """After a converged search at amplitude A1: (1) the viscous feed-forward in the loop when
    the motor lags the reference (the lag moves the criterion's optimum off the Coulomb
    level: corrected), (2) K_fc* at a second amplitude (the amplitude dependence: the
    reported K_fc* is extrapolated to 1/A -> 0 and the part is the size of that step),
    (3) the encoder floor and the flatness of s near the root. Returns a dict with
    ``k_fc``, ``sigma_total``, ``parts`` and ``cause`` (not None: cannot tell, why)."""
    c = ctx.cfg["tune"]
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
    n0 = ctx.tune_experiments
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
            p, r = yield from _at(probe, "lag", k, kv, a1, phases, slope)
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
            # (half the step is the part); a second when the step exceeds 2 %. Two steps the
            # same way converge no faster than geometrically (the search's slope, measured with
            # another K_v, is not this loop's): the rest of that series, step q / (1 - q) with
            # q the ratio of the steps, bounds what is left (kp 1 at 0.3125 Hz: steps 2.3 %, 1.4 %,
            # K_fc* -3.5 % with the last step as the part, sigma_total 1.7 %)
            part = step / 2 if i == 0 else step
            if i == 1 and visc["steps"][0]["root"] is not None:
                first = visc["steps"][0]["root"] - visc["steps"][0]["k_fc"]
                q = step / abs(first) if first else math.inf
                if first * (k_new - k) > 0:
                    part = math.inf if q >= 1 else max(step, step * q / (1 - q))
            k, last = k_new, (p, se, part)
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
    candidates = [x for x in candidates if x <= a1 or _amplitude_allowed(ctx, x)]
    p2 = r2 = None
    tried = []
    for a2 in candidates:
        p2, r2 = yield from _at(probe, "amplitude2", k, kv, a2, phases,
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
    if math.isfinite(k2) and abs(k2 - k_a) > SECOND_POINT_STEP * abs(k_a) and 0 < k2 <= probe_limit(ctx):
        # a long step along a scaled slope (the slope at A2 need not be the scaled one, e.g. in
        # stick-slip): one more experiment at the root, then the secant through both
        p3, r3 = yield from _at(probe, "amplitude2", k2, kv, a2, phases, slope2)
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
        repeat = yield from _repeat_first(probe, by_k)
        if repeat and repeat["changed"]:
            out["cause"] = _repeat_text(repeat, f", after the one at {a2:.3g} rad,") + (
                f"; the difference to {a2:.3g} rad ({k2:.5g} V against {k:.5g} V) is no amplitude "
                "dependence")
            out["cause_key"] = "non-stationary"
            out["repeat"] = repeat
            return out
    k_est, noise_est, amp_part, how = _tuning.amplitude_combination(
        k, sig_noise, a1, k2, sigma2, a2, rule=AMPLITUDE_RULE)
    q, q_source = _encoder_step(ctx, p_star)
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
    if not math.isfinite(visc_part):
        # two K_v steps the same way, the second no smaller: the correction does not converge
        # and no part bounds what is left (uncertainty_budget skips a part that is not finite;
        # kept, it refuses the result with the viscous part the largest)
        total, parts = math.inf, dict(parts, viscous=math.inf)
    out.update({
        "k_fc": float(k_est), "sigma_total": total, "parts": parts,
        "k_fc_at_amplitude": {"amplitude_rad": [_f(a1), _f(a2)], "k_fc": [_f(k), _f(k2)],
                              "sigma_noise": [_f(sig_noise), _f(sigma2)],
                              "s_at_second": _f(s2), "s_std_at_second": _f(se2),
                              "secant_at_second": second},
        "rule": how,
        "k_fc_search": _f(k1), "viscous": visc,
        "encoder_step_rad": _f(q), "encoder_step_source": q_source,
        "experiments": ctx.tune_experiments - n0,
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


def _percent(share):
    """``share`` as a percentage for a person: two significant digits below 100 % ("44 %",
    "0.53 %"), whole percent above ("120 %", not "1.2e+02 %")."""
    pct = 100.0 * share
    return f"{pct:.2g} %" if abs(pct) < 99.5 else f"{pct:.0f} %"


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
            f"{_percent(width / (omega * probe.amplitude))} of the sine's peak velocity: its odd "
            f"harmonics are not the friction's relay (offset bound {100 * min(bias, 9.99):.3g} %), so "
            "the criterion cannot find the Coulomb level; set fc_smooth to 0 for the tune or raise "
            "the amplitude")
    why = yield from _repeat_check(probe, by_k, kv)
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
    rep = yield from probe.measure("repeat", k_top, first["kv"], amplitude=first["amplitude"], repeat=True)
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
    rep = yield from _repeat_first(probe, by_k)
    return _repeat_text(rep) if rep and rep["changed"] else None

def spread_concentration(y_periods, top=0.01):
    """The share of the period-to-period deviation's power in the ``top`` fraction of its DFT
    bins: about top (1 + ln(1 / top)) for white measurement noise (5.6 % for 1 %), near 1 for
    motion that differs between periods at a few frequencies (a loop ringing at its resonance).

    Parameters
    ----------
    y_periods : array_like, shape (P, N)
        The recorded periods of a signal (P >= 2).

    Returns
    -------
    float
        NaN when P < 2 or the deviation is zero.
    """
    y = np.asarray(y_periods, dtype=float)
    if y.ndim != 2 or y.shape[0] < 2:
        return math.nan
    dev = y - y.mean(axis=0)
    pw = np.sum(np.abs(np.fft.rfft(dev, axis=1)[:, 1:]) ** 2, axis=0)
    total = float(np.sum(pw))
    if not total > 0:
        return math.nan
    k = max(1, int(round(top * pw.size)))
    return float(np.sum(np.sort(pw)[-k:]) / total)


def _spread_text(probe, p):
    """The text naming motion that differs between the recorded periods of experiment ``p``
    (its spread not white: :func:`spread_concentration` with samples, else
    :func:`line_variance_is_white` on the drive's line statistics), or None."""
    rec = p["record"]
    if "motor_angle" in rec.signals:
        share = spread_concentration(_blocks(rec.signals["motor_angle"], probe.n))
        if not share > SPREAD_MAX_SHARE:
            return None
        what = f"its spectrum is not flat: {100 * share:.0f} % of its power in 1 % of the frequencies"
    elif rec.stats is not None and "motor_angle" in rec.stats.var:
        v = np.asarray(rec.stats.var["motor_angle"], dtype=float)
        if line_variance_is_white(v):
            return None
        what = (f"the period-to-period variance of the harmonic lines is not flat: its largest "
                f"{np.max(v) / max(np.median(v), 1e-300):.3g} times its median")
    else:
        return None
    return (f"the motor angle differs between the recorded periods at K_fc = {p['kfc']:.4g} V by motion, "
            f"not measurement noise ({what}): a loop that has not settled or does not repeat (near "
            "its resonance?); raise tune.settle_periods or lower tune.frequency_hz")


def line_variance_is_white(var, ratio=None):
    """Whether the period-to-period variances of a signal's harmonic lines look like white
    measurement noise (about equal at every line: their largest at most ``ratio`` times their
    median, default LINE_VARIANCE_MAX_RATIO) rather than motion that differs between periods
    at some lines (a loop ringing near its resonance, a slow settling transient)."""
    v = np.asarray(var, dtype=float)
    v = v[np.isfinite(v)]
    if v.size < 3:
        return True
    med = float(np.median(v))
    return bool(med > 0 and np.max(v) <= (LINE_VARIANCE_MAX_RATIO if ratio is None else ratio) * med)


def _loop_gain_text(probe, by_k, k):
    """The text naming the loop's own dynamics when the motor's |H_1| at the measured point
    nearest ``k`` lies outside LOOP_GAIN_BAND, else None."""
    pts = [(kk, p) for kk, p in by_k.items() if math.isfinite(p["ratio"])]
    if not pts or not math.isfinite(k):
        return None
    kk, p = min(pts, key=lambda kp: abs(kp[0] - k))
    gain = abs(complex(p["H"][0]))
    lo, hi = LOOP_GAIN_BAND
    if lo <= gain <= hi:
        return None
    return (f"the loop cannot follow the {probe.c['frequency_hz']:g} Hz sine: the motor moves {gain:.3g} "
            f"times the reference at K_fc = {kk:.4g} V (outside {lo:g} .. {hi:g}; lag "
            f"{p['lag_deg']:.3g} deg): the loop's own dynamics at this frequency (a load resonance "
            "or anti-resonance near it) shape the motion, so the amplitude dependence and the viscous "
            "fit that stopped the tune describe the loop, not the friction; lower tune.frequency_hz "
            "or change the loop gains")


def period_drift(s_periods, slope, k_fc):
    """Whether the signed objective drifts the same way within every experiment of a tune.

    Parameters
    ----------
    s_periods : list of array_like
        Per experiment, the signed objective of each recorded period (time order).
    slope : float
        ds/dK_fc of the search (1/V).
    k_fc : float
        K_fc* (V).

    Returns
    -------
    (drifting, rate_rel) : (bool, float)
        ``rate_rel`` the mean change per period, as the K_fc it corresponds to (change / |slope|),
        relative to |K_fc|; ``drifting`` when at least DRIFT_MIN_EXPERIMENTS experiments change
        with one sign and |rate_rel| > DRIFT_MIN_REL.
    """
    d = []
    for sp in s_periods:
        sp = np.asarray(sp, dtype=float)
        if sp.size >= 2 and np.all(np.isfinite(sp)):
            d.append((sp[-1] - sp[0]) / (sp.size - 1))
    if len(d) < DRIFT_MIN_EXPERIMENTS or not (np.isfinite(slope) and slope != 0 and k_fc):
        return False, math.nan
    d = np.asarray(d)
    rate = float(np.mean(d) / abs(slope) / abs(k_fc))
    same = bool(np.all(d > 0) or np.all(d < 0))
    return bool(same and abs(rate) > DRIFT_MIN_REL), rate


def _period_drift(probe, outcome, by_k):
    """:func:`period_drift` over the tune's experiments (per-period HOSIDFs: raw capture)."""
    phases, slope = _phases_and_slope(probe, outcome, by_k)
    if phases is None:
        return False, math.nan
    s_periods = []
    for p in probe.points.values():
        if p["H_periods"] is None or not math.isfinite(p["ratio"]) or not p["kfc"] > 0:
            continue        # (at K_fc = 0 the objective hardly moves with the friction)
        Hp = np.asarray(p["H_periods"])
        Hp = Hp.reshape(Hp.shape[0], -1)
        with np.errstate(divide="ignore", invalid="ignore"):
            s_periods.append([float(_tuning.signed_odd_ratio(h, phases, probe.harmonics)) for h in Hp])
    return period_drift(s_periods, slope, float(outcome.k_fc))


def lag_bound_deg(lags_below, lags_above):
    """A bound of the motor's lag behind the reference at K_fc* (deg) from experiments on
    either side of it: the lag falls as K_fc rises (more feed-forward pushes the motor ahead),
    so it is at least the lag of any experiment above the root (over-compensated, s < 0) and
    at most that of any below it (s > 0).

    Parameters
    ----------
    lags_below, lags_above : sequence of float
        Lags (deg; < 0 a lead) of the experiments below and above the root.

    Returns
    -------
    float
        The largest lag above the root when it is > 0, else the smallest lag below the root
        when it is < 0 (a lead at least that large), else 0 (no bound beyond the limits).
    """
    above = [x for x in lags_above if math.isfinite(x)]
    below = [x for x in lags_below if math.isfinite(x)]
    if above and max(above) > 0:
        return float(max(above))
    if below and min(below) < 0:
        return float(min(below))
    return 0.0


def _lag_sides(probe, by_k):
    """The lags of the search's experiments below and above the root: the sign of the signed
    objective with the phases of its first bracket (K_fc = 0 and the top), below where it is
    K_fc = 0's (under-compensated by definition), above where it is the other; ([], [])
    before both ends are measured or while K_fc = 0's sign is not clear of its noise. (The
    phases fix the sign's convention, not which side is positive.)"""
    pts = [(k, p) for k, p in by_k.items() if math.isfinite(p["ratio"])]
    if 0.0 not in by_k or len(pts) < 2 or not math.isfinite(by_k[0.0]["ratio"]):
        return [], []
    top = max(k for k, _ in pts)
    phases = _tuning.reference_phases(np.asarray(by_k[0.0]["H"]) - np.asarray(by_k[top]["H"]), probe.harmonics)
    signed = {k: _tuning.signed_point(probe.search_point(p), phases, probe.harmonics)[:2] for k, p in pts}
    s0, se0 = signed[0.0]
    if not abs(s0) > 2 * se0:
        return [], []
    # the lag falls with K_fc at one K_v, and is the loop's own only without a viscous
    # feed-forward: with a K_v pre-estimate (K_fc = 0 runs without it) the lag moves with K_v
    # itself (the paper's set-up: 38 deg at K_fc = 0, leads of 5 .. 27 deg at K_v 0.157 on
    # either side of a root the search finds, verified, at 0.625 Hz), which the budget's K_v
    # step corrects: no bound then.
    kv = by_k[top].get("kv", 0.0)
    if kv != 0.0:
        return [], []
    below, above = [], []
    for k, p in pts:
        s_k, se = signed[k]
        if abs(s_k) > 2 * se and p.get("kv", 0.0) == kv:
            (below if (s_k > 0) == (s0 > 0) else above).append(p["lag_deg"])
    return below, above


def _tune_at_frequency(ctx):
    """K_fc at one frequency (a generator of experiments): (a) the paper's sweep (optional),
    (b) the automated search, then (c) K_v.

    Returns
    -------
    results : dict
    data : dict
        Sweep (or search) HOSIDFs, the records at K_fc = 0, K_fc* and at the smallest rms
        error (for the paper's Figures 7 and 9).
    """
    c = ctx.cfg["tune"]
    probe = _TuneProbe(ctx)
    ctx.tune_experiments = 0
    settings = ctx.drive_settings
    cause = None
    # (0) amplitude
    amp_block = stop = None
    if c["amplitude_rad"] == "auto":
        # at a lower frequency after a refusal: from the amplitude chosen before (the loop's
        # stick-slip is the amplitude's, the probes below it would be repeated)
        start = min(max(c["amplitude_start_rad"], getattr(ctx, "amplitude_start", None) or 0.0),
                    c["amplitude_max_rad"])
        probe.amplitude, amp_block, _, stop = yield from choose_amplitude(probe, start, c["amplitude_max_rad"])
    n_amplitude_probes = ctx.tune_experiments
    # (b) automated search, one experiment at a time; saturation or no motion ends it
    k_hi = c["search"]["k_fc_max"] or c["sweep"]["k_fc_max"]
    limit = ctx.k_fc_limit
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
        p_zero = yield from probe.measure("search", 0.0)
        resonance = _resonance_check(probe, p_zero)
        if resonance is not None or p_zero["check"]["cause"] is not None:
            stop = resonance or p_zero["check"]
            by_k[0.0] = p_zero
        else:
            kv_pre, kv_share = _viscous_estimate(probe, p_zero)
            if kv_share < KV_MIN_SHARE:
                kv_pre = 0.0
    probe.kv_search = kv_pre
    while not search.done and stop is None:
        k = search.ask()
        p = yield from probe.measure("search", float(k), kv_pre if k != 0.0 else 0.0)
        by_k[float(k)] = p
        if p["check"]["cause"] is not None:
            stop = p["check"]
            break
        if p["H_periods"] is not None:
            search.tell(k, p["H_periods"])
        else:
            search.tell_moments(k, p["H"], p["H_var"], p["n_periods"])
        # (with the viscous step enabled the lag left at K_fc* is judged after its K_v, as
        # before: the experiments' lag holds the viscous friction's, which K_v removes; the
        # paper's simulation leads 24 deg at 0.625 Hz before its K_v, and tunes there)
        # (and only a lag: the loop's own bandwidth delays the motor; a lead is a feed-forward's,
        # K_fc's or a K_v read into the search, which the budget judges). Off by default
        # (LAG_BOUND_STOP): the experiments' lag also holds the viscous friction's, which no
        # search-time rule tells from the loop's; on the paper's simulation (viscous friction,
        # K_v off) it read 15 deg at 0.625 Hz, where the search converges and reproduces
        # Figure 7's phase turns, and moved the tune to 0.3125 Hz (make paper: H_5 151 deg).
        bound = 0.0 if not LAG_BOUND_STOP or (c.get("viscous") or {}).get("enabled") \
            else lag_bound_deg(*_lag_sides(probe, by_k))
        if bound > LAG_BOUND_MARGIN * _tuning.LOOP_LAG_MAX_DEG:
            # the lag at K_fc* is already known to exceed the limit: no need to find K_fc*
            stop = {"cause": "loop lag", "lag_bound_deg": bound, "text": (
                f"the loop cannot follow the {c['frequency_hz']:g} Hz sine closely enough: the motor "
                f"{'lags' if bound > 0 else 'leads'} the reference by {abs(bound):.3g} deg or more at K_fc* "
                f"(more than {_tuning.LOOP_LAG_MAX_DEG:g} deg; bounded by the experiments on either side "
                "of the root: the lag falls as K_fc rises), the loop's own bandwidth, which no K_v "
                "removes; lower tune.frequency_hz or raise the loop gains")}
            break
    outcome = search.result
    if stop is not None:
        outcome.converged = False
        outcome.reason = f"{stop['cause']}: {stop['text']}"
        outcome.sigma = math.nan
        cause = stop["cause"]
        if not by_k:                       # stopped in the amplitude choice
            by_k[0.0] = yield from probe.measure("amplitude", 0.0)
        if not math.isfinite(outcome.k_fc):
            outcome.k_fc = min(by_k)
    elif not outcome.converged:
        cause, why = yield from _diagnose_search(probe, outcome, by_k, kv_pre)
        if why:
            outcome.reason = f"{why} ({outcome.reason})"
    # the angle's spread of the K_fc = 0 experiment, or the median over the search's experiments
    # at its amplitude (the lower of two) when smaller: measurement noise is in every experiment,
    # a change of the plant or a transient inside one experiment is not (a +50 % friction step
    # inside the K_fc = 0 experiment read as "noise 15 % of the amplitude" with the drive's
    # statistics); near K_fc* a Stribeck curve's stick-slip spreads more than at K_fc = 0
    spread_pts = sorted((p for p in by_k.values() if p["amplitude"] == probe.amplitude
                         and math.isfinite(p["angle_noise_rad"])), key=lambda p: p["angle_noise_rad"])
    p_lo = by_k.get(0.0)
    if spread_pts and (p_lo is None or spread_pts[(len(spread_pts) - 1) // 2]["angle_noise_rad"]
                       < p_lo["angle_noise_rad"]):
        p_lo = spread_pts[(len(spread_pts) - 1) // 2]
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
        # measurement noise is the same in rad at every amplitude; a spread that grew with the
        # amplitude over the auto probes is motion that differs between periods (a loop near
        # its resonance, slow to settle): the loop's cause, a lower frequency may remove it
        spread = [(q["angle_noise_re_amplitude"] * q["amplitude_rad"], q["amplitude_rad"])
                  for q in (amp_block or {}).get("probes", [])
                  if q.get("angle_noise_re_amplitude") is not None and q.get("amplitude_rad")]
        lines_var = None if not from_lines else np.asarray(p_lo["record"].stats.var["motor_angle"], dtype=float)
        if from_lines:
            white = line_variance_is_white(lines_var)
        else:
            share = spread_concentration(_blocks(p_lo["record"].signals["motor_angle"], probe.n))
            white = not share > SPREAD_MAX_SHARE
            if not white:
                lines_var = None
        if spread or not white:
            n_min, a_min = min(spread) if spread else (p_lo["angle_noise_rad"], probe.amplitude)
            if not white or (p_lo["angle_noise_rad"] > UNSETTLED_SPREAD_GROWTH * n_min
                             and probe.amplitude > a_min):
                cause = "unsettled"
                outcome.reason = (
                    f"the motor angle differs between the recorded periods by {p_lo['angle_noise_rad']:.2g} "
                    f"rad at {probe.amplitude:g} rad"
                    + (f" and {n_min:.2g} rad at {a_min:g} rad" if white else "") + ": not measurement "
                    + ("noise (it grows with the amplitude)" if white else
                       f"noise (the period-to-period variance of the harmonic lines is not flat: its largest "
                       f"{np.max(lines_var) / max(np.median(lines_var), 1e-300):.3g} times its median)"
                       if lines_var is not None else
                       f"noise (its spectrum is not flat: {100 * share:.0f} % of its power in 1 % of the "
                       "frequencies)")
                    + " but a loop that has not settled or does not "
                    "repeat (near its resonance?); raise tune.settle_periods or lower tune.frequency_hz ("
                    + outcome.reason + ")")
    k_search = float(outcome.k_fc)
    search_converged = bool(outcome.converged)
    budget = None
    kv_search = 0.0
    if outcome.converged:
        budget = yield from _budget(ctx, probe, outcome, by_k, amp_block)
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
            if part == "noise":
                # the spread of s over the periods: measurement noise, or motion that differs
                # between them (a loop ringing near its resonance), which is no noise
                # (the experiment with the largest spread: it dominates the pooled noise)
                p_worst = max((p for p in by_k.values() if math.isfinite(p["angle_noise_rad"])),
                              key=lambda p: p["angle_noise_rad"], default=None)
                why = _spread_text(probe, p_worst) if p_worst is not None else None
                if why:
                    cause = "unsettled"
                    outcome.reason = f"{why} ({outcome.reason})"
        else:
            outcome.k_fc, outcome.sigma = budget["k_fc"], budget["sigma_total"]
            kv_search = budget["k_v_in_search"]
    if not outcome.converged and cause in REPEAT_FOR + ("viscous", "noise"):
        # the loop's own dynamics at this frequency, not the friction's shape
        why = _loop_gain_text(probe, by_k, float(outcome.k_fc))
        if why:
            cause, outcome.reason = "loop lag", f"{why} ({outcome.reason})"
    drift = None
    if outcome.converged:
        drifting, rate = _period_drift(probe, outcome, by_k)
        drift = {"rate_re_k_fc_per_period": _f(rate), "repeated": bool(drifting)}
        if drifting:
            # the objective moved the same way within every experiment: did the plant change?
            rep = yield from _repeat_first(probe, by_k)
            drift["repeat"] = rep
            if rep and rep["changed"]:
                outcome.converged = False
                outcome.sigma = math.nan
                cause = "non-stationary"
                outcome.reason = _repeat_text(rep) + (
                    f"; within every experiment the objective moved the same way "
                    f"({100 * rate:+.2g} % of K_fc* per recorded period)")
    if not outcome.converged and cause in REPEAT_FOR:
        # before an unconverged tune blames the plant's shape or the budget: did it change?
        why = yield from _repeat_check(probe, by_k, kv_pre)
        if why:
            cause, outcome.reason = "non-stationary", f"{why} ({outcome.reason})"
    n_search = ctx.tune_experiments
    pts = sorted(by_k.items())
    p0 = by_k.get(0.0) or (yield from probe.measure("verify", 0.0))
    k_star = float(outcome.k_fc)
    # the verification experiment: the measured point nearest K_fc* (within the tolerance
    # when converged)
    k_ver, p_star = min(pts, key=lambda kp: abs(kp[0] - k_star))
    # (a) the paper's sweep, the figure step (skipped with tune.sweep.points: 0)
    sweep = []
    k_sweep_opt, sweep_note = None, "skipped (tune.sweep.points: 0)"
    if c["sweep"]["points"]:
        ks = np.linspace(0.0, c["sweep"]["k_fc_max"], c["sweep"]["points"])
        sweep = []
        for k in ks:
            sweep.append((yield from probe.measure("sweep", float(k))))
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
        p_star_exact = (yield from probe.measure("verify", k_star)) if abs(k_ver - k_star) > 0 else p_star
        # Brent's minimiser of fftune.analysis.tuning on the rms error instead of the ratio.
        mini = _tuning.RatioMinimizer(0.0, c["viscous"]["k_v_max"],
                                      max_evaluations=c["viscous"]["max_experiments"])
        while not mini.done:
            kv = mini.ask()
            p = yield from probe.measure("viscous", k_star, float(kv))
            kv_eval.append(p)
            mini.tell(kv, p["rms_error"])
        kv_star = float(mini.result.k_fc)
        p_kv = yield from probe.measure("verify", k_star, kv_star)
        if p_kv["rms_error"] > p_star_exact["rms_error"]:
            # Brent never evaluates the bracket ends; K_v = 0 (the K_fc* run) is better.
            kv_star, p_kv = 0.0, p_star_exact
        kv_block = {
            "k_v_star": _f(kv_star), "experiments": len(kv_eval),
            "rms_error_rad": _f(p_kv["rms_error"]),
            "evaluations": [{"k_v": _f(p["kv"]), "rms_error_rad": _f(p["rms_error"])} for p in kv_eval],
        }
    # what the unconverged search leaves: an estimate whose budget is too large, or only
    # the experiment with the smallest ratio, which is no estimate of K_fc*
    is_estimate = outcome.converged or (budget is not None and budget.get("cause") is None
                                        and "k_fc" in budget and cause != "non-stationary")
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
            # the objective's change from one recorded period to the next (raw capture), and
            # whether it brought the first experiment again (a drift inside the experiments)
            "period_drift": drift,
            # the search's own root (before the budget's corrections), and the lag of the motor
            # behind the reference left at it with the viscous feed-forward (the loop's own)
            "k_fc_search_v": _f(k_search) if search_converged else None,
            # (or, when the search stopped on it before K_fc* was found, its bound from the
            # experiments on either side of the root, also in loop_lag_bound_deg)
            "loop_lag_deg": (budget or {}).get("viscous", {}).get("lag_residual_deg",
                                                                  _f((stop or {}).get("lag_bound_deg"))),
            "loop_lag_bound_deg": _f((stop or {}).get("lag_bound_deg")),
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
                             "lag_deg": _f(p["lag_deg"]), "h1": _f(abs(complex(p["H"][0]))),
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
        # the plant's truth (a simulated drive's): the host's, with_truth
        "true_coulomb_v": None, "true_coulomb_v_at_start": None, "k_fc_star_error_re_truth": None,
    }
    if kv_block:
        results["rms_error_rad"]["k_fc_star_k_v_star"] = kv_block["rms_error_rad"]
    data = {"k_sweep": kfc_fig, "H_sweep": H_fig, "ratio_sweep": ratio_fig,
            "H_std_sweep": _std_over_periods(fig_pts),
            "signed_sweep": signed_fig, "k_star": k_star, "p0": p0, "p_star": p_star, "p_rms": p_rms,
            "p_kv": p_kv, "n": probe.n, "fs": ctx.fs_hz}
    return results, data


def check_plan(cfg, fs_hz, capture):
    """The tune keys of ``cfg`` against the drive's sample rate and the capture mode (the
    sine on the DFT grid, its harmonics below fs/2 and within the drive's statistics);
    FftuneError naming the key. Part of the host's preflight, before any experiment."""
    _TuneProbe(_Context(cfg, fs_hz, capture, math.inf, None))


def _lower_frequency_helps(search):
    """Whether a lower frequency may remove what stopped the tune: the causes HALVE_FOR, and a
    budget whose largest part is the noise of s over the periods while the angle's own spread
    passed its check (motion that differs between periods: a loop still ringing from a
    frequency near its resonance; kp 5, kd 0.01 at 1.875 Hz after 3.75 Hz, +-41 %, converged
    +0.2 % at 0.9375 Hz; a lower frequency also has more samples per period)."""
    return search["cause"] in HALVE_FOR or (search["cause"] == "noise"
                                            and search.get("sigma_total_v") is not None)


def _tune(ctx, max_halvings, log):
    """K_fc* (:func:`_tune_at_frequency`) at ``tune.frequency_hz``; when the loop cannot follow
    that sine (cause ``loop lag``: its own lag, which no K_v removes, moves the criterion's
    optimum; ``unsettled``; a budget stopped by the noise of s: :func:`_lower_frequency_helps`),
    again at half the frequency (on the drive's DFT grid, N <= 8192: :func:`fftune.analysis.
    tuning.lower_frequency`), at most ``max_halvings`` halvings; a frequency where the lag
    measured or bounded here, scaled with the frequency, would still exceed LOOP_LAG_MAX_DEG is
    skipped (it counts as a halving). ``frequency_changes`` in the results says so."""
    cfg0 = ctx.cfg
    changes, experiments = [], 0
    try:
        results, data = yield from _tune_at_frequency(ctx)
        while _lower_frequency_helps(results["search"]) and len(changes) < max_halvings:
            c = ctx.cfg["tune"]
            src = ctx.cfg.get("_source", "config")
            # the lag measured (or bounded) here: it falls at least in proportion to the
            # frequency, so a lower frequency where it would still be above the limit is skipped
            lag = results["search"].get("loop_lag_bound_deg") or results["search"].get("loop_lag_deg")
            if lag is None or not math.isfinite(lag) or results["search"]["cause"] != "loop lag":
                lag = 0.0
            lag = abs(lag)
            n, cyc, f = c["period_samples"], _cycles(ctx.fs_hz, c["period_samples"], c["frequency_hz"],
                                                     f"{src}: key 'tune.frequency_hz'"), c["frequency_hz"]
            steps = 0
            while len(changes) < max_halvings:
                nxt = _tuning.lower_frequency(n, cyc, n_max=8192)
                if nxt is None:
                    break
                f2 = nxt[1] * ctx.fs_hz / nxt[0]
                lag *= f2 / f          # (a third, for odd cycles in the longest period)
                n, cyc = nxt
                changes.append({"from_hz": _f(f), "to_hz": _f(f2), "period_samples": int(n),
                                "reason": results["search"]["stop_reason"] if steps == 0 else (
                                    f"skipped: the lag at {f:g} Hz would still be about {lag * f / f2:.3g} "
                                    f"deg (the lag scaled with the frequency from {c['frequency_hz']:g} Hz; "
                                    f"more than {_tuning.LOOP_LAG_MAX_DEG:g} deg)")})
                f, steps = f2, steps + 1
                if lag <= _tuning.LOOP_LAG_MAX_DEG:
                    break
            if steps == 0:
                break
            log(f"tune: the loop cannot follow {c['frequency_hz']:g} Hz; again at {f:g} Hz")
            experiments += results["search"]["experiments"]     # (the amplitude probes among them)
            ctx.cfg = dict(ctx.cfg, tune=dict(c, frequency_hz=f, period_samples=n))
            # (not after `unsettled`: the amplitude chosen there is the unsettled loop's)
            ctx.amplitude_start = results["amplitude_rad"] if c["amplitude_rad"] == "auto" and \
                results["search"]["cause"] == "loop lag" else None
            results, data = yield from _tune_at_frequency(ctx)
    finally:
        ctx.cfg = cfg0
        ctx.amplitude_start = None
    if changes:
        results["frequency_changes"] = changes
        results["search"]["experiments_at_other_frequencies"] = experiments
        results["search"]["experiments"] += experiments      # every experiment of the tune
    return results, data


class SearchTune:
    """`tune.method: search` (and the paper's sweep, ``tune.sweep.points``) as an ask/tell
    object: every decision of the tune, no drive.

    Parameters
    ----------
    cfg : dict
        The validated configuration (its ``tune``, ``detect`` and ``limits`` sections; ``_source``
        names it in errors).
    fs_hz : float
        The drive's sample rate.
    k_fc_limit_v : float
        The largest K_fc the drive allows (its output limit u_max, at most 100 V).
    capture : {"raw", "stats", "both"}
        What the host records of each experiment (samples, the drive's line statistics).
    drive_settings : dict, optional
        The drive's settings for results['drive_settings'] (kp, kd, tau_d, fc_smooth, u_max).
    max_halvings : int
        How often the frequency may be halved when the loop cannot follow the sine (0: the
        tune at the configured frequency only).
    log : callable, optional
        Receives progress lines.

    Notes
    -----
    ``ask()`` gives the next :class:`ExperimentRequest` (None when the tune is finished),
    ``tell(request, measurement)`` hands back the :class:`Measurement` of that request,
    ``result()`` gives ``(results, data)``: results['tune'] without the plant's truth (see
    :func:`with_truth`) and the figure data. A key error found at a new frequency raises
    FftuneError from ``tell``.
    """

    def __init__(self, cfg, *, fs_hz, k_fc_limit_v, capture="raw", drive_settings=None,
                 max_halvings=MAX_FREQUENCY_HALVINGS, log=None):
        self.ctx = _Context(cfg, fs_hz, capture, k_fc_limit_v, drive_settings or {})
        self.requests = []
        self._result = None
        self._gen = _tune(self.ctx, int(max_halvings), log or (lambda s: None))
        self._advance(None)

    def _advance(self, measured):
        try:
            self._pending = self._gen.send(measured)
        except StopIteration as stop:
            self._pending, self._result = None, stop.value
        else:
            self.requests.append(self._pending)

    @property
    def done(self):
        return self._pending is None

    def ask(self):
        """The next :class:`ExperimentRequest`, or None when the tune is finished."""
        return self._pending

    def tell(self, request, measured):
        """The :class:`Measurement` of ``request`` (the one just asked)."""
        if self._pending is None:
            raise ValueError("tune strategy: finished, nothing was asked; read result()")
        if request is not self._pending and request != self._pending:
            raise ValueError(f"tune strategy: told {request.key!r}, but asked {self._pending.key!r}")
        self._advance(measured)

    def result(self):
        """``(results, data)`` once finished (results['tune'] without the truth, figure data)."""
        if self._result is None:
            raise ValueError("tune strategy: not finished; ask() for the next experiment")
        return self._result

    @property
    def experiments(self):
        """Experiments told so far at the current frequency."""
        return self.ctx.tune_experiments


def replay(strategy, load):
    """Drive ``strategy`` from recorded experiments alone: ``load(request)`` gives the
    :class:`Measurement` of a request (e.g. from its capture); raises ValueError naming the
    request's key when it has none. Returns ``strategy.result()``."""
    while (request := strategy.ask()) is not None:
        measured = load(request)
        if measured is None:
            raise ValueError(f"tune strategy replay: no capture of experiment {request.key!r}")
        strategy.tell(request, measured)
    return strategy.result()


def with_truth(results, fc_true_start_v, fc_true_end_v):
    """results['tune'] with the plant's truth (a simulated drive's Coulomb level, V, at the
    tune's start and end) and the error of K_fc* against the one at its end."""
    k_star = results.get("k_fc_star")
    results["true_coulomb_v"] = _f(fc_true_end_v)
    if "true_coulomb_v_at_start" in results:
        results["true_coulomb_v_at_start"] = _f(fc_true_start_v)
    results["k_fc_star_error_re_truth"] = (_f(k_star / fc_true_end_v - 1)
                                           if fc_true_end_v and k_star is not None else None)
    return results


# ---------------------------------------------------------------------------------------
# the model-based tune (`tune.method: model`) on the same protocol
# ---------------------------------------------------------------------------------------
N_LINES = 8          # lines k = 0 .. 8: the fit (n_fit <= 7) and the ratios (k <= 7)


def model_amplitude(c):
    """The identification amplitude: tune.model.amplitude_rad, or auto: 1 rad (pi with the
    position term: the level's variation over the revolution is told apart from the Coulomb
    level by sweeping a large part of it), not below a numeric tune.amplitude_rad."""
    a = c["model"]["amplitude_rad"]
    if a != "auto":
        return float(a)
    a = math.pi if "position" in c["terms"] else 1.0
    if c["amplitude_rad"] != "auto":
        a = max(a, float(c["amplitude_rad"]))
    return a


def model_plan(c):
    """The sine amplitudes the model tune of the tune keys ``c`` may ask for, each with the
    key that sets it: what the preflight (:func:`fftune.host.plan.preflight`) checks and
    what :class:`ModelTune` hands to the tune, so the two cannot differ.

    Returns
    -------
    dict
        ``amplitude`` the identification amplitude (:func:`model_amplitude`),
        ``amplitude_max`` the ceiling of its doubling (odd harmonics at the estimate:
        ``FeedForwardModelTune``), ``verify`` the verifying experiment's amplitude or None,
        ``checked`` [(key, amplitude_rad)]: the identification amplitude, the largest one the
        doubling can reach (when above it) and the verifying one; the half-amplitude
        experiment is below the first.
    """
    a = model_amplitude(c)
    a_max = max(a, float(c["amplitude_max_rad"]))
    top = a
    while 2 * top <= a_max:     # the tune's own rule (FeedForwardModelTune._next)
        top *= 2
    verify, verify_key = c["model"]["verify_amplitude_rad"], "tune.model.verify_amplitude_rad"
    if verify is None and c["amplitude_rad"] != "auto" and float(c["amplitude_rad"]) < 0.5 * a:
        verify, verify_key = float(c["amplitude_rad"]), "tune.amplitude_rad"   # the smaller one verifies
    # (auto: 1 rad or pi, raised to a larger numeric tune.amplitude_rad: that key then sets it)
    from_tune = c["model"]["amplitude_rad"] == "auto" and c["amplitude_rad"] != "auto" and \
        float(c["amplitude_rad"]) > (math.pi if "position" in c["terms"] else 1.0)
    checked = [("tune.amplitude_rad" if from_tune else "tune.model.amplitude_rad", a)]
    if top > a:
        checked.append(("tune.amplitude_max_rad", top))
    if verify is not None:
        checked.append((verify_key, float(verify)))
    return {"amplitude": a, "amplitude_max": a_max, "verify": None if verify is None else float(verify),
            "checked": checked}


def check_model_lines(c, fs_hz, src):
    """The lines k = 0 .. N_LINES the model tune reads lie below fs/2; returns the sine's
    cycles per period. Raises FftuneError naming tune.frequency_hz."""
    n = c["period_samples"]
    cycles = _cycles(fs_hz, n, c["frequency_hz"], f"{src}: key 'tune.frequency_hz'")
    if (N_LINES + 1) * cycles * 2 > n:
        raise FftuneError(f"{src}: key 'tune.frequency_hz': harmonic {N_LINES} of {c['frequency_hz']:g} Hz "
                          f"is above fs/2 (tune.method: model reads k = 0 .. {N_LINES})")
    return cycles


class ModelTune:
    """`tune.method: model` (:class:`fftune.analysis.ffmodel.FeedForwardModelTune`) on the
    protocol of :class:`SearchTune`: it asks for closed-loop sines with the feed-forward gains
    (K_fc, K_fa, K_v, K_ps, K_pc) and is told the records; the lines k = 0 .. 8 of the plant
    input and the motor angle go to the tune, per recorded period from raw samples, or their
    means from the drive's statistics. The same checks as every tune experiment (samples at
    u_max, motion) end it with the cause.

    Parameters
    ----------
    cfg : dict
        The validated configuration (``tune``; ``_source`` names it in errors).
    fs_hz : float
        The drive's sample rate.
    capture : {"raw", "stats", "both"}
    controller : dict or None
        kp, kd, tau_d of the drive's position controller (the Gauss-Newton part of sigma).
    gain_limits : dict or None
        (low, high) of the signed gains ``kfa``, ``kps``, ``kpc`` asked for (the drive's
        ranges within its output limit); None: the tune's defaults.
    """

    def __init__(self, cfg, *, fs_hz, capture="raw", controller=None, gain_limits=None):
        c = cfg["tune"]
        src = cfg.get("_source", "config")
        self.n = c["period_samples"]
        self.c = c
        self.cycles = check_model_lines(c, fs_hz, src)
        if capture != "raw" and N_LINES > _stats.STAT_K_MAX:
            raise FftuneError(f"{src}: tune.method model needs {N_LINES} harmonics, the drive's statistics hold "
                              f"{_stats.STAT_K_MAX}")
        omega = 2 * math.pi * c["frequency_hz"]
        plan = model_plan(c)
        self.amplitude = amplitude = plan["amplitude"]
        k_hi = c["search"]["k_fc_max"] or c["sweep"]["k_fc_max"]
        # the signed gains' limits (the drive's ranges and u_max) when the host knows them
        signed = {} if gain_limits is None else {"gain_limits": gain_limits}
        self.tuner = _ffmodel.FeedForwardModelTune(
            c["terms"], omega_rad_s=omega, amplitude_rad=amplitude, verify_amplitude_rad=plan["verify"],
            n_fit=c["model"]["n_fit"], rtol=c["model"]["rtol"], max_experiments=c["model"]["max_experiments"],
            k_fc_max=max(k_hi, 1e-3), k_v_max=c["viscous"]["k_v_max"], controller=controller,
            amplitude_max_rad=plan["amplitude_max"], **signed)
        self.stats_request = {"harmonics": N_LINES, "signals": ["motor_angle", "plant_input"],
                              "power": ["plant_input", "motor_angle", "error"]}
        self.rms, self.captures = {}, []
        self._exp = self._request = None

    def ask(self):
        """The next :class:`ExperimentRequest`, or None when the tune is finished."""
        if self._request is not None:
            return self._request
        if self.tuner.done:
            return None
        exp = self.tuner.ask()
        if exp is None:
            return None
        g = exp.gains
        key = (f"tune-model-{exp.index}-{exp.tag}-a{exp.amplitude_rad:.6g}-"
               + "-".join(f"{k}{g[k]:.9g}" for k in _ffmodel.GAINS))
        c = self.c
        self._exp = exp
        self._request = ExperimentRequest(
            key=key, tag=exp.tag, amplitude_rad=float(exp.amplitude_rad),
            gains={k: float(g[k]) for k in ("kfc", "kv", "kfa", "kps", "kpc")},
            frequency_hz=float(c["frequency_hz"]), period_samples=int(self.n), cycles=int(self.cycles),
            settle_periods=int(c["settle_periods"]), periods=int(c["periods"]), stats=self.stats_request,
            index=int(exp.index))
        return self._request

    def tell(self, request, measured):
        """The :class:`Measurement` of ``request`` (the one just asked)."""
        if self._request is None:
            raise ValueError("tune strategy: finished, nothing was asked; read result()")
        if request is not self._request and request != self._request:
            raise ValueError(f"tune strategy: told {request.key!r}, but asked {self._request.key!r}")
        exp, n = self._exp, self.n
        self._request = self._exp = None
        rec, u_max = measured.record, measured.u_max_v
        sat = u_rms_re_max = None
        if rec.stats is not None:
            st = rec.stats
            U = np.concatenate([[st.power_mean["plant_input"]], 2.0 / n * st.mean["plant_input"][:N_LINES]])
            Y = np.concatenate([[st.power_mean["motor_angle"]], 2.0 / n * st.mean["motor_angle"][:N_LINES]])
            self.rms[exp.index] = st.rms("error")
            r_mean = st.power_mean["motor_angle"] + st.power_mean["error"]
            # period-to-period variance of the plant input's lines (the mean's: unknown, that
            # of the fundamental stands in), scaled as the lines
            var_u = (2.0 / n) ** 2 * np.asarray(st.var["plant_input"][:N_LINES], dtype=float)
            line_var, n_periods = np.concatenate([[var_u[0] / 4.0], var_u]), st.periods
            if u_max:
                u_rms_re_max = st.rms("plant_input") / u_max
        else:
            s = rec.signals
            U = _ffmodel.harmonic_lines(s["plant_input"], n, self.cycles, N_LINES)
            Y = _ffmodel.harmonic_lines(s["motor_angle"], n, self.cycles, N_LINES)
            self.rms[exp.index] = float(np.sqrt(np.mean(s["error"] ** 2)))
            r_mean = float(np.mean(s["reference"])) if "reference" in s else None
            line_var = n_periods = None
            sat = _saturation_fraction(s["plant_input"], u_max)
        h1 = float(abs(np.mean(np.atleast_2d(Y)[:, 1]))) / exp.amplitude_rad
        check = _tuning.check_experiment(h1, saturated_fraction=sat, u_rms_re_max=u_rms_re_max,
                                         amplitude_rad=exp.amplitude_rad, u_max_v=u_max)
        self.captures.append({"key": request.key, "tag": exp.tag, "amplitude_rad": exp.amplitude_rad,
                              "gains": dict(exp.gains)})
        if check["cause"] is not None:
            self.tuner.fail(exp, check["cause"], check["text"])
        else:
            self.tuner.tell(exp, U, Y, reference_mean_rad=r_mean, line_var=line_var, n_periods=n_periods)

    def result(self):
        """``(results, None)``: results['tune'] of the model-based tune without the truth
        (:func:`with_truth`)."""
        if not self.tuner.done:
            raise ValueError("tune strategy: not finished; ask() for the next experiment")
        r = self.tuner.result
        c = self.c
        rms = self.rms
        terms = {name: {k: (_f(v) if isinstance(v, float) else v) for k, v in t.items() if k != "parts"}
                 | {"parts": {k: _f(v) for k, v in t["parts"].items()}}
                 for name, t in r["terms"].items()}
        coul = r["terms"].get("coulomb")
        converged = bool(r["converged"])
        k_star = coul["value"] if coul else None
        its = r["iterations"]
        first = 0 if its else None
        ver = next((i for i in range(len(its) - 1, -1, -1) if its[i]["tag"] == r["verification"]["tag"]), None) \
            if r["verification"] else None
        return {
            "method": "model",
            "frequency_hz": c["frequency_hz"], "amplitude_rad": _f(self.amplitude),
            "terms": terms,
            "experiments": r["experiments"],
            "odd_ratio_at_optimum": _f(r["odd_ratio_at_optimum"]),
            "even_ratio_at_optimum": _f(r["even_ratio_at_optimum"]),
            "model": {
                "method": "least squares of the plant input's lines on the terms' regressors along the motion "
                          "and a rigid body, iterated at the estimate (fftune.analysis.ffmodel)",
                "converged": converged, "stop_reason": r["reason"], "cause": r["cause"],
                "gains": None if r["gains"] is None else {k: _f(v) for k, v in r["gains"].items()},
                "inertia_v_s2_per_rad": _f(r["inertia_v_s2_per_rad"]),
                "gauss_newton_step_at_half_amplitude": None if not r.get("gauss_newton_step") else
                {k: _f(v) for k, v in r["gauss_newton_step"].items()},
                "verification": r["verification"],
                "experiments": [dict(cap, odd_ratio=_f(it["odd_ratio"]), even_ratio=_f(it["even_ratio"]),
                                     rms_error_rad=_f(rms.get(i)),
                                     estimate=None if it["estimate"] is None else
                                     {k: _f(v) for k, v in it["estimate"].items()},
                                     fit_residual_rel=_f(it["fit_residual_rel"]))
                                for i, (cap, it) in enumerate(zip(self.captures, its))],
            },
            # the keys the report and the pipeline read for every method
            "search": {"converged": converged, "stop_reason": r["reason"], "cause": r["cause"],
                       "sigma_v": _f(coul["sigma"]) if coul and converged else None,
                       "sigma_parts_v": {k: _f(v) for k, v in coul["parts"].items()} if coul and converged
                       else None,
                       "relative_to_sweep_optimum": None, "experiments": r["experiments"]},
            "sweep": None, "viscous": None,
            "k_fc_star": _f(k_star) if converged else None,
            "k_fc_best_measured": _f(k_star),
            "ratio_at_zero": _f(r["odd_ratio_at_start"]),
            "ratio_at_k_fc_star": _f(r["odd_ratio_at_optimum"]),
            "ratio_improvement": _f(r["odd_ratio_at_start"] / r["odd_ratio_at_optimum"])
            if r["odd_ratio_at_start"] and r["odd_ratio_at_optimum"] else None,
            "rms_error_rad": {"k_fc_0": _f(rms.get(first)) if first is not None else None,
                              "k_fc_star": _f(rms.get(ver)) if ver is not None else None,
                              "sweep_min": None, "sweep_min_at_k_fc": None},
            "true_coulomb_v": None,
            "k_fc_star_error_re_truth": None,
        }, None
