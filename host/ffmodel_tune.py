"""`tune.method: model`: executes and records the experiments the model-based tune of
:mod:`fftune.analysis.ffmodel` asks for (the decisions and every estimate live there).

Each experiment is a closed-loop sine at the reference with the feed-forward gains asked
for (K_fc, K_fa, K_v, K_ps, K_pc); the lines k = 0 .. 8 of the plant input and the motor
angle go back to the tune, per recorded period from raw samples, or their means from the
drive's statistics (harmonics of both signals, and their means as power statistics). The
same checks as every tune experiment (samples at u_max, motion) end it with the cause.
"""
import math

import numpy as np

from fftune.analysis import ffmodel as _ffmodel
from fftune.analysis import tuning as _tuning
from fftune.analysis.errors import FftuneError
from fftune.analysis.stats import STAT_K_MAX

N_LINES = 8          # lines k = 0 .. 8: the fit (n_fit <= 7) and the ratios (k <= 7)


def _f(x):
    return None if x is None or not math.isfinite(x) else float(x)


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
    what :func:`run_model_tune` hands to the tune, so the two cannot differ.

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
    from fftune.host.experiments import _cycles
    n = c["period_samples"]
    cycles = _cycles(fs_hz, n, c["frequency_hz"], f"{src}: key 'tune.frequency_hz'")
    if (N_LINES + 1) * cycles * 2 > n:
        raise FftuneError(f"{src}: key 'tune.frequency_hz': harmonic {N_LINES} of {c['frequency_hz']:g} Hz "
                          f"is above fs/2 (tune.method: model reads k = 0 .. {N_LINES})")
    return cycles


def signed_gain_limits(u_max_v):
    """(low, high) of K_fa, K_ps, K_pc the model tune may ask for: the range of their drive
    objects (configs/od.yaml, 0x2000:9 .. 11) within +-u_max_v (None: not known), so no
    request is refused by the drive nor alone exceeds its output."""
    from fftune.host.config import od_param_high
    out = {}
    for alias in ("kfa", "kps", "kpc"):
        high = od_param_high(alias.upper())
        if u_max_v is not None:
            high = min(high, float(u_max_v))
        out[alias] = (-high, high)
    return out


