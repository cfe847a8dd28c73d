"""`tune.method: model` end to end (issue 35): fftune.host.experiments.tune dispatching to
the model-based tune on the firmware core + plant through ctypes (tests/fwsim_drive.py: the
same C controller, feed-forward terms and plant as drive_sim), and its configuration keys.
The slow matrix is tests/bench/bench_ffmodel.py."""
import os

import pytest
import yaml

from fftune.analysis.errors import FftuneError
from fftune.host import experiments as ex
from fftune.host.config import validate

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
TUNE = {"frequency_hz": 0.625, "amplitude_rad": "auto", "period_samples": 4096, "periods": 2,
        "settle_periods": 2, "harmonics": 7, "sweep": {"k_fc_max": 0.3, "points": 0},
        "search": {"max_experiments": 10}, "viscous": {"enabled": False}, "method": "model"}


def _truth(plant_path):
    with open(plant_path) as fh:
        p = yaml.safe_load(fh)["plant"]
    km = p["km"]
    return {"coulomb": p["coulomb"] / km, "asymmetry": p["coulomb"] * p.get("coulomb_asymmetry", 0.0) / km,
            "viscous": (p["viscous"] + p.get("load_viscous", 0.0)) / km,
            "position": p["coulomb"] * p.get("coulomb_position", 0.0) / km}


def run_model(tmp_path, plant_over, tune_over, base="plant_twomass.yaml"):
    from fwsim_drive import FwSimDrive, plant_file
    plant = plant_file(plant_over, base=os.path.join(REPO, "configs", base), directory=str(tmp_path))
    with open(plant) as fh:
        ctl = yaml.safe_load(fh)["controller"]
    cfg = validate({"output": "unused", "tune": dict(TUNE, **tune_over)}, "test")
    cfg["drive"]["controller"].update({k: ctl[k] for k in ("kp", "kd", "tau_d", "u_max")})
    drive = FwSimDrive(plant)
    try:
        drive.enable()
        session = ex.Session(drive, cfg, str(tmp_path / "out"), log=lambda s: None)
        results, data = ex.tune(session)
        left = {k: drive.get(k) for k in ("kfa", "kps", "kpc")}
    finally:
        drive.close()
    return results, data, _truth(plant), left


def test_config_keys_of_the_model_method():
    cfg = validate({"output": "o", "tune": {"method": "model", "terms": ["viscous", "coulomb"]}}, "c.yaml")
    assert cfg["tune"]["terms"] == ["viscous", "coulomb"] and cfg["tune"]["model"]["amplitude_rad"] == "auto"
    assert validate({"output": "o"}, "c.yaml")["tune"]["method"] == "search"
    for tune, key in (({"method": "model", "terms": ["coulomb", "stiction"]}, "tune.terms"),
                      ({"method": "model", "terms": []}, "tune.terms"),
                      ({"method": "model", "terms": "coulomb"}, "tune.terms"),
                      ({"method": "model", "terms": ["coulomb", "coulomb"]}, "tune.terms"),
                      ({"terms": ["coulomb", "viscous"]}, "tune.terms"),
                      ({"method": "gradient"}, "tune.method"),
                      ({"method": "model", "model": {"n_fit": 9}}, "tune.model.n_fit"),
                      ({"method": "model", "model": {"amplitude_rad": -1}}, "tune.model.amplitude_rad"),
                      ({"method": "model", "model": {"max_experiments": 2}}, "tune.model.max_experiments"),
                      ({"method": "model", "model": {"step": 1}}, "tune.model.step")):
        with pytest.raises(FftuneError) as exc:
            validate({"output": "o", "tune": tune}, "c.yaml")
        msg = str(exc.value)
        assert msg.startswith("c.yaml: ") and key in msg and "\n" not in msg


@pytest.mark.parametrize("capture", ["raw", "stats"])
def test_coulomb_alone_on_the_demo_plant(tmp_path, capture):
    r, data, truth, left = run_model(tmp_path, {"plant": {"viscous": 2e-3}}, {"terms": ["coulomb"], "capture": capture})
    assert data is None and r["method"] == "model" and r["model"]["converged"], r["model"]["stop_reason"]
    c = r["terms"]["coulomb"]
    assert set(c) >= {"value", "sigma", "unit", "object"} and c["unit"] == "V" and c["object"] == "0x2000:4"
    assert c["value"] == pytest.approx(truth["coulomb"], rel=0.01)
    assert 0 < c["sigma"] <= 0.01 * c["value"]
    assert r["experiments"] <= 3 and r["search"]["experiments"] == r["experiments"]
    assert r["k_fc_star"] == c["value"] and r["true_coulomb_v"] == pytest.approx(truth["coulomb"], rel=1e-6)
    assert r["odd_ratio_at_optimum"] < 0.005 and r["odd_ratio_at_optimum"] < r["ratio_at_zero"] / 10
    assert left == {"kfa": 0.0, "kps": 0.0, "kpc": 0.0}


