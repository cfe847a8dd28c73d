"""The simulated plant of firmware_sim (C, via ctypes) against scipy and against physics.

The reference is scipy.integrate.solve_ivp (DOP853, rtol 1e-12) of the same equations
(firmware_sim/plant/plant.h), integrated controller step by controller step with the input
held (ZOH) and with the motor velocity zero crossing as a terminal event at which the
friction sign is switched: a trajectory that reverses without sticking.
"""
import os
import sys

import numpy as np
import pytest
import yaml
from scipy.integrate import solve_ivp

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "firmware_sim", "tests"))
from fwsim import FwSim  # noqa: E402

ROOT = os.path.join(os.path.dirname(__file__), "..")
TWOMASS = os.path.join(ROOT, "configs", "plant_twomass.yaml")
STAGE = os.path.join(ROOT, "configs", "plant_stage.yaml")
DT = 1.0 / 2560.0
# State error bounds asserted against solve_ivp (max over the four states; angles in rad,
# velocities in rad/s, over 0.3 s with 4 velocity reversals). Measured here: exact-ZOH path
# (event steps by RK4 sub-steps + bisection) 6e-12; RK4 sub-step path throughout (Stribeck
# on, 8 sub-steps of 49 us) 2e-9, RK4's h^4 error.
STATE_ERROR_BOUND = 1e-9
STATE_ERROR_BOUND_RK4 = 1e-8


def write_config(tmp_path, base=TWOMASS, **overrides):
    """Copy a plant config with `section__key=value` overrides, ideal sensor, small recorder."""
    with open(base, encoding="utf-8") as f:
        cfg = yaml.safe_load(f)
    cfg["sensor"]["counts_per_rev"] = 0
    cfg["sensor"]["noise_std"] = 0.0
    cfg["drive"]["rec_capacity"] = 1000
    for name, value in overrides.items():
        section, key = name.split("__")
        cfg[section][key] = value
    path = tmp_path / "plant.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path), cfg["plant"]


def rhs(t, x, u, s, p):
    th1, w1, th2, w2 = x
    spring = p["k"] * (th1 - th2) + p["c"] * (w1 - w2)
    g = 1 + p.get("coulomb_position", 0.0) * np.sin(th1)     # run-out: friction levels x g(th1)
    fc = g * p["coulomb"] * (1 + s * p.get("coulomb_asymmetry", 0.0))
    fr = fc
    if p["stribeck_velocity"] > 0:
        fr += (g * p["static"] - fc) * np.exp(-(w1 / p["stribeck_velocity"]) ** 2)
    friction = s * fr + p["viscous"] * w1
    return [w1, (p["km"] * u - spring - friction) / p["j1"], w2, (spring - p["load_viscous"] * w2) / p["j2"]]


def velocity_zero(t, x, u, s, p):
    """s * w1 falling through zero: the motion in direction s stops (not re-detected at a
    start on w1 = 0, where s * w1 rises)."""
    return s * x[1]


velocity_zero.terminal = True
velocity_zero.direction = -1


def reference_trajectory(p, x0, inputs):
    """solve_ivp step by step; returns the states after each step and the reversal count."""
    x = np.array(x0, dtype=float)
    s = np.sign(x[1])
    states, reversals = [], 0
    for u in inputs:
        t = 0.0
        while t < DT:
            sol = solve_ivp(rhs, (t, DT), x, method="DOP853", rtol=1e-12, atol=1e-13,
                            args=(u, s, p), events=velocity_zero)
            x = sol.y[:, -1].copy()
            if sol.status == 1:  # the motor velocity reached zero inside the step
                t = sol.t[-1]
                x[1] = 0.0
                net = p["km"] * u - p["k"] * (x[0] - x[2]) + p["c"] * x[3]
                g = 1 + p.get("coulomb_position", 0.0) * np.sin(x[0])
                assert abs(net) > g * p["static"], "reference trajectory sticks: not the case under test"
                s = np.sign(net)
                reversals += 1
            else:
                t = DT
        states.append(x)
    return np.array(states), reversals


def c_trajectory(path, x0, inputs):
    with FwSim(path) as sim:
        sim.plant_set_state(*x0)
        out = []
        for u in inputs:
            sim.plant_advance(u, DT)
            out.append(sim.plant_state())
    return np.array(out)


