"""The ground-truth matrix of synthetic systems (tests/groundtruth_systems.py): a fast
subset, one seed per system (the whole matrix over seeds and the simulated encoders:
tests/bench/bench_detect_matrix.py, `make bench`)."""
import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import groundtruth_systems as gt  # noqa: E402


@pytest.mark.parametrize("name", gt.SYSTEMS)
def test_ground_truth_system(name):
    ok, causes, text, res = gt.judge(name, seed=3)
    assert ok, f"{name}: {causes}: {text}"


def test_cross_coupling_over_levels_is_not_a_plant_nonlinearity():
    lv = gt.cross_coupling_levels(seed=2)
    for res in lv.results:
        causes = gt.level_verdict(res.summary)["causes"]
        assert causes == ["unmeasured inputs or a scale-free nonlinearity"]
