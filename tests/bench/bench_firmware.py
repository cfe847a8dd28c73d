"""Benchmark: closed-loop simulation rate of firmware_sim (C: simulated plant + drive core)
beside a scipy solve_ivp simulation of the same loop, as a ratio, measured in the same run.

Both sides run ONE configuration: configs/plant_twomass.yaml with the Coulomb feed-forward
set to the plant's friction (K_fc = Fc / km, the tuned operating point, so the feed-forward
path runs on both sides), sine reference 0.5 rad at 1 Hz, encoder quantisation of the
config. C: build/bench_fw rate (free run, -O2; median of 5 x 2e6 steps). scipy: what a
Python user would reach for: per controller step the same PD (backward-Euler filtered
derivative) + K_fc sgn(v_r) + K_v v_r law on the quantised motor angle, saturated, then
solve_ivp (RK45, rtol 1e-8) over the step with the input held and friction
Fc sign(w1) + viscous; median of 3 runs of 1 s simulated. Remaining difference: the C
plant detects stick/slip events (static friction), scipy's sign() chatters through them.
Rates are controller steps of simulated time per CPU second of the process (one core; the
machine is shared, so wall-clock rates measure the other load too and are printed beside).
"""
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np
import yaml
from scipy.integrate import solve_ivp

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
FW = os.path.join(ROOT, "firmware_sim")
CONFIG = os.path.join(ROOT, "configs", "plant_twomass.yaml")


def bench_config(path):
    """configs/plant_twomass.yaml with controller.kfc = Fc / km, written to ``path``
    (firmware_sim reads a two-level YAML subset: keep the layout of the original)."""
    with open(CONFIG, encoding="utf-8") as f:
        text = f.read()
    cfg = yaml.safe_load(text)
    kfc = cfg["plant"]["coulomb"] / cfg["plant"]["km"]
    text, n = re.subn(r"^(  kfc: *)\S+", lambda m: f"{m.group(1)}{kfc!r}", text, flags=re.M)
    assert n == 1, "controller.kfc not found in " + CONFIG
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
    return kfc


def c_rate(config):
    subprocess.run(["make", "--no-print-directory", "-C", FW, "core-all"], check=True, stdout=subprocess.DEVNULL)
    out = subprocess.run([os.path.join(FW, "build", "bench_fw"), "rate", config], check=True,
                         capture_output=True, text=True).stdout
    print(out.strip())
    return float(re.search(r"^RATE (\S+)", out, re.M).group(1))


def scipy_rate(config, sim_seconds=1.0, amplitude=0.5, f0=1.0):
    with open(config, encoding="utf-8") as f:
        cfg = yaml.safe_load(f)
    p, c = cfg["plant"], cfg["controller"]
    fs = cfg["drive"]["fs_hz"]
    dt = 1.0 / fs
    tau, kp, kd, kfc, kv, umax = c["tau_d"], c["kp"], c["kd"], c["kfc"], c["kv"], c["u_max"]
    counts = cfg["sensor"]["counts_per_rev"]
    quantum = 2 * np.pi / counts if counts else 0.0

    def rhs(t, x, u):
        th1, w1, th2, w2 = x
        spring = p["k"] * (th1 - th2) + p["c"] * (w1 - w2)
        friction = p["coulomb"] * np.sign(w1) + p["viscous"] * w1
        return [w1, (p["km"] * u - spring - friction) / p["j1"], w2, (spring - p["load_viscous"] * w2) / p["j2"]]

    n = int(round(sim_seconds * fs))
    x = np.zeros(4)
    e_prev, d = 0.0, 0.0
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(n):
        ref = amplitude * np.sin(2 * np.pi * f0 * i * dt)
        vref = amplitude * 2 * np.pi * f0 * np.cos(2 * np.pi * f0 * i * dt)
        theta = np.floor(x[0] / quantum + 0.5) * quantum if quantum else x[0]   # nearest count, as plant.c
        e = ref - theta
        d = tau / (tau + dt) * d + kd / (tau + dt) * (e - e_prev)
        e_prev = e
        u = float(np.clip(kp * e + d + kfc * np.sign(vref) + kv * vref, -umax, umax))
        x = solve_ivp(rhs, (0.0, dt), x, method="RK45", rtol=1e-8, atol=1e-10, args=(u,)).y[:, -1]
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return n / cpu, n / wall


def main():
    with tempfile.TemporaryDirectory() as tmp:
        config = os.path.join(tmp, "plant_twomass_kfc.yaml")
        kfc = bench_config(config)
        print(f"loop: configs/plant_twomass.yaml with K_fc = Fc / km = {kfc:.4g} V on both sides")
        rate_c = c_rate(config)
        runs = [scipy_rate(config) for _ in range(3)]
    rates_py = sorted(r[0] for r in runs)
    rate_py = rates_py[1]
    wall_py = sorted(r[1] for r in runs)[1]
    print(f"scipy solve_ivp closed loop (same model, same controller): median {rate_py:.3g} steps per CPU second "
          f"(min {rates_py[0]:.3g}, max {rates_py[2]:.3g}; wall {wall_py:.3g}/s) over 3 x 1 s simulated")
    print(f"firmware_sim C closed loop: {rate_c:.3g} steps per CPU second (target >= 1e7)")
    print(f"ratio C / scipy (same loop, K_fc = {kfc:.4g} V, CPU-time rates of this run): "
          f"{rate_c / rate_py:.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
