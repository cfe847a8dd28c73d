"""`fftune fleet`: a fleet's captures re-analysed on Dask (host/fleet.py).

The fleet is made here on the Python test double of the drive (tests/host_fixtures.py,
about a second per capture directory): two axes of one machine with unequal Coulomb
levels (0.3 V, 0.5 V), one of them on two dates with a drifted level (0.35 V), plus a
damaged and a partial copy. The table must carry what the live sessions found, row by
row (unequal truths: a mix-up of rows fails), whatever the scheduler.
"""
import json
import os
import shutil
import subprocess
import sys

import can
import pytest
import yaml

from fftune.host import fleet
from fftune.host.cli import main
from fftune.host.pipeline import run_pipeline
from host_fixtures import EDS, FakeDriveForTests, free_port
from test_host_experiments import _cfg

VENV_BIN = os.path.dirname(sys.executable)


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    for rel, fc in (("m1/x/2026-01-01", 0.3), ("m1/x/2026-02-01", 0.35), ("m1/y", 0.5)):
        d = FakeDriveForTests(fc_volt=fc, fv_volt=0.02, noise_std=1e-5)
        d.enable()
        run_pipeline(d, _cfg(), str(root / rel), log=lambda s: None, figures=False)
    # a damaged copy (one detect capture with a flipped byte) and a partial one (the last
    # tune run missing)
    shutil.copytree(root / "m1/y", root / "m2/damaged")
    victim = root / "m2/damaged/captures/detect-L01-M02.h5"
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    shutil.copytree(root / "m1/y", root / "m2/partial")
    tune_files = sorted((root / "m2/partial/captures").glob("tune-*"))
    tune_files[-1].unlink()
    return root


def _live(path):
    with open(os.path.join(path, "results.yaml")) as fh:
        return yaml.safe_load(fh)


@pytest.fixture(scope="module")
def local_rows(fleet_dir):
    items, bad = fleet.discover([str(fleet_dir)])
    assert bad == []
    return fleet.run_graph(items, workers=2)


def test_local_scheduler_table_matches_the_live_sessions(fleet_dir, local_rows):
    by = {os.path.relpath(os.path.dirname(r["source"]), fleet_dir): r for r in local_rows}
    assert sorted(by) == ["m1/x/2026-01-01", "m1/x/2026-02-01", "m1/y", "m2/damaged", "m2/partial"]
    for rel in ("m1/x/2026-01-01", "m1/x/2026-02-01", "m1/y"):
        live, row = _live(fleet_dir / rel), by[rel]
        assert row["status"] == "ok", row["reason"]
        assert row["k_fc_star"] == live["tune"]["k_fc_star"]
        assert row["k_fc_sigma"] == live["tune"]["search"]["sigma_v"]
        assert row["ratio_at_k_fc_star"] == live["tune"]["ratio_at_k_fc_star"]
        ev = {e["k_fc"]: e["ratio_std"] for e in live["tune"]["search"]["evaluations"]}
        assert row["ratio_at_zero_std"] == ev[0.0] and row["ratio_at_zero_std"] > 0
        k_ver = live["tune"]["search"]["verification_k_fc"]
        assert row["ratio_at_k_fc_star_std"] == ev[min(ev, key=lambda k: abs(k - k_ver))] > 0
        assert row["hosidf_max_odd_rel"] == live["quantify"]["max_odd_relative_level"]
        assert row["bla_nl_re_output_db"] == [lv["summary_db"]["nl_re_output_db"]
                                              for lv in live["detect"]["levels"]]
        assert row["detect_verdict"] == live["detect"]["verdict"]
        assert row["runs"] == live["experiments"]["measured"]
    # names: <machine>/<axis>[/<date>]; the two dates of axis x are one axis
    assert [(by[r]["machine"], by[r]["axis"]) for r in ("m1/x/2026-01-01", "m1/x/2026-02-01", "m1/y")] \
        == [("m1", "x"), ("m1", "x"), ("m1", "y")]
    assert abs(by["m1/x/2026-02-01"]["k_fc_star"] / 0.35 - 1) < 0.02
    assert abs(by["m1/y"]["k_fc_star"] / 0.5 - 1) < 0.02


