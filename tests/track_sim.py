"""The direct simulation path of friction tracking (issue 26) for tests and benchmarks: the
drive core + plant through ctypes (firmware_sim/tests/fwsim.py), no CAN bus, the same
estimator and tracker as ``fftune track`` (fftune.analysis.track)."""
import ctypes
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "firmware_sim", "tests"))
from fwsim import FwSim  # noqa: E402

from fftune.analysis.track import (NotIdentifiable, Tracker, TrackSettings,  # noqa: E402
                                   estimate_task, parse_task_stats, sensor_noise_gain)

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")
DEMO_TASK = dict(task_distance=1.0, task_v_max=4.0, task_a_max=40.0, task_jerk=800.0, task_dwell=0.2)


def task_stats_bytes(sim, design, last=False):
    """Object 0x2062 (design=True) or 0x2061 as bytes, straight from the drive core;
    last=True: 0x2064 / 0x2063 (the last latched repetition)."""
    lib = sim.lib
    lib.drv_task_stats_size_bytes.restype = ctypes.c_uint32
    lib.drv_task_stats_size_bytes.argtypes = [ctypes.c_void_p, ctypes.c_uint32]
    lib.drv_task_stats_read.restype = ctypes.c_int
    lib.drv_task_stats_read.argtypes = [ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_char_p,
                                        ctypes.c_uint32]
    part = (1 if design else 0) + (2 if last else 0)
    n = lib.drv_task_stats_size_bytes(sim.drv, part)
    buf = ctypes.create_string_buffer(n)
    st = lib.drv_task_stats_read(sim.drv, part, 0, buf, n)
    if st != 0:
        raise RuntimeError(f"drv_task_stats_read: status {st}")
    return buf.raw[:n]


def task_stats(sim, last=False):
    return parse_task_stats(task_stats_bytes(sim, True, last), task_stats_bytes(sim, False, last))


def plant_file(tmp_dir, name="plant.yaml", base=TWOMASS, sensor=None, drift=None):
    """plant_twomass.yaml with sensor values replaced and a drift section appended."""
    lines = []
    with open(base, encoding="utf-8") as fh:
        section = None
        for line in fh:
            s = line.split("#")[0].rstrip()
            if s and not s.startswith(" "):
                section = s.rstrip(":")
            elif s and section == "sensor" and sensor:
                key = s.strip().split(":")[0]
                if key in sensor:
                    line = f"  {key}: {sensor[key]!r}\n"
            lines.append(line)
    if drift:
        lines.append("drift:\n")
        lines += [f"  {k}: {v!r}\n" for k, v in drift.items()]
    path = os.path.join(tmp_dir, name)
    with open(path, "w", encoding="utf-8") as fh:
        fh.writelines(lines)
    return path


def run_tracking(plant, tasks, k_fc=0.1157, k_v=0.002, k_a=0.0062, task=None, mode=1,
                 settings=None, track_k_v=False, settle=0, correct_noise=True, watch_viscous=True):
    """Track over ``tasks`` repetitions; rows of dicts (k_fc in effect, estimate, sigma,
    truth at the task's end, action) and the last decision. ``correct_noise``: the sensor
    noise's bias removed (the drive's PD gains give the noise gain); ``watch_viscous``: a
    viscous change with K_v held detected and taken into the fit (as ``fftune track``)."""
    rows = []
    with FwSim(plant) as sim:
        sim.configure(task_mode=mode, exc_kind=0, exc_settle_periods=settle, exc_record_periods=1,
                      rec_signals=0, **(task or DEMO_TASK))
        sim.enable()
        tr = Tracker(k_fc=k_fc, k_v=k_v, k_a=k_a, settings=settings or TrackSettings(update_kv=track_k_v))
        n = sim.get("TASK_PERIOD")
        fs = sim.get("FS")
        decision = None
        recent, recent_est = [], []
        gain = sensor_noise_gain(sim.get("KP"), sim.get("KD"), sim.get("TAU_D"), fs) if correct_noise else None
        for k in range(tasks):
            sim.set("KFC", tr.k_fc)
            sim.set("KV", tr.k_v)
            sim.set("TASK_KA", tr.k_a)
            applied = tr.k_fc
            sim.start()
            sim.run_until_idle()
            try:
                est = estimate_task(task_stats(sim), k_v_hold=tr.k_v, hold_k_v=not track_k_v,
                                    recent_k_fc=recent, noise_gain=gain,
                                    recent=recent_est if watch_viscous else None)
                recent.append(est.k_fc)
                recent_est.append(est)
            except NotIdentifiable as exc:
                est = exc
            decision = tr.after_task(est)
            ok = not isinstance(est, NotIdentifiable)
            rows.append({"task": k, "t_s": (k + 1) * (1 + settle) * n / fs, "k_fc": applied,
                         "k_fc_estimate": est.k_fc if ok else None,
                         "k_fc_sigma": est.k_fc_sigma if ok else None,
                         "k_fc_sigma_stat": est.k_fc_sigma_stat if ok else None,
                         "notes": list(est.notes) if ok else [],
                         "cause": decision.cause,
                         "k_v_shift": est.k_v_shift if ok else None,
                         "k_v_free": est.k_v_free if ok else None,
                         "sensor_noise_rad": est.sensor_noise_rad if ok else None,
                         "rms_error": est.rms_error if ok else None,
                         "rms_residual": est.rms_residual if ok else None,
                         "k_fc_true": sim.truth("SIM_FC_VOLT"), "action": decision.action})
            if decision.action == "stop":
                break
    return rows, decision
