"""`tune.method: model`: executes and records the experiments the model-based tune asks for
(:class:`fftune.analysis.tune_strategy.ModelTune` around
:class:`fftune.analysis.ffmodel.FeedForwardModelTune`: the decisions, the line reduction, the
checks and every estimate live there).

Each experiment is a closed-loop sine at the reference with the feed-forward gains asked
for (K_fc, K_fa, K_v, K_ps, K_pc), run and recorded by the session (raw samples, or the
drive's statistics: harmonics of the plant input and the motor angle, and their means as
power statistics).
"""
from fftune.analysis import tune_strategy as _ts
from fftune.analysis.errors import FftuneError
# the plan the preflight checks and the tune asks for (one source: fftune.analysis.tune_strategy)
from fftune.analysis.tune_strategy import N_LINES, check_model_lines, model_amplitude, model_plan  # noqa: F401


def _controller(session):
    """kp, kd, tau_d of the drive's position controller (the configuration's, else read from
    the drive), or None when unknown."""
    ctl = session.controller
    if ctl.get("kp") is None:
        try:
            ctl = dict(ctl, **{k: session.drive.get(k) for k in ("kp", "kd", "tau_d")})
        except (AttributeError, FftuneError):
            pass
    return {k: float(ctl.get(k) or 0.0) for k in ("kp", "kd", "tau_d")} if ctl.get("kp") else None


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
    """results['tune'] and the figure data (None) of `tune.method: model`."""
    from fftune.host.experiments import execute, k_fc_limit
    strategy = _ts.ModelTune(session.cfg, fs_hz=session.fs_hz, capture=session.capture_mode("tune"),
                             controller=_controller(session),
                             gain_limits=signed_gain_limits(k_fc_limit(session)))
    session.tune_experiments = 0
    measured_before = session.counts["measured"]
    results, data = execute(session, strategy)
    if session.counts["measured"] > measured_before:
        # the extra gains back to 0 (the other steps' requests set K_fc and K_v only); a tune
        # read back from its captures alone leaves the drive untouched
        session.drive.set_parameters({"kfa": 0.0, "kps": 0.0, "kpc": 0.0})
    fc = (session.truth or {}).get("sim_fc_volt")
    return _ts.with_truth(results, fc, fc), data