def test_every_column_is_the_live_sessions_value(fleet_dir, local_rows):
    """Each column of the table against the field of the live session's results.yaml it
    reports (the even levels are not the odd ones there: one filled from the other fails)."""
    by = {os.path.relpath(os.path.dirname(r["source"]), fleet_dir): r for r in local_rows}
    for rel in ("m1/x/2026-01-01", "m1/x/2026-02-01", "m1/y"):
        live, row = _live(fleet_dir / rel), by[rel]
        det, q, t = live["detect"], live["quantify"], live["tune"]
        s = t["search"]
        summ = [lv["summary_db"] for lv in det["levels"]]
        want = {
            "detect_verdict": det["verdict"],
            "bla_rms_levels": [lv["rms_requested"] for lv in det["levels"]],
            "bla_nl_re_output_db": [x["nl_re_output_db"] for x in summ],
            "bla_noise_re_output_db": [x["noise_re_output_db"] for x in summ],
            "bla_odd_re_output_db": [x["odd_re_output_db"] for x in summ],
            "bla_even_re_output_db": [x["even_re_output_db"] for x in summ],
            "bla_max_change_db": det["bla_max_change_over_levels_db"],
            "hosidf_max_odd_rel": q["max_odd_relative_level"],
            "hosidf_max_even_rel": q["max_even_relative_level"],
            "k_fc_star": t["k_fc_star"], "k_fc_sigma": s["sigma_v"], "k_fc_converged": s["converged"],
            "tune_stop_reason": s["stop_reason"], "ratio_at_zero": t["ratio_at_zero"],
            "ratio_at_k_fc_star": t["ratio_at_k_fc_star"], "tune_experiments": s["experiments"],
            "k_fc_true": t["true_coulomb_v"], "runs": live["experiments"]["measured"],
        }
        for col, value in want.items():
            assert row[col] == value, (rel, col)
        # the pairs a mix-up would confuse differ in the data
        assert q["max_even_relative_level"] != q["max_odd_relative_level"]
        assert want["bla_even_re_output_db"] != want["bla_odd_re_output_db"]
        assert want["bla_noise_re_output_db"] != want["bla_nl_re_output_db"]
        assert t["ratio_at_zero"] != t["ratio_at_k_fc_star"] and row["ratio_at_zero_std"] != row["ratio_at_k_fc_star_std"]
        assert row["k_fc_true"] == pytest.approx({"m1/x/2026-01-01": 0.3,
                                                 "m1/x/2026-02-01": 0.35, "m1/y": 0.5}[rel])


def test_damaged_and_partial_captures_are_rows_with_their_reason(fleet_dir, local_rows):
    by = {os.path.relpath(os.path.dirname(r["source"]), fleet_dir): r for r in local_rows}
    dmg = by["m2/damaged"]
    assert dmg["status"] == "partial"
    assert "detect:" in dmg["reason"] and "detect-L01-M02.h5" in dmg["reason"] and "checksum" in dmg["reason"]
    assert dmg["detect_verdict"] is None
    assert dmg["k_fc_star"] == by["m1/y"]["k_fc_star"]          # the undamaged steps analysed
    part = by["m2/partial"]
    assert part["status"] == "partial" and "tune: partial capture: run tune-" in part["reason"]
    assert part["k_fc_star"] is None
    assert part["detect_verdict"] == by["m1/y"]["detect_verdict"]


