"""results.yaml's time budget (issue 13 item 2): excitation (settle + recorded periods at
fs), bus (SDO transfers), host (the rest), per step and in total.

The live test runs `fftune quantify` against drive_sim behind its CAN bus model at
125 kbit/s and checks the budget against what it can be checked with independently: the
excitation against the capture files' own metadata (periods, N, fs), the bus time against
the physical lower bound of the bytes the recorder uploads carried (7 payload bytes per
frame of at least 47 + 8 x 7 bit times, plus ...), the sum against the step's wall time.
"""
import glob
import os

import pytest
import yaml

from fftune.analysis.capture import read_run
from fftune.host.cli import main
from fftune.host.pipeline import summary_lines, time_budget
from fftune.host.sim import start_drive_sim
from host_fixtures import REPO, drive_sim_missing_reason

DEMO = os.path.join(REPO, "configs", "demo.yaml")
PLANT = os.path.join(REPO, "configs", "plant_twomass.yaml")


def test_budget_free_run_drive_is_faster_than_real_time():
    before = {"excitation_s": 1.0, "transfer_s": 0.5, "run_wait_s": 0.2}
    after = {"excitation_s": 11.0, "transfer_s": 2.5, "run_wait_s": 1.2}
    b = time_budget(before, after, wall_s=5.0)
    # the simulated drive needed 1 s for 10 s of excitation: host = 5 - 2 - 1
    assert b == {"excitation": 10.0, "bus": 2.0, "host": 2.0, "wall": 5.0, "drive_wait": 1.0}


def test_budget_real_time_drive_polling_latency_is_host_time():
    b = time_budget({}, {"excitation_s": 10.0, "transfer_s": 2.0, "run_wait_s": 10.4}, wall_s=13.0)
    assert b["host"] == pytest.approx(1.0)  # 13 - 2 - 10: the 0.4 s of polling latency included
    assert b["excitation"] + b["bus"] + b["host"] == pytest.approx(b["wall"])


def test_summary_prints_the_budget(monkeypatch):
    import fftune.host.report as report
    monkeypatch.setattr(report, "key_numbers", lambda results: [])  # the budget lines alone
    results = {"time_budget_s": {"tune": {"excitation": 26.6, "bus": 3.1, "host": 1.0, "wall": 30.7,
                                          "drive_wait": 26.9},
                                 "total": {"excitation": 26.6, "bus": 3.1, "host": 1.0, "wall": 30.7,
                                           "drive_wait": 26.9}}}
    text = "\n".join(summary_lines(results, "out"))
    assert "time budget [s]" in text
    assert "tune                    26.6      3.1      1.0     30.7  (26.9)" in text


@pytest.mark.skipif(drive_sim_missing_reason() is not None, reason=drive_sim_missing_reason() or "")
def test_live_budget_against_captures_and_the_bus_model(tmp_path):
    bitrate = 125_000
    cfg = yaml.safe_load(open(DEMO))
    cfg["quantify"].update(frequencies_hz=[2.5], rms_levels=[0.35], repeats=2, period_samples=1024)
    config = tmp_path / "q.yaml"
    config.write_text(yaml.safe_dump(cfg))
    sim = start_drive_sim(PLANT, bitrate=bitrate, log_path=str(tmp_path / "drive_sim.log"))
    try:
        out = tmp_path / "out"
        assert main(["quantify", "--config", str(config), "--out", str(out), "--port", str(sim.port),
                     "--no-progress", "--no-figures"]) == 0
    finally:
        sim.stop()
    results = yaml.safe_load(open(out / "results.yaml"))
    budget = results["time_budget_s"]
    assert set(budget) == {"quantify", "total"}
    q = budget["quantify"]
    assert set(q) == {"excitation", "bus", "host", "wall", "drive_wait"}
    runs = [read_run(p) for p in sorted(glob.glob(str(out / "captures" / "*.h5")))]
    assert len(runs) == 2
    excitation = sum((r.meta["metadata"]["drive_settle_periods"] + r.meta["record_periods"])
                     * r.meta["n_period"] / r.meta["fs_hz"] for r in runs)
    assert q["excitation"] == pytest.approx(excitation, abs=2e-3)
    # the uploads alone: 7 payload bytes per frame of at least 47 + 56 bit times
    uploaded = sum(sum(v.size for v in r.signals.values()) * 4 for r in runs)
    assert q["bus"] >= uploaded / 7 * (47 + 56) / bitrate
    assert q["host"] >= 0
    assert q["wall"] == pytest.approx(results["timing_s"]["quantify"], abs=0.05)
    assert budget["total"] == q