def run_model_tune(session):
    """results['tune'] and the figure data (None) of `tune.method: model`. The session's
    preflight (:func:`fftune.host.plan.preflight`) has checked what it asks for
    (:func:`model_plan`)."""
    from fftune.host.experiments import _run_u_max, _saturation_fraction, k_fc_limit, sine_request
    c = session.cfg["tune"]
    src = session.cfg.get("_source", "config")
    n = c["period_samples"]
    cycles = check_model_lines(c, session.fs_hz, src)
    capture = session.capture_mode("tune")
    if capture != "raw" and N_LINES > STAT_K_MAX:
        raise FftuneError(f"{src}: tune.method model needs {N_LINES} harmonics, the drive's statistics hold "
                          f"{STAT_K_MAX}")
    omega = 2 * math.pi * c["frequency_hz"]
    plan = model_plan(c)
    amplitude, verify = plan["amplitude"], plan["verify"]
    k_hi = c["search"]["k_fc_max"] or c["sweep"]["k_fc_max"]
    ctl = session.controller
    if ctl.get("kp") is None:
        try:
            ctl = dict(ctl, **{k: session.drive.get(k) for k in ("kp", "kd", "tau_d")})
        except (AttributeError, FftuneError):
            pass
    controller = {k: float(ctl.get(k) or 0.0) for k in ("kp", "kd", "tau_d")} if ctl.get("kp") else None
    tuner = _ffmodel.FeedForwardModelTune(
        c["terms"], omega_rad_s=omega, amplitude_rad=amplitude, verify_amplitude_rad=verify,
        n_fit=c["model"]["n_fit"], rtol=c["model"]["rtol"], max_experiments=c["model"]["max_experiments"],
        k_fc_max=max(k_hi, 1e-3), k_v_max=c["viscous"]["k_v_max"], controller=controller,
        amplitude_max_rad=plan["amplitude_max"], gain_limits=signed_gain_limits(k_fc_limit(session)))
    stats_request = {"harmonics": N_LINES, "signals": ["motor_angle", "plant_input"],
                     "power": ["plant_input", "motor_angle", "error"]}
    session.tune_experiments = 0
    measured_before = session.counts["measured"]
    rms = {}
    captures = []
    while not tuner.done:
        exp = tuner.ask()
        if exp is None:
            break
        g = exp.gains
        key = (f"tune-model-{exp.index}-{exp.tag}-a{exp.amplitude_rad:.6g}-"
               + "-".join(f"{k}{g[k]:.9g}" for k in _ffmodel.GAINS))
        req = sine_request(inject="reference", amplitude_peak=exp.amplitude_rad, n=n, cycles=cycles,
                           settle=c["settle_periods"], periods=c["periods"], kfc=g["kfc"], kv=g["kv"])
        req.update(kfa=g["kfa"], kps=g["kps"], kpc=g["kpc"])
        rec = session.run("tune", key, req, stats=stats_request)
        session.tune_experiments += 1
        u_max = _run_u_max(session, rec)
        sat = u_rms_re_max = None
        if rec.stats is not None:
            st = rec.stats
            U = np.concatenate([[st.power_mean["plant_input"]], 2.0 / n * st.mean["plant_input"][:N_LINES]])
            Y = np.concatenate([[st.power_mean["motor_angle"]], 2.0 / n * st.mean["motor_angle"][:N_LINES]])
            rms[exp.index] = st.rms("error")
            r_mean = st.power_mean["motor_angle"] + st.power_mean["error"]
            # period-to-period variance of the plant input's lines (the mean's: unknown, that
            # of the fundamental stands in), scaled as the lines
            var_u = (2.0 / n) ** 2 * np.asarray(st.var["plant_input"][:N_LINES], dtype=float)
            line_var, n_periods = np.concatenate([[var_u[0] / 4.0], var_u]), st.periods
            if u_max:
                u_rms_re_max = st.rms("plant_input") / u_max
        else:
            s = rec.signals
            U = _ffmodel.harmonic_lines(s["plant_input"], n, cycles, N_LINES)
            Y = _ffmodel.harmonic_lines(s["motor_angle"], n, cycles, N_LINES)
            rms[exp.index] = float(np.sqrt(np.mean(s["error"] ** 2)))
            r_mean = float(np.mean(s["reference"])) if "reference" in s else None
            line_var = n_periods = None
            sat = _saturation_fraction(s["plant_input"], u_max)
        h1 = float(abs(np.mean(np.atleast_2d(Y)[:, 1]))) / exp.amplitude_rad
        check = _tuning.check_experiment(h1, saturated_fraction=sat, u_rms_re_max=u_rms_re_max,
                                         amplitude_rad=exp.amplitude_rad, u_max_v=u_max)
        captures.append({"key": key, "tag": exp.tag, "amplitude_rad": exp.amplitude_rad, "gains": dict(g)})
        if check["cause"] is not None:
            tuner.fail(exp, check["cause"], check["text"])
        else:
            tuner.tell(exp, U, Y, reference_mean_rad=r_mean, line_var=line_var, n_periods=n_periods)
    if session.counts["measured"] > measured_before:
        # the extra gains back to 0 (the other steps' requests set K_fc and K_v only); a tune
        # read back from its captures alone leaves the drive untouched
        session.drive.set_parameters({"kfa": 0.0, "kps": 0.0, "kpc": 0.0})
    return _results(session, tuner, captures, rms, amplitude), None


def _results(session, tuner, captures, rms, amplitude):
    r = tuner.result
    c = session.cfg["tune"]
    truth = session.truth or {}
    fc_true = truth.get("sim_fc_volt")
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
        "frequency_hz": c["frequency_hz"], "amplitude_rad": _f(amplitude),
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
                            for i, (cap, it) in enumerate(zip(captures, its))],
        },
        # the keys the report and the pipeline read for every method
        "search": {"converged": converged, "stop_reason": r["reason"], "cause": r["cause"],
                   "sigma_v": _f(coul["sigma"]) if coul and converged else None,
                   "sigma_parts_v": {k: _f(v) for k, v in coul["parts"].items()} if coul and converged else None,
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
        "true_coulomb_v": _f(fc_true),
        "k_fc_star_error_re_truth": _f(k_star / fc_true - 1) if fc_true and converged and k_star else None,
    }
