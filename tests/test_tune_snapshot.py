"""results['tune'] of a few deterministic tunes, unchanged by the move of the tune strategy
into fftune.analysis.tune_strategy (issue 35, item 3): the firmware core + plant through
ctypes (tests/fwsim_drive.py, fixed seeds) and the Python test double of the drive.

The rows cover a converged search (raw samples and the drive's statistics), a frequency
halving (the loop does not repeat at 0.625 Hz), a drift inside the tune (the repeated
first experiment), the drive's smoothed sign, a sine the loop cannot follow and a stop in
the checks (no motion); and the model-based tune (`tune.method: model`). tests/data/tune_snapshot.json holds
the results from before the move; ``python tests/test_tune_snapshot.py --write`` rewrites it
(the rows not in it; with --all every row: only when a change of the results is intended)."""
import json
import os
import sys
import tempfile

import pytest

from host_fixtures import REPO, FakeDriveForTests

sys.path.insert(0, os.path.join(REPO, "tests", "bench"))
import bench_tune  # noqa: E402
import bench_tune_matrix  # noqa: E402

SNAPSHOT = os.path.join(REPO, "tests", "data", "tune_snapshot.json")
MATRIX = {name: (plant, tune) for rows in bench_tune_matrix.families().values() for name, plant, tune, _ in rows}
ROWS = {
    "demo raw": ("demo, noise 0.002, seed 1", "raw"),
    "demo stats": ("demo, noise 0.002, seed 1", "stats"),
    "halving": ("j1 x30, seed 1", "raw"),
    "drift": ("step -20 % at 30 s", "raw"),
    "no motion": ("Fc 0.46 V, u_max 0.4 V", "raw"),
    "smoothed sign": ("fc_smooth 1", "raw"),
    "fast sine": ("sine 2.5 Hz", "stats"),
}


def _fake_tune():
    """The Python test double (Coulomb 0.3 V, viscous 0.02 V s/rad) with the paper's sweep
    and the K_v minimiser (tests/test_host_experiments.py's configuration)."""
    import test_host_experiments as th
    from fftune.host import experiments as ex
    with tempfile.TemporaryDirectory() as tmp:
        session = ex.Session(th._drive(), th._cfg(), tmp, log=lambda s: None)
        return ex.tune(session)[0]


def _model_tune(plant, tune):
    """`tune.method: model` (tests/test_ffmodel_host.py's configuration)."""
    import pathlib

    import test_ffmodel_host as tm
    with tempfile.TemporaryDirectory() as tmp:
        return tm.run_model(pathlib.Path(tmp), plant, tune)[0]


MODEL = {
    "model coulomb stats": ({"plant": {"viscous": 2e-3}}, {"terms": ["coulomb"], "capture": "stats"}),
    "model asymmetry raw": ({"plant": {"coulomb_asymmetry": 0.3, "static": 7.6e-3}},
                            {"terms": ["coulomb", "asymmetry", "viscous"], "capture": "raw"}),
}


def run(name):
    if name == "fake sweep+kv":
        return _fake_tune()
    if name in MODEL:
        return _model_tune(*MODEL[name])
    row, capture = ROWS[name]
    plant, tune = MATRIX[row]
    return bench_tune_matrix.run_row(plant, tune, capture)


def _plain(x):
    """JSON round trip: the floats exactly (repr), tuples as lists."""
    return json.loads(json.dumps(x))


NAMES = list(ROWS) + ["fake sweep+kv"] + list(MODEL)


@pytest.fixture(scope="module")
def snapshot():
    with open(SNAPSHOT, encoding="utf-8") as fh:
        return json.load(fh)


@pytest.mark.parametrize("name", NAMES)
def test_tune_results_are_those_from_before_the_move(snapshot, name):
    assert _plain(run(name)) == snapshot[name]


if __name__ == "__main__":
    if "--write" in sys.argv:
        sys.path.insert(0, os.path.join(REPO, "tests"))
        # the rows not in the file yet (every row with --all)
        out = {}
        if os.path.exists(SNAPSHOT) and "--all" not in sys.argv:
            with open(SNAPSHOT, encoding="utf-8") as fh:
                out = json.load(fh)
        out = {name: out[name] if name in out else _plain(run(name)) for name in NAMES}
        with open(SNAPSHOT, "w", encoding="utf-8") as fh:
            json.dump(out, fh, indent=1, sort_keys=False)
            fh.write("\n")
