"""`fftune tune` with `tune.method: model` against drive_sim over CANopen (issue 35): the
terms go to the drive as SDO writes of 0x2000:4, 5, 9, 10, 11, the results and the report
carry them."""
import os

import pytest
import yaml

from fftune.host.cli import main
from fftune.host.sim import start_drive_sim
from host_fixtures import drive_sim_missing_reason

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))

pytestmark = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                reason=drive_sim_missing_reason() or "")


def test_model_tune_over_canopen(tmp_path, capsys):
    from fftune.host.sim import derived_plant
    plant = derived_plant(os.path.join(REPO, "configs", "plant_twomass.yaml"),
                          {"plant": {"coulomb_asymmetry": 0.25, "static": 7.3e-3, "viscous": 2e-3}},
                          str(tmp_path / "plant.yaml"))
    drive = start_drive_sim(plant, log_path=str(tmp_path / "drive_sim.log"))
    try:
        cfg = yaml.safe_load(open(os.path.join(REPO, "configs", "demo.yaml")))
        cfg["tune"].update(method="model", terms=["coulomb", "asymmetry", "viscous"])   # 0.625 Hz
        cfg["tune"]["sweep"]["points"] = 0
        path = tmp_path / "model.yaml"
        path.write_text(yaml.safe_dump(cfg))
        out = tmp_path / "out"
        code = main(["tune", "--config", str(path), "--out", str(out), "--port", str(drive.port),
                     "--no-progress", "--no-figures"])
        assert code == 0
    finally:
        drive.stop()
    text = capsys.readouterr().out
    assert "feed-forward terms (tune.method model): converged" in text
    assert "on object 0x2000:09" in text and "K_fa = " in text      # the recommendation names every term's object
    t = yaml.safe_load(open(out / "results.yaml"))["tune"]
    assert t["method"] == "model" and t["model"]["converged"], t["model"]["stop_reason"]
    fc, a = 5.785e-3 / 0.05, 0.25 * 5.785e-3 / 0.05
    terms = t["terms"]
    assert set(terms) == {"coulomb", "asymmetry", "viscous"}
    assert terms["coulomb"]["value"] == pytest.approx(fc, rel=0.02)
    assert terms["coulomb"]["fc_plus_v"] == pytest.approx(fc + a, rel=0.02)
    assert terms["coulomb"]["fc_minus_v"] == pytest.approx(fc - a, rel=0.03)
    assert terms["viscous"]["value"] == pytest.approx(2e-3 / 0.05, rel=0.05)
    assert all({"value", "sigma", "unit", "object"} <= set(v) for v in terms.values())
    assert t["experiments"] <= 5 and t["odd_ratio_at_optimum"] < 0.01 and t["even_ratio_at_optimum"] < 0.01
