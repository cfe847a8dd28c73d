"""The tune strategy as an ask/tell object (fftune.analysis.tune_strategy, issue 35 item 3):
a tune run on the firmware core + plant (tests/fwsim_drive.py), then replayed from its
captures alone, with no drive: the same experiments asked, the same K_fc*, sigma and
experiment count, the same results; and the protocol's misuse named."""
import math
import os
import sys

import pytest

from fftune.analysis import tune_strategy as ts
from fftune.analysis.errors import FftuneError
from fftune.host import experiments as ex
from fftune.host.captures import CaptureStore
from host_fixtures import REPO

sys.path.insert(0, os.path.join(REPO, "tests", "bench"))
import bench_tune  # noqa: E402
import bench_tune_matrix  # noqa: E402

MATRIX = {name: (plant, tune) for rows in bench_tune_matrix.families().values() for name, plant, tune, _ in rows}


def _tune_on_drive(row, capture, out):
    """A tune of matrix row ``row`` on the simulated drive; (results, what the replay needs:
    the configuration, the sample rate, the drive's limit and settings)."""
    from fwsim_drive import FwSimDrive, plant_file
    plant, tune = MATRIX[row]
    cfg = bench_tune.tune_config(dict(tune, capture=capture))
    if capture == "stats":
        cfg["detect"]["encoder_step_rad"] = 2 * math.pi / 2000
    if "drift" in plant:          # the plant's friction steps during the tune (bench_tune.run_row)
        plant = dict(plant, drift=dict(bench_tune.NO_DRIFT, **plant["drift"]))
        path = plant_file(plant, base=bench_tune.DRIFT_BASE, directory=str(out))
    else:
        path = plant_file(plant, directory=str(out))
    with FwSimDrive(path) as drive:
        drive.enable()
        session = ex.Session(drive, cfg, str(out / "out"), log=lambda s: None)
        results, _ = ex.tune(session)
        facts = {"fs_hz": session.fs_hz, "k_fc_limit_v": ex.k_fc_limit(session),
                 "drive_settings": ex.drive_settings(session), "controller": session.controller,
                 "truth": (session.truth["sim_fc_volt"], drive.plant_truth()["sim_fc_volt"])}
    return cfg, results, facts


def _replay(cfg, out_dir, facts, capture, strategy=None):
    """The strategy (default: the search's) driven by the captures in ``out_dir`` alone."""
    store = CaptureStore(out_dir)
    strategy = strategy or ts.SearchTune(cfg, fs_hz=facts["fs_hz"], k_fc_limit_v=facts["k_fc_limit_v"],
                                         capture=capture, drive_settings=facts["drive_settings"])
    used = []

    def load(request):
        rec = store.load(request.key, dict(facts["controller"], **ex.tune_request(request)))
        used.append(request.key)
        return None if rec is None else ts.measurement_from_record(rec, facts["controller"])

    results, _ = ts.replay(strategy, load)
    return ts.with_truth(results, *facts["truth"]), used


@pytest.mark.parametrize("row, capture", [("demo, noise 0.002, seed 1", "stats"),
                                          ("j1 x30, seed 1", "raw"),
                                          ("step -20 % at 30 s", "raw")])
def test_a_tune_replays_from_its_captures_to_the_same_result(tmp_path, row, capture):
    cfg, live, facts = _tune_on_drive(row, capture, tmp_path)
    replayed, used = _replay(cfg, str(tmp_path / "out"), facts, capture)
    s, r = live["search"], replayed["search"]
    assert r["k_fc_star"] == s["k_fc_star"] and r["sigma_v"] == s["sigma_v"]
    assert r["experiments"] == s["experiments"] and r["cause"] == s["cause"]
    assert replayed == live
    # every capture of the tune was asked for, each once
    files = {f[:-len(".stats.json")] if f.endswith(".stats.json") else f[:-3]
             for f in os.listdir(tmp_path / "out" / "captures") if f.endswith((".h5", ".stats.json"))}
    assert sorted(used) == sorted(files) and len(used) == len(set(used))
    if row.startswith("j1"):
        assert live["frequency_changes"] and any("-f" in k for k in used)
    if row.startswith("step"):
        assert s["cause"] == "non-stationary" and any(k.endswith("-repeat") for k in used)


