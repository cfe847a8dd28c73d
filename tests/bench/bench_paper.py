"""The paper's results reproduced: `fftune paper --short` (the tune step of
configs/paper_setup.yaml on configs/plant_paper.yaml with a 0.01 V sweep step, and the
Figure 7 sweep on configs/plant_paper_sim.yaml) into a temporary directory; prints each
claim of the paper beside the measured number (fftune.analysis.reproduction) and the wall
time. The table of docs/paper-reproduction.md is the full run's (`make paper`: 0.005 V
sweep step, detect and quantify too); this bench shows the same figures from the shortened
run that `make test` checks (tests/test_paper.py)."""
import json
import os
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, os.pardir))


def main():
    from fftune.host.cli import main as fftune

    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out")
        t0 = time.monotonic()
        rc = fftune(["paper", "--short", "--no-progress", "--out", out])
        wall = time.monotonic() - t0
        if rc != 0:
            print(f"bench_paper: fftune paper --short failed with exit status {rc}")
            return rc
        with open(os.path.join(out, "reproduction.json"), encoding="utf-8") as fh:
            doc = json.load(fh)
    print(f"\nbench_paper: fftune paper --short in {wall:.1f} s (sweep step {doc['sweep_step_v']:.3g} V)")
    print(f"  {'claim':<64} {'paper':>10} {'measured':>10}  agrees")
    for row in doc["comparison"]:
        print(f"  {row['claim'][:64]:<64} {row['paper']:>10} {row['measured_text']:>10}  "
              f"{ {'yes': 'yes', 'no': 'NO'}.get(row.get('verdict', 'yes' if row['agrees'] else 'no'), 'other set-up')}")
    print(f"  H_3 / H_5 turn on the set-up itself: {doc['h3_phase_turn_deg_setup']:.0f} / "
          f"{doc['h5_phase_turn_deg_setup']:.0f} deg (the paper's 180 deg is its simulation's)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
