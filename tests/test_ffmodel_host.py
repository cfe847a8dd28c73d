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


# ---- the one preflight (fftune.host.plan.preflight) for what the model tune asks for -------
DEMO = os.path.join(REPO, "configs", "demo.yaml")
# drive_sim's limits (as tests/test_host_preflight.py): u_max 10 V, fs 2560 Hz
SIM = dict(fs_hz=2560.0, u_max_v=10.0, rec_capacity=4194304, lines_capacity=1024, table_capacity=8192,
           amplitude_high=1000.0, source="test")


def _demo_model(tmp_path, changes, name="cfg.yaml"):
    """configs/demo.yaml with tune.method model and dotted keys changed, as a file."""
    with open(DEMO, encoding="utf-8") as fh:
        raw = yaml.safe_load(fh)
    raw["tune"]["method"] = "model"
    for key, value in changes.items():
        node = raw
        *parents, last = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    path = tmp_path / name
    path.write_text(yaml.safe_dump(raw))
    return str(path)


def _refused(cfg_path, limits=None):
    from fftune.host.config import load_config
    from fftune.host.plan import DriveLimits, preflight
    cfg = load_config(cfg_path)
    with pytest.raises(FftuneError) as exc:
        preflight(cfg, DriveLimits(**(limits or SIM)), steps=("tune",))
    msg = str(exc.value)
    assert "\n" not in msg and msg.endswith("nothing was run"), msg
    return msg


def test_model_plan_names_every_amplitude_it_may_ask_for():
    from fftune.host.ffmodel_tune import model_plan
    base = validate({"output": "o", "tune": {"method": "model"}}, "c.yaml")["tune"]
    # auto, coulomb alone: 1 rad, doubled while <= tune.amplitude_max_rad (8): 2, 4, 8
    p = model_plan(base)
    assert p["amplitude"] == 1.0 and p["amplitude_max"] == 8.0 and p["verify"] is None
    assert p["checked"] == [("tune.model.amplitude_rad", 1.0), ("tune.amplitude_max_rad", 8.0)]
    # with the position term pi, doubled once (2 pi <= 8 < 4 pi); a smaller numeric
    # tune.amplitude_rad (below half) verifies
    t = validate({"output": "o", "tune": {"method": "model", "terms": ["coulomb", "position"],
                                           "amplitude_rad": 0.3, "amplitude_max_rad": 7.0}}, "c.yaml")["tune"]
    p = model_plan(t)
    assert p["amplitude"] == pytest.approx(3.141592653589793) and p["verify"] == 0.3
    assert p["checked"] == [("tune.model.amplitude_rad", p["amplitude"]),
                            ("tune.amplitude_max_rad", 2 * p["amplitude"]), ("tune.amplitude_rad", 0.3)]
    # a larger numeric tune.amplitude_rad sets the identification amplitude (that key named);
    # tune.amplitude_max_rad below it: no doubling; an explicit verification amplitude
    t = validate({"output": "o", "tune": {"method": "model", "amplitude_rad": 2.5, "amplitude_max_rad": 4.0,
                                           "model": {"verify_amplitude_rad": 0.7}}}, "c.yaml")["tune"]
    assert model_plan(t)["checked"] == [("tune.amplitude_rad", 2.5), ("tune.model.verify_amplitude_rad", 0.7)]


