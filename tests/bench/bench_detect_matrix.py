"""Ground-truth matrix of the nonlinear detection (issue 23; `make bench`): every synthetic
system of tests/groundtruth_systems.py over 10 seeds, the cross-coupling over levels, and
the simulated drive (C core, PD loop) with encoders of 128 .. 4096 counts on a frictionless
plant (no plant nonlinearity is the truth) and with Coulomb friction. Prints the share of
right answers per row and the causes found."""
import collections
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.join(REPO, "tests"))
sys.path.insert(0, os.path.join(REPO, "firmware_sim", "tests"))

import groundtruth_systems as gt  # noqa: E402


def synthetic(seeds=10):
    print(f"synthetic systems (open loop, M = {gt.M}, P = {gt.P}, N = {gt.N}), {seeds} seeds:")
    for name in gt.SYSTEMS:
        good, seen = 0, collections.Counter()
        t0 = time.perf_counter()
        for seed in range(seeds):
            ok, causes, _, _ = gt.judge(name, seed)
            good += ok
            seen[", ".join(causes)] += 1
        print(f"  {name:20s} {good:2d}/{seeds} right  ({1e3 * (time.perf_counter() - t0) / seeds:5.1f} ms)"
              f"  causes: {dict(seen)}")
    good = 0
    for seed in range(seeds):
        lv = gt.cross_coupling_levels(seed)
        good += all(gt.level_verdict(r.summary)["causes"] ==
                    ["unmeasured inputs or a scale-free nonlinearity"] for r in lv.results)
    print(f"  {'cross-coupling, 3 levels, other grid':20s} {good:2d}/{seeds} right")


def encoders():
    import test_analysis_detect as td
    print("simulated drive, PD loop, levels 0.3 / 1 V rms: causes per level")
    tmp = tempfile.mkdtemp()
    for counts in (128, 200, 512, 1024, 2000, 4096):
        for friction in (False, True):
            plant = {"viscous": 2e-3} if friction else \
                {"viscous": 2e-3, "coulomb": 0.0, "static": 0.0}
            p = td.write_plant(os.path.join(tmp, "p.yaml"),
                               {"sensor": {"counts_per_rev": counts}, "plant": plant})
            res, _ = td.simulate_detect(p, levels=[0.3, 1.0])
            causes = [lv["causes"] for lv in res["levels"]]
            plant_claim = any(c.startswith("plant ") for lv in causes for c in lv)
            truth = "friction" if friction else "frictionless"
            verdict = ("right" if not plant_claim else "WRONG: plant claimed") if not friction \
                else ("detected" if plant_claim else "not detected (quantisation dominates?)")
            print(f"  {counts:5d} counts, {truth:12s}: {verdict:40s} {causes}")


if __name__ == "__main__":
    synthetic()
    encoders()