def test_asymmetric_plant_both_directions(tmp_path):
    r, _, truth, _ = run_model(tmp_path, {"plant": {"coulomb_asymmetry": 0.3, "static": 7.6e-3}},
                               {"terms": ["coulomb", "asymmetry"]})
    c = r["terms"]["coulomb"]
    fc_plus, fc_minus = truth["coulomb"] + truth["asymmetry"], truth["coulomb"] - truth["asymmetry"]
    for est, true in ((c["fc_plus_v"], fc_plus), (c["fc_minus_v"], fc_minus)):
        assert abs(est / true - 1) <= 0.02 or abs(est - true) <= 2 * c["fc_plus_minus_sigma_v"]
    assert r["terms"]["asymmetry"]["object"] == "0x2000:9"
    assert r["model"]["gains"]["kfa"] == pytest.approx(r["terms"]["asymmetry"]["value"])


def test_paper_setup_three_terms(tmp_path):
    """configs/plant_paper.yaml (run-out: position-dependent friction, the paper's even 3 %),
    the configured 0.125 rad verifies."""
    r, _, truth, _ = run_model(tmp_path, {}, {"terms": ["coulomb", "viscous", "position"], "amplitude_rad": 0.125,
                                              "periods": 4}, base="plant_paper.yaml")
    assert r["model"]["converged"], r["model"]["stop_reason"]
    for name in ("coulomb", "viscous", "position"):
        t = r["terms"][name]
        assert abs(t["value"] - truth[name]) <= 2 * t["sigma"], (name, t, truth[name])
    assert r["experiments"] <= 5
    assert r["model"]["verification"]["amplitude_rad"] == 0.125
    assert r["odd_ratio_at_optimum"] <= 0.005 and r["even_ratio_at_optimum"] <= 0.005
    assert r["terms"]["position"]["phase_deg"] == pytest.approx(0.0, abs=2.0)   # the plant's sin(theta)


class NoDrive:
    """A drive that is not there: every run must come from the captures."""

    def __init__(self, truth, values):
        self.truth, self.values = truth, values

    def get(self, name):
        return self.values[name]

    def identity(self):
        return {"vendor_id": 0xFF7, "product_code": 1, "revision": 0x10000, "serial": 0,
                "firmware_version": "replay", "device_name": "none", "node_id": 1, "bus": "none"}

    def plant_truth(self):
        return self.truth

    def run(self, *a, **k):
        raise AssertionError("the replay asked the drive for a run")

    def set_parameters(self, values):
        raise AssertionError("the replay wrote to the drive")


def test_replay_from_the_captures_without_a_drive(tmp_path):
    """The recorded tune, read back from its captures (the session's capture store) by the
    same decisions, gives the same results; no run reaches a drive."""
    from fwsim_drive import FwSimDrive, plant_file
    plant = plant_file({"plant": {"coulomb_asymmetry": 0.2, "static": 7.0e-3, "viscous": 2e-3}},
                       directory=str(tmp_path))
    cfg = validate({"output": "unused", "tune": dict(TUNE, terms=["coulomb", "asymmetry", "viscous"])}, "test")
    out = str(tmp_path / "out")
    drive = FwSimDrive(plant)
    try:
        drive.enable()
        first, _ = ex.tune(ex.Session(drive, cfg, out, log=lambda s: None))
        truth = drive.plant_truth()
        values = {k: drive.get(k) for k in ("fs", "kp", "kd", "tau_d")}
    finally:
        drive.close()
    session = ex.Session(NoDrive(truth, values), cfg, out, log=lambda s: None)
    again, _ = ex.tune(session)
    assert session.counts == {"measured": 0, "resumed": first["experiments"]}
    assert again == first
    assert first["model"]["converged"] and set(first["terms"]) == {"coulomb", "asymmetry", "viscous"}