@pytest.mark.parametrize("case", ["exact_zoh_path", "rk4_substep_path", "position_dependent"])
def test_plant_matches_solve_ivp_with_reversals(tmp_path, case):
    # the Stribeck term makes the slip dynamics nonlinear: the plant then integrates with
    # RK4 sub-steps; without it, exact ZOH steps between events
    if case == "exact_zoh_path":  # with direction-dependent Coulomb friction
        over = {"plant__coulomb_asymmetry": 0.3, "plant__static": 8e-3}
    elif case == "rk4_substep_path":
        over = {"plant__stribeck_velocity": 0.5, "plant__static": 8e-3}
    else:  # friction levels x (1 + e sin(th1)): the sub-step path; th1 swings over ~1 rad
        over = {"plant__coulomb_position": 0.6, "plant__static": 8e-3}
    path, p = write_config(tmp_path, **over)
    n = 768
    t = np.arange(n) * DT
    inputs = 3.0 * np.cos(2 * np.pi * 5.0 * t) + 0.05  # velocity ~ sin: reverses every 0.1 s
    x0 = [0.0, 0.5, 0.0, 0.3]
    ref, reversals = reference_trajectory(p, x0, inputs)
    got = c_trajectory(path, x0, inputs)
    assert reversals >= 4  # the trajectory does go through w1 = 0 (without sticking)
    err = np.abs(got - ref).max()
    bound = STATE_ERROR_BOUND if case == "exact_zoh_path" else STATE_ERROR_BOUND_RK4
    print(f"{case}: {reversals} reversals, max state error {err:.3g} (bound {bound:g})")
    assert err < bound, f"max state error {err:.3g}"


def test_stiction_holds_while_load_swings(tmp_path):
    # motor stuck, load released 5 mrad away: the spring torque (max k * 5e-3 = 2.5e-3 N m)
    # stays below static friction (5.785e-3 N m), so the motor must not move by one bit
    # while the load rings out; the load follows the clamped two-state dynamics
    path, p = write_config(tmp_path)
    x0 = [0.1, 0.0, 0.105, 0.0]
    n = 2560 * 5
    with FwSim(path) as sim:
        sim.plant_set_state(*x0)
        th1 = np.empty(n)
        w1 = np.empty(n)
        th2 = np.empty(n)
        for i in range(n):
            sim.plant_advance(0.0, DT)
            x = sim.plant_state()
            th1[i], w1[i], th2[i] = x[0], x[1], x[2]
        assert sim.plant_mode() == 0
    assert np.all(th1 == 0.1) and np.all(w1 == 0.0)

    def load_rhs(t, y):
        return [y[1], (p["k"] * (0.1 - y[0]) - (p["c"] + p["load_viscous"]) * y[1]) / p["j2"]]

    sol = solve_ivp(load_rhs, (0, n * DT), [0.105, 0.0], method="DOP853", rtol=1e-12, atol=1e-14,
                    t_eval=np.arange(1, n + 1) * DT)
    assert np.abs(sol.y[0] - th2).max() < STATE_ERROR_BOUND


def test_stiction_no_drift_under_constant_input_below_static(tmp_path):
    path, p = write_config(tmp_path, plant__static=8e-3)
    u = 0.99 * p["static"] / p["km"]
    with FwSim(path) as sim:
        sim.plant_set_state(0.0, 0.0, 0.0, 0.0)
        for _ in range(2560 * 3):
            sim.plant_advance(u, DT)
        x_stuck = sim.plant_state()
        # the load settles where the spring carries the input torque; the motor stays
        assert x_stuck[0] == 0.0 and x_stuck[1] == 0.0
        # 2 % over the static level: it breaks away and moves in the torque's direction
        for _ in range(100):
            sim.plant_advance(1.02 * p["static"] / p["km"], DT)
        assert sim.plant_state()[0] > 1e-6


def test_configs_are_yaml_and_load_in_c():
    for path in (TWOMASS, STAGE):
        with open(path, encoding="utf-8") as f:
            cfg = yaml.safe_load(f)
        assert set(cfg) == {"drive", "controller", "plant", "sensor"}
        with FwSim(path) as sim:
            assert sim.truth("SIM_FC_VOLT") == pytest.approx(cfg["plant"]["coulomb"] / cfg["plant"]["km"], rel=1e-6)
            assert sim.truth("SIM_FS_VOLT") == pytest.approx(cfg["plant"]["static"] / cfg["plant"]["km"], rel=1e-6)
            assert sim.truth("SIM_FV_VOLT") == pytest.approx(cfg["plant"]["viscous"] / cfg["plant"]["km"], rel=1e-6)
            assert sim.truth("SIM_NOISE_STD") == pytest.approx(cfg["sensor"]["noise_std"], rel=1e-6, abs=0)
            assert sim.get("KP") == pytest.approx(cfg["controller"]["kp"])
            assert sim.get("FS") == pytest.approx(cfg["drive"]["fs_hz"])
            assert sim.get("REC_CAPACITY") == cfg["drive"]["rec_capacity"]


def test_config_error_names_file_line_and_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("plant:\n  j1: 1.0e-4\n  spring: 3\n")
    with pytest.raises(ValueError, match=r"bad\.yaml:3: unknown key 'spring' in section 'plant'"):
        FwSim(str(bad))
    bad.write_text("controller:\n  kp: 2.0e6\n")
    with pytest.raises(ValueError, match=r"bad\.yaml:2: controller\.kp = 2\.0e6: out of range"):
        FwSim(str(bad))
