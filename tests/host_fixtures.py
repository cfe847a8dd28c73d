"""Host test helpers: a Python TEST DOUBLE of the drive, and drive_sim process helpers.

``FakeDriveForTests`` implements the :class:`fftune.host.drive.DriveClient` interface the
experiments use (identity, get/set/read_parameters, plant_truth, enable, run) with a
Python simulation of a single mass with Coulomb + viscous friction and stiction under the
drive's controller law (firmware_sim/core/ctl.h: PD with backward-Euler filtered
derivative, K_fc sgn(v_r) + K_v v_r feed-forward, saturation). It exists so the
experiment logic can be unit-tested without the CANopen node; it is never used by the
product. The end-to-end tests use the real ``drive_sim``.
"""
import math
import os
import socket
import subprocess
import time
import zlib

import numpy as np

from fftune.analysis.errors import FftuneError
from fftune.analysis.multisine import drive_multisine
from fftune.host.drive import RunRecord
from fftune.host.odmap import PARAMS, SIGNAL_BITS

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
DRIVE_SIM = os.path.join(REPO, "firmware_sim", "build", "drive_sim")
EDS = os.path.join(REPO, "firmware_sim", "build", "gen", "fftune_drive.eds")


class FakeDriveForTests:
    """Plant J ddq = u - Fc sgn(dq) - Fv dq (all in volts), sticking while |u| <= Fs."""

    def __init__(self, fc_volt=0.3, fv_volt=0.0, fs_volt=None, inertia_v=0.002, noise_std=0.0,
                 fs_hz=2560.0, substeps=4, seed=0):
        self.fc, self.fv = fc_volt, fv_volt
        self.fstat = fc_volt if fs_volt is None else fs_volt
        self.j, self.noise = inertia_v, noise_std
        self.substeps = substeps
        self.seed = seed
        self.params = {a: 0 for a in PARAMS}
        self.params.update(kp=20.0, kd=0.4, tau_d=0.0005, kfc=0.0, kv=0.0, fc_smooth=0.0, u_max=10.0,
                           fs=fs_hz, exc_kind=0, exc_inject=0, exc_amplitude=0.0, exc_offset=0.0,
                           exc_period=2048, exc_sine_cycles=1, exc_settle_periods=1,
                           exc_record_periods=1, ms_k_min=1, ms_k_max=99, ms_group=5, ms_seed=1,
                           ms_realization=0, rec_signals=0x07)
        self.runs = 0
        self.enabled = False
        self.calls = []

    # interface of fftune.host.drive.DriveClient
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        pass

    def identity(self):
        return {"vendor_id": 0xFF7, "product_code": 1, "revision": 0x10000, "serial": 0,
                "firmware_version": "test-double", "device_name": "FakeDriveForTests",
                "node_id": 1, "bus": "none (test double)"}

    def plant_truth(self):
        return {"sim_fc_volt": self.fc, "sim_fv_volt": self.fv, "sim_fs_volt": self.fstat,
                "sim_noise_std": self.noise, "sim_fc_torque": self.fc}

    def enable(self):
        self.enabled = True

    def get(self, name):
        return self.params[name]

    def set(self, name, value):
        if name not in self.params:
            raise FftuneError(f"no object named '{name}'")
        self.params[name] = value

    def set_parameters(self, values):
        for k, v in values.items():
            self.set(k, v)

    def read_parameters(self):
        return {k: v for k, v in self.params.items()
                if not k.startswith(("sim_", "meas_"))}

    def _excitation(self, n_total):
        p = self.params
        n = int(p["exc_period"])
        idx = np.arange(n_total)
        if p["exc_kind"] == 1:
            w = 2 * np.pi * int(p["exc_sine_cycles"]) / n
            x = p["exc_amplitude"] * np.sin(w * idx) + p["exc_offset"]
            v = p["exc_amplitude"] * w * p["fs"] * np.cos(w * idx)
        elif p["exc_kind"] == 3:
            one = drive_multisine(n, int(p["ms_k_min"]), int(p["ms_k_max"]), int(p["ms_group"]),
                                  int(p["ms_seed"]), int(p["ms_realization"]), float(p["exc_amplitude"]))
            x = np.tile(one, n_total // n) + p["exc_offset"]
            v = np.diff(x, prepend=x[-1]) * p["fs"]
        else:
            x = np.zeros(n_total)
            v = np.zeros(n_total)
        return x, v

    def run(self, parameters, signals=("reference", "plant_input", "motor_angle", "error"), desc="run"):
        self.set_parameters(parameters)
        self.calls.append(dict(parameters))
        p = self.params
        if not self.enabled:
            raise FftuneError("run refused: not enabled")
        t0 = time.time()
        n = int(p["exc_period"])
        settle, rec = int(p["exc_settle_periods"]), int(p["exc_record_periods"])
        n_total = (settle + rec) * n
        exc, exc_v = self._excitation(n_total)
        exc, exc_v = exc.tolist(), exc_v.tolist()
        inject_ref = int(p["exc_inject"]) == 0
        ts = 1.0 / p["fs"]
        h = ts / self.substeps
        kp, kd, tau, kfc, kv, umax = (p["kp"], p["kd"], p["tau_d"], p["kfc"], p["kv"], p["u_max"])
        d_pole, d_gain = tau / (tau + ts), kd / (tau + ts)
        q = dq = 0.0
        e_prev, dstate = 0.0, 0.0
        j, fc, fv, fst = self.j, self.fc, self.fv, self.fstat
        out = np.zeros((n_total, 5))
        # Noise seeded by the run's parameters: the same request gives the same record.
        seed_items = sorted((k, v) for k, v in p.items() if k != "run_counter")
        rng = np.random.default_rng([self.seed, zlib.crc32(repr(seed_items).encode())])
        noise = (rng.normal(0.0, self.noise, n_total) if self.noise else np.zeros(n_total)).tolist()
        for i in range(n_total):
            r = exc[i] if inject_ref else 0.0
            vr = exc_v[i] if inject_ref else 0.0
            uadd = 0.0 if inject_ref else exc[i]
            qm = q + noise[i]
            e = r - qm
            dstate = d_pole * dstate + d_gain * (e - e_prev) if i else 0.0
            e_prev = e
            sg = (vr > 0) - (vr < 0)
            u = kp * e + dstate + kfc * sg + kv * vr + uadd
            u = max(-umax, min(umax, u))
            for _ in range(self.substeps):
                if dq == 0.0 and abs(u) <= fst:
                    continue                      # stuck
                drive_f = u - fv * dq
                if dq != 0.0:
                    fr = fc if dq > 0 else -fc
                else:
                    fr = fc if u > 0 else -fc
                dq_new = dq + h * (drive_f - fr) / j
                if dq != 0.0 and dq_new * dq < 0.0 and abs(u) <= fst:
                    dq_new = 0.0                  # velocity reversal while the force cannot break away
                q += h * 0.5 * (dq + dq_new)
                dq = dq_new
            out[i] = (r, u, qm, 0.0, e)
        keep = out[settle * n:]
        mask = 0
        for s in signals:
            mask |= 1 << SIGNAL_BITS[s]
        p["rec_signals"] = mask
        order = [s for s, b in sorted(SIGNAL_BITS.items(), key=lambda kv: kv[1]) if mask >> b & 1]
        sig = {s: keep[:, SIGNAL_BITS[s]].astype(np.float32).astype(np.float64) for s in order}
        self.runs += 1
        p["run_counter"] = self.runs
        return RunRecord(signals=sig, parameters=self.read_parameters(), fs_hz=float(p["fs"]),
                         period_samples=n, settle_periods=settle, record_periods=rec,
                         run_counter=self.runs, t_start=t0, t_end=time.time())


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def drive_sim_missing_reason():
    """None if drive_sim and its EDS are built, else why not (for pytest.skip)."""
    if not os.path.exists(DRIVE_SIM):
        return f"drive_sim not built ({DRIVE_SIM} missing; the CANopen node is another issue)"
    if not os.path.exists(EDS):
        return f"EDS not generated ({EDS} missing)"
    return None