def test_the_model_tune_replays_through_the_same_protocol(tmp_path):
    """`tune.method: model` (ModelTune around FeedForwardModelTune): the same replay."""
    import yaml
    from fftune.host.config import validate
    from fftune.host.ffmodel_tune import _controller
    from fwsim_drive import FwSimDrive, plant_file
    import test_ffmodel_host as tm
    path = plant_file({"plant": {"coulomb_asymmetry": 0.2, "static": 7.0e-3, "viscous": 2e-3}},
                      directory=str(tmp_path))
    with open(path) as fh:
        ctl = yaml.safe_load(fh)["controller"]
    cfg = validate({"output": "unused", "tune": dict(tm.TUNE, terms=["coulomb", "asymmetry", "viscous"])}, "test")
    cfg["drive"]["controller"].update({k: ctl[k] for k in ("kp", "kd", "tau_d", "u_max")})
    with FwSimDrive(path) as drive:
        drive.enable()
        session = ex.Session(drive, cfg, str(tmp_path / "out"), log=lambda s: None)
        live, _ = ex.tune(session)
        fc = session.truth["sim_fc_volt"]
        facts = {"controller": session.controller, "truth": (fc, fc)}
        strategy = ts.ModelTune(cfg, fs_hz=session.fs_hz, capture="raw", controller=_controller(session))
    replayed, used = _replay(cfg, str(tmp_path / "out"), facts, "raw", strategy)
    assert replayed["terms"] == live["terms"] and replayed["experiments"] == live["experiments"]
    assert replayed == live and live["model"]["converged"]
    assert used == [e["key"] for e in live["model"]["experiments"]]


def test_a_replay_without_the_capture_of_an_experiment_names_it(tmp_path):
    cfg, _, facts = _tune_on_drive("demo, noise 0.002, seed 1", "raw", tmp_path)
    victim = sorted(os.listdir(tmp_path / "out" / "captures"))[-1]
    os.remove(tmp_path / "out" / "captures" / victim)
    with pytest.raises(ValueError, match="no capture of experiment 'tune-"):
        _replay(cfg, str(tmp_path / "out"), facts, "raw")


def test_the_protocol_refuses_a_measurement_of_another_request():
    cfg = bench_tune.tune_config({"amplitude_rad": 0.5})
    # the sine on the drive's DFT grid: 0.625 Hz is 1 cycle in 4096 samples at 2560 Hz, not at 1000 Hz
    with pytest.raises(FftuneError, match="bench_tune: key 'tune.frequency_hz': 0.625 Hz is not on the DFT grid"):
        ts.SearchTune(cfg, fs_hz=1000.0, k_fc_limit_v=2.0, capture="raw")
    strategy = ts.SearchTune(cfg, fs_hz=2560.0, k_fc_limit_v=2.0, capture="raw")
    first = strategy.ask()
    # the first experiment of a fixed amplitude: the search's K_fc = 0, K_v = 0 at 0.5 rad
    assert first.tag == "search" and first.gains == {"kfc": 0.0, "kv": 0.0} and first.amplitude_rad == 0.5
    assert first.index == 0 and strategy.ask() is first
    other = ts.ExperimentRequest(**dict(vars(first), key="tune-other"))
    with pytest.raises(ValueError, match="told 'tune-other', but asked 'tune-search-kfc0-kv0'"):
        strategy.tell(other, None)
    with pytest.raises(ValueError, match="not finished"):
        strategy.result()


def test_the_model_tune_asks_through_the_protocol_and_refuses_misuse():
    """ModelTune's first request: the identification at the auto amplitude (1 rad without the
    position term) with every gain 0, the lines k = 0 .. 8 asked of the drive's statistics."""
    from fftune.host.config import validate
    import test_ffmodel_host as tm
    cfg = validate({"output": "unused", "tune": dict(tm.TUNE, terms=["coulomb", "viscous"])}, "test")
    strategy = ts.ModelTune(cfg, fs_hz=2560.0, capture="stats")
    first = strategy.ask()
    assert first.tag == "identify" and first.amplitude_rad == 1.0 and first.index == 0
    assert first.gains == {"kfc": 0.0, "kv": 0.0, "kfa": 0.0, "kps": 0.0, "kpc": 0.0}
    assert first.stats["harmonics"] == ts.N_LINES == 8 and strategy.ask() is first
    with pytest.raises(ValueError, match="told 'tune-x', but asked 'tune-model-0-identify-a1-"):
        strategy.tell(ts.ExperimentRequest(**dict(vars(first), key="tune-x")), None)
    with pytest.raises(ValueError, match="not finished"):
        strategy.result()