@pytest.mark.parametrize("changes, needle", [
    # the identification amplitude (explicit, and auto with the position term: pi)
    ({"tune.model.amplitude_rad": 3.0, "limits.max_amplitude_rad": 2.0},
     "key 'tune.model.amplitude_rad': 3 rad peak is above 2 rad (limits.max_amplitude_rad)"),
    ({"tune.terms": ["coulomb", "position"], "limits.max_amplitude_rad": 3.0, "tune.amplitude_max_rad": 3.0},
     "key 'tune.model.amplitude_rad': 3.142 rad peak is above 3 rad (limits.max_amplitude_rad)"),
    # the largest amplitude its doubling can reach: 0.75 -> 1.5 -> 3 -> 6 <= 7
    ({"tune.model.amplitude_rad": 0.75, "tune.amplitude_max_rad": 7.0, "limits.max_amplitude_rad": 5.0},
     "key 'tune.amplitude_max_rad': 6 rad peak is above 5 rad (limits.max_amplitude_rad)"),
    # the verifying amplitude
    ({"tune.model.verify_amplitude_rad": 9.5},
     "key 'tune.model.verify_amplitude_rad': 9.5 rad peak is above 8 rad (limits.max_amplitude_rad)"),
    # the peak velocity of its sine: 2 pi 0.625 Hz x 8 rad = 31.4 rad/s
    ({"limits.max_velocity_rad_s": 20.0},
     "key 'tune.amplitude_max_rad': peak velocity 31.42 rad/s is above 20 rad/s (limits.max_velocity_rad_s)"),
    # its gains: K_fc's bound above the drive's output limit, K_v's above its object's range
    ({"tune.sweep.k_fc_max": 12.0},
     "key 'tune.sweep.k_fc_max': 12 V is above what the drive allows (its output limit u_max = 10 V)"),
])
def test_model_tune_refused_by_the_preflight(tmp_path, changes, needle):
    msg = _refused(_demo_model(tmp_path, changes))
    assert needle in msg, msg


def test_model_gains_against_the_drives_object_ranges(tmp_path):
    from fftune.host.config import od_param_high
    # a drive whose EDS allows K_v up to 0.05 V s/rad: the demo's k_v_max 0.1 is refused
    narrow = dict(SIM, gain_high={p: od_param_high(p) for p in ("KFC", "KFA", "KPS", "KPC")} | {"KV": 0.05})
    msg = _refused(_demo_model(tmp_path, {}), narrow)
    assert "key 'tune.viscous.k_v_max': viscous gain 0.1 V s/rad is above 0.05 V s/rad " \
           "(the range of the drive's object 0x2000:5)" in msg
    # ... also with tune.viscous.enabled false: the model tune sets K_v whatever that key says
    msg = _refused(_demo_model(tmp_path, {"tune.viscous.enabled": False}), narrow)
    assert "tune.viscous.k_v_max" in msg
    # K_fc against its object's range when it is below u_max (a drive with u_max 200 V)
    wide_u = dict(SIM, u_max_v=200.0, gain_high={"KFC": 0.2})
    msg = _refused(_demo_model(tmp_path, {}), wide_u)
    assert "key 'tune.sweep.k_fc_max': feed-forward 0.3 V is above 0.2 V (the range of the drive's " \
           "object 0x2000:4)" in msg


def test_signed_gains_asked_for_within_the_objects_and_u_max():
    from fftune.analysis.errors import InputError
    from fftune.analysis.ffmodel import FeedForwardModelTune
    from fftune.host.ffmodel_tune import signed_gain_limits
    assert signed_gain_limits(None) == {k: (-100.0, 100.0) for k in ("kfa", "kps", "kpc")}
    assert signed_gain_limits(7.5) == {k: (-7.5, 7.5) for k in ("kfa", "kps", "kpc")}
    t = FeedForwardModelTune(["coulomb", "asymmetry"], omega_rad_s=3.9, amplitude_rad=1.0,
                             gain_limits=signed_gain_limits(7.5), k_fc_max=0.3)
    assert t.limits["kfa"] == (-7.5, 7.5) and t.limits["kfc"] == (0.0, 0.3) and t.limits["kpc"] == (-7.5, 7.5)
    for bad in ({"kfc": (-1.0, 1.0)}, {"kfa": (0.5, 1.0)}):
        with pytest.raises(InputError):
            FeedForwardModelTune(["coulomb"], omega_rad_s=3.9, amplitude_rad=1.0, gain_limits=bad)


