"""Configuration files: the shipped ones validate, bad ones fail naming file, key, expectation."""
import os

import pytest

from fftune.analysis.errors import FftuneError
from fftune.host.config import check_output_dir, expand_values, load_config

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))


def _write(tmp_path, text):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    return str(p)


def test_paper_config_has_the_paper_settings():
    cfg = load_config(os.path.join(REPO, "configs", "paper.yaml"))
    d, q = cfg["detect"], cfg["quantify"]
    assert (d["period_samples"], d["realizations"], d["periods"], d["group"]) == (8192, 10, 10, 5)
    assert cfg["drive"]["fs_hz"] == 2560.0
    assert len(d["rms_levels"]) == 20
    assert d["rms_levels"][0] == pytest.approx(0.3) and d["rms_levels"][-1] == pytest.approx(5.0)
    ratios = [b / a for a, b in zip(d["rms_levels"], d["rms_levels"][1:])]
    assert max(ratios) == pytest.approx(min(ratios))          # log-spaced
    # the paper's 5 Hz steps, up to 180 Hz: H_7 of it (1260 Hz) below fs/2 = 1280 Hz (the
    # paper's 300 Hz needed its 5120 Hz; configs/paper.yaml's header)
    assert q["frequencies_hz"][0] == 5.0 and q["frequencies_hz"][-1] == 180.0
    assert len(q["frequencies_hz"]) == 36 and q["harmonics"] == 7
    assert (q["repeats"], q["period_samples"]) == (10, 2048)
    assert q["rms_levels"][0] == pytest.approx(0.07) and q["rms_levels"][-1] == pytest.approx(1.41)


def test_demo_config_validates():
    cfg = load_config(os.path.join(REPO, "configs", "demo.yaml"))
    assert cfg["output"] == "out/demo"
    assert cfg["tune"]["search"]["max_experiments"] <= 8


@pytest.mark.parametrize("text, needle", [
    ("detect:\n  realizations: 0\n", "key 'detect.realizations': expected an integer >= 1, got 0"),
    ("detect:\n  period_samples: 1000\n", "key 'detect.period_samples': expected a power of two"),
    ("detect:\n  inject: motor\n", "key 'detect.inject': expected one of reference, plant_input"),
    ("tune:\n  sweep: {points: two}\n", "key 'tune.sweep.points': expected an integer"),
    ("tune:\n  k_fc: 1\n", "key 'tune.k_fc': unknown key"),
    ("quantify:\n  rms_levels: {start: 0.1, stop: 1}\n", "key 'quantify.rms_levels': expected a list"),
    ("quantify:\n  frequencies_hz: [5, -1]\n", "key 'quantify.frequencies_hz[1]': expected a number > 0"),
    ("drive:\n  node_id: 200\n", "key 'drive.node_id': expected an integer <= 127"),
    # attempts per SDO request: 0 would send nothing (it was raised to 1 without a word)
    ("drive:\n  sdo_retries: 0\n", "key 'drive.sdo_retries': expected an integer >= 1, got 0"),
    ("detect: [1, 2]\n", "key 'detect': expected a mapping"),
])
def test_bad_config_names_file_key_and_expectation(tmp_path, text, needle):
    path = _write(tmp_path, text)
    with pytest.raises(FftuneError) as exc:
        load_config(path)
    msg = str(exc.value)
    assert msg.startswith(path) and needle in msg


def test_drive_client_refuses_zero_sdo_attempts():
    from fftune.host.drive import BusOptions, DriveClient
    with pytest.raises(ValueError, match="sdo_retries: attempts per SDO request"):
        DriveClient(BusOptions(), sdo_retries=0)


def test_invalid_yaml_names_the_line(tmp_path):
    path = _write(tmp_path, "detect:\n  periods: 3\n  band_hz: [1, 2\n")
    with pytest.raises(FftuneError, match=r"c\.yaml:\d+: invalid YAML"):
        load_config(path)


def test_missing_config_file_is_named(tmp_path):
    with pytest.raises(FftuneError, match="nope.yaml: cannot read configuration"):
        load_config(str(tmp_path / "nope.yaml"))


def test_range_specs_expand():
    assert expand_values({"start": 5, "stop": 20, "step": 5}, "f", "k") == [5.0, 10.0, 15.0, 20.0]
    vals = expand_values({"start": 0.1, "stop": 10, "count": 3}, "f", "k")
    assert vals == pytest.approx([0.1, 1.0, 10.0])


def test_unwritable_output_dir_is_refused(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(FftuneError, match="output directory .*file/out: cannot create it"):
        check_output_dir(str(blocker / "out"))
    assert check_output_dir(str(tmp_path / "ok" / "deep")).endswith("deep")
