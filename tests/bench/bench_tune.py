"""Tuning-accuracy matrix: `fftune tune`'s experiment logic (fftune.host.experiments.tune)
over plant variants of configs/plant_twomass.yaml, on the firmware core + plant through
ctypes (tests/fwsim_drive.py, the same C code as drive_sim without the CANopen transport).

Each row runs twice: on per-period HOSIDFs from raw samples (capture: raw) and on the
drive's line statistics (capture: stats: mean HOSIDFs and their variance). Prints per row: true Coulomb level, K_fc*, error, reported sigma, closed-loop experiments of
the search (amplitude probes, bracket ends and verification included), converged, regime and
reason; then the acceptance summary. `python tests/bench/bench_tune.py --fast` runs the
subset the tests use.
"""
import math
import os
import statistics
import sys
import tempfile

import yaml

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, os.pardir))
sys.path.insert(0, os.path.join(REPO, "tests"))

from fftune.host import experiments as ex  # noqa: E402
from fftune.host.config import validate  # noqa: E402

FC0 = 5.785e-3                # plant_twomass.yaml Coulomb torque [N m]

# The tune configuration of configs/demo.yaml with the amplitude chosen automatically and
# no sweep (the search alone); rows change the plant and the bracket.
TUNE = {"frequency_hz": 0.625, "amplitude_rad": "auto", "period_samples": 4096, "periods": 2,
        "settle_periods": 2, "harmonics": 7, "sweep": {"k_fc_max": 0.3, "points": 0},
        "search": {"max_experiments": 10}, "viscous": {"enabled": False}}


def _coulomb(mult):
    return {"plant": {"coulomb": FC0 * mult, "static": FC0 * mult}}


def rows():
    """(name, plant overrides, tune overrides)."""
    out = []
    for mult in (0.1, 0.3, 1, 3, 10):
        fc_v = FC0 * mult / 0.05
        out.append((f"Coulomb x{mult:g}, k_fc_max 0.3 x Fc", _coulomb(mult),
                    {"search": {"k_fc_max": round(0.3 * fc_v, 6)}}))
        out.append((f"Coulomb x{mult:g}, k_fc_max 1 V", _coulomb(mult), {"search": {"k_fc_max": 1.0}}))
    out += [
        ("Coulomb x3, fixed 0.5 rad (stick-slip)", _coulomb(3),
         {"amplitude_rad": 0.5, "search": {"k_fc_max": 0.3}}),
        ("static 1.5 Fc, Stribeck 0.05 rad/s", {"plant": {"static": 1.5 * FC0, "stribeck_velocity": 0.05}}, {}),
        ("asymmetric Coulomb 0.2", {"plant": {"coulomb_asymmetry": 0.2, "static": 1.2 * FC0}}, {}),
        ("noise 1e-3 rad", {"sensor": {"noise_std": 1e-3}}, {}),
        ("noise 1e-2 rad", {"sensor": {"noise_std": 1e-2}}, {}),
        ("noise 3e-2 rad", {"sensor": {"noise_std": 3e-2}}, {}),
        ("noise 3e-2 rad, fixed 0.5 rad", {"sensor": {"noise_std": 3e-2}}, {"amplitude_rad": 0.5}),
        ("stiffness x0.1", {"plant": {"k": 0.05}}, {}),
        ("stiffness x10", {"plant": {"k": 5.0}}, {}),
        ("kp x0.5", {"controller": {"kp": 1.0}}, {}),
        ("ideal encoder", {"sensor": {"counts_per_rev": 0}}, {}),
        ("500-count encoder", {"sensor": {"counts_per_rev": 500}}, {}),
        ("viscous 1e-4", {"plant": {"viscous": 1e-4}}, {}),
        ("viscous 2e-3 (demo plant)", {"plant": {"viscous": 2e-3}}, {}),
    ]
    return out


FAST = ("Coulomb x3, k_fc_max 0.3 x Fc", "Coulomb x10, k_fc_max 1 V", "noise 1e-2 rad",
        "viscous 2e-3 (demo plant)", "Coulomb x3, fixed 0.5 rad (stick-slip)")


def tune_config(tune_over):
    t = yaml.safe_load(yaml.safe_dump(TUNE))
    for k, v in tune_over.items():
        if isinstance(v, dict):
            t[k].update(v)
        else:
            t[k] = v
    cfg = validate({"output": "unused", "tune": t}, "bench_tune")
    cfg["_source"] = "bench_tune"
    return cfg


DRIFT_BASE = os.path.join(REPO, "configs", "plant_twomass_drift.yaml")
NO_DRIFT = {"coulomb_step": 0.0, "coulomb_ramp": 0.0, "coulomb_ramp_start_s": 0.0, "coulomb_ramp_end_s": 0.0}


