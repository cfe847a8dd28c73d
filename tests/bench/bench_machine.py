"""Benchmark: a machine of 4 axes tuned concurrently on one simulated 1 Mbit/s CAN bus.

First `make demo-machine` itself (configs/machine_demo.yaml, the demo configuration per
axis, free-running). Then `fftune demo --machine` with the same 4 axes (plants: Coulomb
0.1157, 0.16, 0.08, 0.14 V; different inertias and encoders) on a short configuration
(configs/demo.yaml with detect at one level, 2 realizations; quantify 1 frequency; tune
without the sweep and K_v), once free-running and once with --realtime (drive_sim steps
every axis at its 2560 Hz controller rate). Printed per run: each axis' K_fc* against its
truth, the bus time (drive_sim's bus model: bits carried / bit rate) against the longest
axis' excitation (acceptance: <= 15 %), and the machine's wall time against the longest
axis' excitation (--realtime acceptance: <= 1.15), the whole wall time with every axis'
figures and report (drawn step by step in a separate figure process while the axes
measure) and until the last axis has measured. The wall time of --realtime is bounded
below by the longest axis' excitation; what it adds is the SDO traffic of the four axes
between their runs (parameters, read-back, statistics uploads) on the shared bus, the
host's analysis between runs and the last axis' tune figure; it depends on the load of the
machine (Python threads of 4 axes and the figure process on 2 shared cores).
"""
import os
import subprocess
import sys
import tempfile

import yaml

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", ".."))
FFTUNE = os.path.join(os.path.dirname(sys.executable), "fftune")


def main():
    with tempfile.TemporaryDirectory(prefix="bench-machine-") as d:
        demo = yaml.safe_load(open(os.path.join(REPO, "configs", "demo.yaml")))
        demo["detect"].update(rms_levels=[1.0], realizations=2)
        demo["quantify"].update(frequencies_hz=[2.5], rms_levels=[0.35], repeats=1)
        demo["tune"]["sweep"]["points"] = 0
        demo["tune"]["viscous"]["enabled"] = False
        demo.pop("sim", None)
        with open(os.path.join(d, "short.yaml"), "w") as fh:
            yaml.safe_dump(demo, fh)
        machine = yaml.safe_load(open(os.path.join(REPO, "configs", "machine_demo.yaml")))
        machine["config"] = "short.yaml"
        for ax in machine["axes"]:
            ax["plant"] = os.path.join(REPO, ax["plant"])
            ax.get("overrides", {}).get("tune", {}).pop("sweep", None)
        mfile = os.path.join(d, "machine.yaml")
        with open(mfile, "w") as fh:
            yaml.safe_dump(machine, fh)
        demo_file = os.path.join(REPO, "configs", "machine_demo.yaml")
        only = sys.argv[1:]     # e.g. "realtime": only the runs whose name has it
        for mode, mf, extra in (("make demo-machine (configs/machine_demo.yaml, free-running)", demo_file, []),
                                ("short, free-running", mfile, []),
                                ("short, --realtime", mfile, ["--realtime"])):
            if only and not any(o in mode for o in only):
                continue
            out = os.path.join(d, "".join(c if c.isalnum() else "_" for c in mode))
            r = subprocess.run([FFTUNE, "demo", "--machine", mf, "--out", out] + extra,
                               capture_output=True, text=True, cwd=REPO)
            if r.returncode not in (0, 1):
                print(f"{mode}: FAILED ({r.returncode}): {r.stdout[-2000:]} {r.stderr[-2000:]}")
                continue
            s = yaml.safe_load(open(os.path.join(out, "results.yaml")))
            t = s["time_budget_s"]["total"]
            print(f"{mode}: 4 axes, wall {t['wall']:.1f} s (until the last axis measured "
                  f"{t['measure_wall']:.1f} s), longest axis' excitation "
                  f"{t['excitation']:.1f} s (sum over axes {t['excitation_sum']:.1f} s): wall / longest "
                  f"excitation {t['wall_re_longest_excitation']:.3f}, measuring / longest excitation "
                  f"{t['measure_re_longest_excitation']:.3f} (realtime acceptance <= 1.15); bus "
                  f"{t['bus']:.2f} s = {100 * t['bus_re_longest_excitation']:.1f} % of the longest "
                  f"excitation (<= 15 %); {s['bus_model']['frames']} frames")
            for a in s["axes"]:
                err = (f"{100 * a['k_fc_error_re_truth']:+.2f} %" if a["k_fc_error_re_truth"] is not None
                       else a.get("error"))
                z = ((a["k_fc_star"] - a["k_fc_true"]) / a["sigma"]
                     if a["k_fc_star"] is not None and a["k_fc_true"] and a["sigma"] else None)
                print(f"    {a['name']} node {a['node_id']}: {a['status']}, K_fc* {a['k_fc_star']} V "
                      f"+- {a['sigma']} V (1 sigma), truth {a['k_fc_true']} V, {err}"
                      + (f", {z:+.2f} sigma" if z is not None else ""))


if __name__ == "__main__":
    main()