def test_cli_writes_table_and_drift_plots_and_names_a_path_that_is_no_capture(fleet_dir, local_rows,
                                                                              tmp_path, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("not a capture")
    out = tmp_path / "out"
    # (in this process: the default multiprocessing scheduler is local_rows')
    assert main(["fleet", str(fleet_dir / "m1"), str(notes), "--out", str(out), "--scheduler", "sync",
                 "--format", "csv"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"fftune fleet: {notes}: not a capture directory nor a CAN log "
                   f"(.log, .asc, .blf, .trc, .csv, .db) (skipped)"]
    rows = fleet.read_table(str(out / "fleet.csv"))
    m1 = [r for r in local_rows if r["machine"] == "m1"]
    assert [r["k_fc_star"] for r in rows] == [r["k_fc_star"] for r in m1]
    assert [r["bla_nl_re_output_db"] for r in rows] == [json.dumps(r["bla_nl_re_output_db"]) for r in m1]
    # one per axis with a K_fc* (x: two dates in one plot)
    assert sorted(p.name for p in out.glob("*.png")) == ["drift_m1_x.png", "drift_m1_y.png"]
    assert (out / "drift_m1_x.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in out.iterdir() if p.name.startswith(".tmp")]


def test_nothing_to_analyse_is_one_error_line(tmp_path, capsys):
    assert main(["fleet", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"fftune fleet: {tmp_path / 'missing'}: no such file or directory (skipped)",
                   "fftune: error: fleet: nothing to analyse (no capture directory or CAN log among the paths)"]
    assert not (tmp_path / "o").exists()


def test_unknown_scheduler_is_one_line_before_anything_is_written(tmp_path, capsys):
    (tmp_path / "a" / "captures").mkdir(parents=True)
    (tmp_path / "a" / "captures" / "detect-L00-M00.h5").write_bytes(b"x")
    assert main(["fleet", str(tmp_path / "a"), "--out", str(tmp_path / "o"), "--scheduler", "tpc://x:1"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "fftune: error: --scheduler tpc://x:1: expected tcp://HOST:PORT, processes, threads or sync"]
    assert not (tmp_path / "o").exists()


@pytest.mark.skipif(not os.path.exists(EDS), reason=f"EDS not generated ({EDS} missing; make setup)")
def test_can_log_without_runs_is_a_row_naming_its_node(tmp_path):
    f = tmp_path / "m3" / "idle.log"
    f.parent.mkdir()
    with can.Logger(str(f)) as log:
        log(can.Message(arbitration_id=0x603, data=[0x40, 0x00, 0x10, 0, 0, 0, 0, 0],
                        is_extended_id=False, timestamp=1.1))
        log(can.Message(arbitration_id=0x583, data=[0x43, 0x00, 0x10, 0, 0x92, 0x01, 0x02, 0],
                        is_extended_id=False, timestamp=1.2))
    rows = fleet.run_graph(fleet.discover([str(f)])[0], scheduler="sync")
    assert [(r["machine"], r["axis"], r["node_id"], r["status"]) for r in rows] == \
        [("m3", "node3", 3, "error")]
    assert "no complete run" in rows[0]["reason"] and "node 3" in rows[0]["reason"]


def test_local_cluster_gives_the_same_table(fleet_dir, local_rows):
    from distributed import LocalCluster

    items, _ = fleet.discover([str(fleet_dir)])
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      host="127.0.0.1") as cluster:
        rows = fleet.run_graph(items, scheduler=cluster.scheduler_address)
    assert fleet.arrow_table(rows).equals(fleet.arrow_table(local_rows))


def test_dask_scheduler_and_worker_from_the_venv_give_the_same_table(fleet_dir, local_rows, tmp_path):
    from distributed import Client

    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    logs = [open(tmp_path / n, "w") for n in ("scheduler.log", "worker.log")]
    procs = [subprocess.Popen([os.path.join(VENV_BIN, "dask"), "scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--no-dashboard"], stdout=logs[0], stderr=logs[0])]
    try:
        procs.append(subprocess.Popen([os.path.join(VENV_BIN, "dask"), "worker", addr, "--nthreads", "1",
                                       "--nworkers", "1", "--no-dashboard", "--host", "127.0.0.1"],
                                      stdout=logs[1], stderr=logs[1]))
        with Client(addr, timeout=30) as c:
            c.wait_for_workers(1, timeout=60)
        out = tmp_path / "out"
        assert main(["fleet", str(fleet_dir / "m2"), str(fleet_dir / "m1" / "y"), "--out", str(out),
                     "--scheduler", addr, "--no-figures"]) == 0
        rows = fleet.read_table(str(out / "fleet.parquet"))
        expected = [r for r in local_rows if r["machine"] == "m2" or r["axis"] == "y"]
        assert len(rows) == 3 and fleet.arrow_table(rows).equals(fleet.arrow_table(expected))
    finally:
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for fh in logs:
            fh.close()


def test_analysis_package_does_not_import_dask():
    code = ("import sys, pkgutil, importlib, fftune.analysis as a\n"
            "for m in pkgutil.iter_modules(a.__path__): importlib.import_module('fftune.analysis.' + m.name)\n"
            "bad = [m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed', 'pyarrow')]\n"
            "print(bad); sys.exit(1 if bad else 0)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_a_logs_steps_are_told_apart_by_the_configuration():
    from types import SimpleNamespace

    from fftune.host.odmap import EXC_KINDS
    cfg = _cfg()   # quantify: N 1024, 2.5 and 5 Hz; tune: N 1024 at 2.5 Hz; fs 2560 Hz

    def rec(kind, n=1024, cycles=0):
        return (None, SimpleNamespace(fs_hz=2560.0, parameters={
            "exc_kind": EXC_KINDS[kind], "exc_period": n, "exc_sine_cycles": cycles, "fs": 2560.0}))
    steps = fleet._logged_steps
    only_q = SimpleNamespace(runs=[rec("sine", 1024, 2)])          # 5 Hz: quantify's, not tune's
    assert steps(only_q, cfg) == {"detect": False, "quantify": True, "tune": False}
    only_t = SimpleNamespace(runs=[rec("sine", 1024, 1)] * 3)      # 2.5 Hz: both grids have it
    assert steps(only_t, cfg) == {"detect": False, "quantify": True, "tune": True}
    other_n = SimpleNamespace(runs=[rec("multisine", 512), rec("sine", 2048, 2)])
    assert steps(other_n, cfg) == {"detect": True, "quantify": False, "tune": False}
