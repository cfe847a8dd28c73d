"""Benchmark: the full `fftune demo --plant` (configs/demo.yaml, its sim.overrides not applied:
the note says so) on each foreign FMU of tests/data/fmu_foreign/ (hand-written FMI 2.0,
built by FMPy's CMake project; docs/fmu.md "FMUs from other exporters"). Prints K_fc* and
sigma_total against the documented truth (the law's sliding friction level / km), or the
stop reason of an unconverged search, and the demo's wall time.

    .venv/bin/python tests/bench/bench_fmu_foreign.py [name ...]
"""
import os
import subprocess
import sys
import tempfile
import time

import yaml

ROOT = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
sys.path.insert(0, os.path.join(ROOT, "tests", "data", "fmu_foreign"))
import foreign_fmus as foreign  # noqa: E402  (tests/data/fmu_foreign/foreign_fmus.py)


def plant_file(folder, name):
    spec = foreign.FOREIGN[name]
    data = {"fmu": {"path": foreign.build(name), "input": spec["input"], "output": spec["output"],
                    "load_output": spec["load_output"], "parameters": spec["parameters"]},
            "sensor": {"counts_per_rev": 2000, "noise_std": 0.0, "seed": 1},
            "truth": spec["truth"]}
    path = os.path.join(folder, f"{name}.yaml")
    with open(path, "w", encoding="utf-8") as fh:
        yaml.safe_dump(data, fh, sort_keys=False, allow_unicode=True)
    return path


def main(names):
    fftune = os.path.join(os.path.dirname(sys.executable), "fftune")
    with tempfile.TemporaryDirectory(prefix="bench_fmu_foreign-") as d:
        for name in names:
            plant = plant_file(d, name)
            out = os.path.join(d, f"out-{name}")
            t0 = time.monotonic()
            run = subprocess.run([fftune, "demo", "--plant", plant, "--out", out, "--no-progress"],
                                 capture_output=True, text=True, check=False)
            wall = time.monotonic() - t0
            truth = foreign.FOREIGN[name]["truth"]["kfc_v"]
            if run.returncode != 0:
                print(f"{name:17s} FAILED (exit {run.returncode}): {run.stderr.strip()}")
                continue
            with open(os.path.join(out, "results.yaml"), encoding="utf-8") as fh:
                s = yaml.safe_load(fh)["tune"]["search"]
            if s.get("converged"):
                k, sig = s["k_fc_star"], s["sigma_v"]
                print(f"{name:17s} K_fc* = {k:.4f} +- {sig:.4f} V, truth {truth:.4f} V: "
                      f"{100 * (k - truth) / truth:+.2f} % ({abs(k - truth) / sig:.2f} sigma); "
                      f"{s.get('experiments', '?')} experiments; demo {wall:.1f} s wall")
            else:
                print(f"{name:17s} not converged: {s.get('stop_reason')!r}; truth {truth:.4f} V; "
                      f"demo {wall:.1f} s wall")


if __name__ == "__main__":
    main(sys.argv[1:] or list(foreign.FOREIGN))
