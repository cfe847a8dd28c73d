"""The direct simulation path of friction tracking (issue 26) for tests and benchmarks: the
drive core + plant through ctypes (firmware_sim/tests/fwsim.py), no CAN bus, the same
estimator and tracker as ``fftune track`` (fftune.analysis.track)."""
import ctypes
import os
import sys

import numpy as np
import yaml

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
                 settings=None, track_k_v=False, settle=0, correct_noise=True, watch_viscous=True,
                 friction_met=False):
    """Track over ``tasks`` repetitions; rows of dicts (k_fc in effect, estimate, sigma,
    truth at the task's end, action) and the last decision. ``correct_noise``: the sensor
    noise's bias removed (the drive's PD gains give the noise gain); ``watch_viscous``: a
    viscous change with K_v held detected and taken into the fit (as ``fftune track``).
    ``friction_met``: each row also has ``k_fc_met``, the friction the task met
    (:func:`friction_met_v`, from the plant's state at every sample boundary; slower)."""
    rows = []
    with open(plant, encoding="utf-8") as fh:
        plant_params = yaml.safe_load(fh)["plant"]
    with FwSim(plant) as sim:
        sim.configure(task_mode=mode, exc_kind=0, exc_settle_periods=settle, exc_record_periods=1,
                      rec_signals=0x03 if friction_met else 0, **(task or DEMO_TASK))
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
            met = None
            if friction_met:
                states = []
                for _ in range(n * (1 + settle)):
                    states.append(sim.plant_state())
                    sim.run(1)
                states.append(sim.plant_state())
            sim.run_until_idle()
            if friction_met:
                rec, _ = sim.record()
                met = friction_met_v(plant_params, np.array(states[-(n + 1):]), rec[-n:, 0], rec[-n:, 1], fs)
            try:
                est = estimate_task(task_stats(sim), k_v_hold=tr.k_v, hold_k_v=not track_k_v,
                                    recent_k_fc=recent, noise_gain=gain,
                                    recent=recent_est if watch_viscous else None, k_fc_applied=applied)
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
                         "k_fc_sigma_viscous": est.k_fc_sigma_viscous if ok else None,
                         "k_fc_sigma_model": est.k_fc_sigma_model if ok else None,
                         "k_fc_sigma_split": est.k_fc_sigma_split if ok else None,
                         "notes": list(est.notes) if ok else [],
                         "cause": decision.cause,
                         "k_v_shift": est.k_v_shift if ok else None,
                         "k_v_free": est.k_v_free if ok else None,
                         "sensor_noise_rad": est.sensor_noise_rad if ok else None,
                         "k_fc_noise_correction": est.k_fc_noise_correction if ok else None,
                         "rms_error": est.rms_error if ok else None,
                         "rms_residual": est.rms_residual if ok else None,
                         "k_fc_true": sim.truth("SIM_FC_VOLT"), "k_fc_met": met,
                         "action": decision.action})
            if decision.action == "stop":
                break
    return rows, decision


def friction_met_v(plant, states, reference_rad, u_v, fs_hz):
    """The friction one repetition met, as the estimator defines K_fc, computed from the
    plant's own state (not from the drive's sums): per sample the motor-side friction torque
    averaged over the sample (the friction law at the motor's velocity while it slides,
    with the Stribeck rise; the torque that holds it while it sticks), from the plant's
    momentum balance over the sample with its input u held (the drive's zero-order hold):
    J1 dw1 = T (k_m u - <spring> - <friction> - b <w1>), J2 dw2 = T (<spring> - b2 <w2>),
    <w> = d theta / T, so

        <friction> = k_m u - (J1 dw1 + J2 dw2) / T - (b dth1 + b2 dth2) / T,

    exact whatever the motor does inside the sample (sticks, breaks away, jitters with the
    sensor noise); projected on the Coulomb regressors p, n and the acceleration a_r of the
    reference (central differences), K_fc = (F_+ + F_-) / 2 in input volts. ``plant`` the
    plant section ({j1, j2, km, viscous, load_viscous}), ``states`` (N + 1, 4) th1 w1 th2 w2
    at each sample's start and the last sample's end, ``reference_rad`` and ``u_v`` (N,)
    the recorded reference and plant input. This is the truth of what ``track`` tracks
    where the friction depends on the speed (a Stribeck rise): the level the task's own
    motion meets, below the plain average along the reference (the motor sticks where the
    reference is slowest). (The first version read the friction law at each sample's start
    only: under sensor noise, where the input jumps every sample and the motor breaks away
    and sticks within one, that read the Stribeck rise 2.8 % too high at 5e-3 rad.)"""
    p = {k: float(plant.get(k, 0.0)) for k in ("j1", "j2", "km", "viscous", "load_viscous")}
    x = np.asarray(states, dtype=float)
    u = np.asarray(u_v, dtype=float)
    if x.shape != (u.size + 1, 4):
        raise ValueError(f"states: expected shape ({u.size + 1}, 4) (each sample's start and the last "
                         f"one's end), got {x.shape}")
    d = np.diff(x, axis=0) * float(fs_hz)      # per sample: d th1 / T, d w1 / T, d th2 / T, d w2 / T
    fric = (p["km"] * u - p["j1"] * d[:, 1] - p["j2"] * d[:, 3]
            - p["viscous"] * d[:, 0] - p["load_viscous"] * d[:, 2])
    vr = np.gradient(np.asarray(reference_rad, dtype=float)) * fs_hz
    ar = np.gradient(vr) * fs_hz
    s = np.sign(np.round(vr, 6))
    X = np.column_stack([np.maximum(s, 0), np.minimum(s, 0), ar])
    th = np.linalg.lstsq(X, fric / p["km"], rcond=None)[0]
    return float(0.5 * (th[0] + th[1]))