def _one_error_line(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fftune: error: "), err
    for n in needles:
        assert n in err[0], (n, err[0])


def test_fftune_tune_refuses_a_model_tune_before_contacting_the_drive(tmp_path, capsys):
    from fftune.host.cli import main
    from host_fixtures import free_port
    out = tmp_path / "out"
    for changes, needles in (
            ({"tune.model.amplitude_rad": 9.0}, ("tune.model.amplitude_rad", "9 rad", "8 rad",
                                                  "limits.max_amplitude_rad")),
            ({"drive.controller": {"u_max": 5.0}, "tune.sweep.k_fc_max": 6.0},
             ("tune.sweep.k_fc_max", "6 V", "u_max = 5 V"))):
        cfg = _demo_model(tmp_path, changes)
        # a port nobody serves: the error is the plan's, not the connection's
        assert main(["tune", "--config", cfg, "-i", "socketcand", "--port", str(free_port()),
                     "--out", str(out)]) == 2
        _one_error_line(capsys, *needles)
        assert not out.exists()


def test_machine_axis_with_a_model_tune_above_its_limits_is_refused(tmp_path, capsys):
    from fftune.host.cli import main
    from host_fixtures import free_port
    small = {"output": "out/unused", "drive": {"heartbeat_ms": 100, "fs_hz": 2560.0},
             "detect": {"enabled": False}, "quantify": {"enabled": False},
             "tune": dict(TUNE, capture="stats")}
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(small))
    machine = tmp_path / "m.yaml"
    machine.write_text(yaml.safe_dump({"machine": "t", "config": "small.yaml", "axes": [
        {"name": "a", "node_id": 3},
        {"name": "b", "node_id": 4, "overrides": {"tune": {"terms": ["coulomb", "position"]},
                                                   "limits": {"max_amplitude_rad": 2.0}}}]}))
    out = tmp_path / "out"
    assert main(["tune", "--machine", str(machine), "-i", "socketcand", "--port", str(free_port()),
                 "--out", str(out)]) == 2
    _one_error_line(capsys, "axis 'b': ", "tune.model.amplitude_rad", "3.142 rad", "2 rad",
                    "limits.max_amplitude_rad")
    assert not out.exists()


def test_refused_against_the_drives_limits_before_any_run(tmp_path):
    """The limits read from the drive (here its u_max, 10 V on the twomass plant) refuse a
    model tune in run_pipeline's preflight: no run, no output directory."""
    from fwsim_drive import FwSimDrive, plant_file
    from fftune.host.pipeline import run_pipeline
    plant = plant_file({}, base=os.path.join(REPO, "configs", "plant_twomass.yaml"), directory=str(tmp_path))
    with open(plant) as fh:
        u_max = float(yaml.safe_load(fh)["controller"]["u_max"])
    cfg = validate({"output": "unused", "drive": {"heartbeat_ms": 100},
                    "detect": {"enabled": False}, "quantify": {"enabled": False},
                    "tune": dict(TUNE, sweep={"k_fc_max": u_max + 2.0, "points": 0})}, "m.yaml")
    out = tmp_path / "out"
    drive = FwSimDrive(plant)
    try:
        drive.enable()
        with pytest.raises(FftuneError) as exc:
            run_pipeline(drive, cfg, str(out), steps=("tune",), figures=False, log=lambda s: None)
        assert drive.runs == 0 and not out.exists()
        assert drive.get("kfc") == 0.0 and drive.get("kfa") == 0.0
    finally:
        drive.close()
    msg = str(exc.value)
    assert f"key 'tune.sweep.k_fc_max': {u_max + 2.0:g} V is above what the drive allows (its output " \
           f"limit u_max = {u_max:g} V); nothing was run" in msg, msg


def test_plan_prints_the_model_tunes_amplitudes_and_runs(tmp_path):
    from fftune.host.config import load_config
    from fftune.host.plan import DriveLimits, preflight
    cfg = load_config(_demo_model(tmp_path, {"tune.terms": ["coulomb", "position"],
                                             "tune.model.max_experiments": 5}))
    plan = preflight(cfg, DriveLimits(**SIM), steps=("tune",))
    text = "\n".join(plan.lines("cfg"))
    # pi, doubled once within 8 rad; 5 runs of (2 + 2) periods of 4096 at 2560 Hz = 32 s
    assert "tune: at most 5 runs at 0.625 Hz, tune.method model (coulomb, position), amplitude 3.14159 rad " \
           "(doubled up to 6.28319 rad), K_fc 0 .. 0.3 V, 32.0 s of excitation at most" in text, text
    keys = [(c.key, c.what) for c in plan.checks if c.step == "tune"]
    assert ("tune.model.amplitude_rad", "peak") in keys and ("tune.amplitude_max_rad", "peak velocity") in keys
    assert ("tune.viscous.k_v_max", "viscous gain") in keys and ("tune.sweep.k_fc_max", "feed-forward") in keys
