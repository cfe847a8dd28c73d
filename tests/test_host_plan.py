"""fftune.host.plan: a configuration's runs, excitation time and upload bytes before it
runs, checked against the time budget a session measures (results.yaml) and by hand."""
import os

import pytest

from fftune.host.config import load_config
from fftune.host.plan import bus_rates, experiment_plan, project, stats_bytes
from host_fixtures import REPO


def test_demo_plan_by_hand():
    cfg = load_config(os.path.join(REPO, "configs", "demo.yaml"))
    plan = {p.step: p for p in experiment_plan(cfg, 2560.0)}
    d, q, t = plan["detect"], plan["quantify"], plan["tune"]
    # detect: 3 levels x 4 realizations of (2 settle + 2 recorded) x 4096 samples at 2560 Hz
    assert d.runs == 12 and d.excitation_s == pytest.approx(12 * 4 * 4096 / 2560)
    assert d.raw_bytes == 12 * 2 * 4096 * 2 * 4
    # the drive's line statistics: every line from the lowest to the highest excited one of
    # 4 .. 160 (2.5 .. 100 Hz at 0.625 Hz), 8 + 44 bytes a line, per run
    from fftune.host.experiments import detect_lines
    k_min, k_max, lines, band = detect_lines(cfg["detect"], 2560.0)
    assert (k_min, k_max) == (4, 160) and band[0] == lines.excited[0] and band[-1] == lines.excited[-1]
    assert 150 <= band.size <= 157
    big = {p.step: p for p in experiment_plan(cfg, 2560.0, lines_capacity=1024)}["detect"]
    assert big.stats_bytes == 12 * (8 + 44 * band.size)
    small = {p.step: p for p in experiment_plan(cfg, 2560.0, lines_capacity=band.size - 1)}["detect"]
    assert small.stats_bytes is None and "raw only" in small.note
    # quantify: 3 levels x 3 frequencies x 2 repeats of (2 + 1) x 2048
    assert q.runs == 18 and q.excitation_s == pytest.approx(18 * 3 * 2048 / 2560)
    assert q.stats_bytes == 18 * stats_bytes(7, 2, 0) == 18 * 176
    assert stats_bytes(7, 2, 1) == 184        # a tune experiment (tests/test_stats_drive_sim.py)
    assert t.runs >= cfg["tune"]["search"]["max_experiments"]


def test_bus_rates_solve_two_steps_and_project_sums():
    a, b = 0.05, 1 / 40e3          # 50 ms per run, 40 kB/s
    raw = (12, 786432, 12 * a + 786432 * b)
    small = (18, 3168, 18 * a + 3168 * b)
    sa, sb = bus_rates(raw, small)
    assert sa == pytest.approx(a) and sb == pytest.approx(b)
    cfg = load_config(os.path.join(REPO, "configs", "demo.yaml"))
    plan = experiment_plan(cfg, 2560.0, lines_capacity=1024)
    st, rw = project(plan, sa, sb, 0.1, "stats"), project(plan, sa, sb, 0.1, "raw")
    assert st["total"]["excitation"] == rw["total"]["excitation"] == pytest.approx(sum(p.excitation_s for p in plan))
    assert st["detect"]["bus"] < rw["detect"]["bus"] / 5         # 12 x 7 kB instead of 786 kB
    assert st["quantify"]["bus"] < rw["quantify"]["bus"]
    for k in ("excitation", "bus", "host"):
        assert st["total"][k] == pytest.approx(sum(st[s][k] for s in ("detect", "quantify", "tune")))
    with pytest.raises(ValueError):
        bus_rates((1, 10, 1.0), (0, 0, 0.0))
