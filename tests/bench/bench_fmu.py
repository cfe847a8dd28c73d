"""Benchmark: the FMU plant path (docs/fmu.md) against the built-in plant.

1. Closed-loop controller steps per CPU second (firmware_sim/build/fmu_bench: drive_sim's
   simulation, sine reference 0.5 rad at 1 Hz, median of 5 x 1e6 steps, one core) with the
   built-in plant (configs/plant_twomass.yaml), its FMU twin (configs/plant_twomass_fmu.yaml:
   the same plant.c behind fmi2SetReal / fmi2DoStep / fmi2GetReal through dlopen) and the
   example FMUs (LuGre, cogging: RK4 with 20 sub-steps per controller step).
2. `fftune demo` wall time, once each, with the built-in plant and with the twin (configs/
   demo.yaml without its sim.overrides, so that both simulate the same plant; the demo's
   time is mostly the host and the bus, not the plant). Goal (issue 34): the FMU within 2x.

    .venv/bin/python tests/bench/bench_fmu.py
"""
import os
import re
import subprocess
import sys
import tempfile
import time

import yaml

ROOT = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
FW = os.path.join(ROOT, "firmware_sim")
PLANTS = [("built-in", "plant_twomass.yaml"), ("FMU twin", "plant_twomass_fmu.yaml"),
          ("LuGre FMU", "plant_lugre_fmu.yaml"), ("cogging FMU", "plant_cogging_fmu.yaml")]


def steps_per_s(plant):
    from fftune.host.fmu import drive_sim_plant

    out = subprocess.run([os.path.join(FW, "build", "fmu_bench"), drive_sim_plant(plant)], check=True,
                         capture_output=True, text=True).stdout
    return float(re.search(r"^RATE (\S+)", out, re.M).group(1))


def demo_wall_s(plant, config, out):
    t0 = time.monotonic()
    subprocess.run([os.path.join(os.path.dirname(sys.executable), "fftune"), "demo", "--config", config,
                    "--plant", plant, "--out", out, "--no-progress"], check=True, stdout=subprocess.DEVNULL)
    return time.monotonic() - t0


def main():
    subprocess.run(["make", "--no-print-directory", "-C", FW, "fmu-bench", f"PYTHON={sys.executable}"],
                   check=True, stdout=subprocess.DEVNULL)
    rates = {}
    for name, f in PLANTS:
        rates[name] = steps_per_s(os.path.join(ROOT, "configs", f))
        print(f"{name:12s} {rates[name]:10.4g} controller steps per CPU second "
              f"({rates['built-in'] / rates[name]:.2f}x the built-in plant's time per step)")
    with open(os.path.join(ROOT, "configs", "demo.yaml"), encoding="utf-8") as fh:
        cfg = yaml.safe_load(fh)
    cfg["sim"]["overrides"] = {}
    with tempfile.TemporaryDirectory(prefix="bench_fmu-") as d:
        config = os.path.join(d, "demo.yaml")
        with open(config, "w", encoding="utf-8") as fh:
            yaml.safe_dump(cfg, fh)
        walls = {}
        for name, f in PLANTS[:2]:
            walls[name] = demo_wall_s(os.path.join(ROOT, "configs", f), config, os.path.join(d, name.replace(" ", "_")))
            print(f"fftune demo with the {name:9s} plant: {walls[name]:6.1f} s wall")
    ratio = walls["FMU twin"] / walls["built-in"]
    print(f"demo wall time, FMU twin / built-in: {ratio:.2f}x (goal: within 2x: "
          f"{'met' if ratio <= 2.0 else 'NOT met'}); steps/s built-in / twin: "
          f"{rates['built-in'] / rates['FMU twin']:.2f}x")


if __name__ == "__main__":
    main()
