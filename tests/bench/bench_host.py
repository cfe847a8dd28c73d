"""Host benchmark: `fftune demo` wall time and the accuracy of the tuning in simulation.

Runs the demo pipeline (configs/demo.yaml) against drive_sim exactly as `make demo` does,
then the tuning step with the paper's settings (configs/paper.yaml, tune only), and prints:
wall time, K_fc* against the plant's true Coulomb level (0x2100:1), the odd-harmonic ratio
at K_fc = 0 and at K_fc*, the number of closed-loop experiments of the automated search,
its distance to the sweep optimum, and the rms tracking errors.
"""
import os
import sys
import tempfile
import time

import yaml

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, os.pardir))
sys.path.insert(0, os.path.join(REPO, "tests"))

from fftune.host.cli import main  # noqa: E402
from host_fixtures import drive_sim_missing_reason  # noqa: E402


def _report(label, r, wall):
    t = r["tune"]
    print(f"{label}: wall time {wall:.1f} s, runs measured {r['experiments']['measured']}")
    print(f"  K_fc* = {t['k_fc_star']:.5f} V, true Coulomb {t['true_coulomb_v']:.5f} V, "
          f"error {100 * t['k_fc_star_error_re_truth']:+.2f} % (goal |e| <= 2 %)")
    print(f"  automated search: {t['search']['experiments']} experiments (goal <= 8), "
          f"{100 * t['search']['relative_to_sweep_optimum']:+.3f} % from the sweep optimum "
          f"{t['sweep']['optimum_k_fc']:.5f} V (goal <= 1 %)")
    print(f"  odd ratio: {t['ratio_at_zero']:.4g} at K_fc = 0 -> {t['ratio_at_k_fc_star']:.4g} at "
          f"K_fc* ({t['ratio_improvement']:.1f}x, goal >= 10x)")
    e = t["rms_error_rad"]
    line = (f"  rms error [rad]: K_fc=0 {e['k_fc_0']:.4g}, K_fc* {e['k_fc_star']:.4g}, sweep min "
            f"{e['sweep_min']:.4g} at K_fc = {e['sweep_min_at_k_fc']:.4g} V "
            f"({100 * (e['sweep_min_at_k_fc'] / t['k_fc_star'] - 1):+.0f} % re K_fc*)")
    if "k_fc_star_k_v_star" in e:
        line += f", K_fc* + K_v* ({t['viscous']['k_v_star']:.4g} V s/rad) {e['k_fc_star_k_v_star']:.4g}"
    print(line)


def run():
    reason = drive_sim_missing_reason()
    if reason:
        print(f"bench_host: skipped: {reason}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.monotonic()
        code = main(["demo", "--out", os.path.join(tmp, "demo"), "--no-progress"])
        wall = time.monotonic() - t0
        if code:
            print(f"bench_host: fftune demo failed ({code})")
            return code
        _report("demo (configs/demo.yaml, `make demo` path)",
                yaml.safe_load(open(os.path.join(tmp, "demo", "results.yaml"))), wall)
        # The paper's settings, tuning step only (the full detect/quantify grid takes hours).
        from fftune.host.config import load_config
        from fftune.host.sim import derived_plant, start_drive_sim
        paper_yaml = os.path.join(REPO, "configs", "paper.yaml")
        sim_cfg = load_config(paper_yaml)["sim"]
        plant = os.path.join(REPO, sim_cfg["plant"] or "configs/plant_twomass.yaml")
        if sim_cfg["overrides"]:       # the paper config's own plant, as `fftune demo` builds it
            plant = derived_plant(plant, sim_cfg["overrides"], os.path.join(tmp, "paper_plant.yaml"))
        sim = start_drive_sim(plant)
        try:
            t0 = time.monotonic()
            code = main(["tune", "--config", paper_yaml,
                         "--out", os.path.join(tmp, "paper"), "--port", str(sim.port),
                         "--no-progress", "--no-figures"])
            wall = time.monotonic() - t0
        finally:
            sim.stop()
        if code:
            print(f"bench_host: paper tune failed ({code})")
            return code
        _report("paper settings, tune only (configs/paper.yaml)",
                yaml.safe_load(open(os.path.join(tmp, "paper", "results.yaml"))), wall)
    return 0


if __name__ == "__main__":
    sys.exit(run())