def run_row(plant_over, tune_over, workdir):
    """results['tune'] of one matrix row (a ``drift`` section in ``plant_over``: the plant
    drifts during the tune, configs/plant_twomass_drift.yaml's section with those keys)."""
    from fwsim_drive import FwSimDrive, plant_file
    if "drift" in plant_over:
        plant_over = dict(plant_over, drift=dict(NO_DRIFT, **plant_over["drift"]))
        plant = plant_file(plant_over, base=DRIFT_BASE, directory=workdir)
    elif "coulomb_position" in plant_over.get("plant", {}):
        # configs/plant_twomass.yaml has no coulomb_position key: a base with it (0)
        os.makedirs(workdir, exist_ok=True)
        base = os.path.join(workdir, "base_position.yaml")
        with open(os.path.join(REPO, "configs", "plant_twomass.yaml"), encoding="utf-8") as fh:
            text = fh.read().replace("  coulomb_asymmetry:", "  coulomb_position: 0.0\n  coulomb_asymmetry:", 1)
        with open(base, "w", encoding="utf-8") as fh:
            fh.write(text)
        plant = plant_file(plant_over, base=base, directory=workdir)
    else:
        plant = plant_file(plant_over, directory=workdir)
    drive = FwSimDrive(plant)
    try:
        drive.enable()
        cfg = tune_config(tune_over)
        if tune_over.get("capture") == "stats":
            # without samples the encoder step is the user's (the data sheet's counts)
            counts = plant_over.get("sensor", {}).get("counts_per_rev", 2000)
            cfg["detect"]["encoder_step_rad"] = 2 * math.pi / counts if counts else 1e-9
        kp = plant_over.get("controller", {}).get("kp")
        if kp is not None:
            cfg["drive"]["controller"]["kp"] = kp
        session = ex.Session(drive, cfg, os.path.join(workdir, "out"), log=lambda s: None)
        results, _ = ex.tune(session)
        return results
    finally:
        drive.close()


def judge(t):
    """(ok, error re truth or None): converged within 2 % (or 2 sigma), or an honest
    not-converged with a reason."""
    s = t["search"]
    if not s["converged"]:
        return bool(s["stop_reason"]), None
    err = t["k_fc_star"] / t["true_coulomb_v"] - 1
    ok = abs(err) <= 0.02 or abs(t["k_fc_star"] - t["true_coulomb_v"]) <= 2 * s["sigma_v"]
    return ok, err


def run(fast=False):
    bad_all = []
    for capture in ("raw", "stats"):
        print(f"-- capture: {capture} ({'per-period HOSIDFs from the recorded samples' if capture == 'raw' else 'the drive line statistics: mean HOSIDFs and their period-to-period variance'})")
        print(f"{'row':42s} {'true Fc':>8s} {'K_fc*':>8s} {'error':>8s} {'sigma':>7s} {'exp':>4s} "
              f"{'amp':>5s} conv  regime / reason")
        counts, bad = [], []
        for name, plant_over, tune_over in rows():
            if fast and name not in FAST:
                continue
            with tempfile.TemporaryDirectory() as tmp:
                t = run_row(plant_over, dict(tune_over, capture=capture), tmp)
            s = t["search"]
            ok, err = judge(t)
            counts.append(s["experiments"])
            kstar = f"{t['k_fc_star']:.5f}" if s["converged"] else "-"
            e = f"{100 * err:+.2f}%" if err is not None else "-"
            sig = f"{100 * s['sigma_v'] / t['true_coulomb_v']:.2f}%" if s["sigma_v"] else "-"
            ext = f" [extended to {s['bracket_extended']['to_v']:.3g} V]" if s["bracket_extended"] else ""
            why = s["regime"] + ext if s["converged"] else s["stop_reason"]
            print(f"{name:42s} {t['true_coulomb_v']:8.5f} {kstar:>8s} {e:>8s} {sig:>7s} "
                  f"{s['experiments']:4d} {t['amplitude_rad']:5.2f} {'yes ' if s['converged'] else 'no  '} "
                  f"{'' if ok else 'FAIL '}{why}")
            if not ok:
                bad.append(name)
        print(f"capture {capture}: median closed-loop experiments {statistics.median(counts):g} "
              f"(goal <= 6: search + the budget's experiments, issue 22), max {max(counts)}; rows failing acceptance: {len(bad)} {bad if bad else ''}")
        if not fast:
            hits, n = coverage(capture=capture)
            print(f"capture {capture}: sigma coverage: truth within +-2 sigma in {hits}/{n} noise "
                  f"seeds at 1e-2 rad (goal >= 90 %)")
        bad_all += bad
    return 1 if bad_all else 0


def coverage(seeds=range(1, 21), noise_rad=1e-2, capture="raw"):
    """(hits, n): converged runs whose truth lies within +-2 reported sigma."""
    hits = n = 0
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            t = run_row({"sensor": {"noise_std": noise_rad, "seed": seed}}, {"capture": capture}, tmp)
        s = t["search"]
        n += 1
        hits += bool(s["converged"]) and abs(t["k_fc_star"] - t["true_coulomb_v"]) <= 2 * s["sigma_v"]
    return hits, n


if __name__ == "__main__":
    sys.exit(run(fast="--fast" in sys.argv))
