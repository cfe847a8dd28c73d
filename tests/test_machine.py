"""A machine: several axes on one bus, tuned concurrently (host/machine.py, drive_sim --axis).

One drive_sim serves two nodes with unequal plants (Coulomb 0.1157 V and 0.16 V, different
motor inertias) behind a 1 Mbit/s bus model; the machine file names a third axis whose node
is not on the bus. The tune step (a small configuration: one sine at 0.625 Hz, N 4096, on
the drive's statistics) runs on the axes at once.
"""
import _thread
import os
import signal
import struct
import time

import pytest
import yaml

from fftune.host import drive as _drive
from fftune.host.cli import main
from fftune.host.drive import BusOptions, DriveClient
from fftune.host.sim import derived_plant, start_drive_sim
from host_fixtures import EDS, REPO, drive_sim_missing_reason

pytestmark = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                reason=drive_sim_missing_reason() or "")

TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")
SMALL = {
    "output": "out/unused",
    "drive": {"heartbeat_ms": 100, "fs_hz": 2560.0},
    # (the encoder step: the search's uncertainty on statistics needs it, 500 lines x 4)
    "detect": {"enabled": False, "encoder_step_rad": 0.0031415926535897933}, "quantify": {"enabled": False},
    "tune": {"frequency_hz": 0.625, "amplitude_rad": 0.5, "period_samples": 4096, "periods": 2,
             "settle_periods": 2, "harmonics": 7, "capture": "stats",
             "sweep": {"k_fc_max": 0.3, "points": 0}, "search": {"method": "root", "max_experiments": 8},
             "viscous": {"enabled": False}},
}
PLANTS = {"a": (5, {"plant": {"viscous": 2.0e-3}}, 0.1157),
          "b": (7, {"plant": {"viscous": 2.0e-3, "coulomb": 8.0e-3, "static": 8.0e-3, "j1": 1.5e-4}}, 0.16)}


@pytest.fixture(scope="module")
def machine_sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("machine")
    extra = []
    for name, (nid, over, _) in PLANTS.items():
        plant = derived_plant(TWOMASS, over, str(d / f"plant_{name}.yaml"))
        extra += ["--axis", f"{nid}:{plant}"]
    (d / "small.yaml").write_text(yaml.safe_dump(SMALL))
    sim = start_drive_sim(TWOMASS, log_path=str(d / "drive_sim.log"), bitrate=1_000_000, extra=extra)
    yield sim, d
    sim.stop()


def _machine_file(d, axes, name="m.yaml", config="small.yaml"):
    path = d / name
    path.write_text(yaml.safe_dump({"machine": "t", "config": config, "axes": axes}))
    return str(path)


def test_axes_tuned_concurrently_and_an_absent_node_is_one_line(machine_sim, tmp_path, capsys):
    sim, d = machine_sim
    # (the absent node's probe: a short SDO timeout, the test waits less for it)
    f = _machine_file(d, [{"name": "a", "node_id": 5},
                          {"name": "ghost", "node_id": 9,
                           "overrides": {"drive": {"sdo_timeout_s": 0.3, "sdo_retries": 1}}},
                          {"name": "b", "node_id": 7}])
    out = tmp_path / "out"
    code = main(["tune", "--machine", f, "--port", str(sim.port), "--out", str(out),
                 "--no-progress"])
    text = capsys.readouterr()
    assert code == 2, text.out + text.err           # an axis failed: reported, the others ran
    # each axis' tune figure drawn by the figure process and linked from the axis' report
    for name in ("a", "b"):
        drawn = [ln for ln in text.out.splitlines() if ln.startswith(f"[{name}] figures of tune: ")]
        assert len(drawn) == 1 and drawn[0].endswith("(figure process)"), text.out
        assert (out / name / "figure7_tuning.png").stat().st_size > 1000
        assert "<img src='figure7_tuning.png'" in (out / name / "report.html").read_text()
        assert not [p.name for p in (out / name).iterdir() if p.name.startswith(".tmp-")]
    assert not (out / "ghost").exists()
    ghost = [ln for ln in text.err.splitlines() if ln.startswith("fftune: error: axis 'ghost'")]
    assert len(ghost) == 1 and "(node 9): no SDO answer from node 9" in ghost[0]
    assert "nodes answering on this bus: 5, 7" in ghost[0]
    summary = yaml.safe_load((out / "results.yaml").read_text())
    by = {a["name"]: a for a in summary["axes"]}
    assert [a["name"] for a in summary["axes"]] == ["a", "ghost", "b"]
    assert by["ghost"]["status"] == "failed" and by["ghost"]["k_fc_star"] is None
    for name in ("a", "b"):
        nid, _, truth = PLANTS[name]
        a = by[name]
        assert (a["status"], a["node_id"]) == ("ok", nid)
        assert a["k_fc_true"] == pytest.approx(truth, rel=1e-3)       # each node's own plant
        assert abs(a["k_fc_star"] / truth - 1) < 0.02, a
        assert a["sigma"] > 0
        own = yaml.safe_load((out / name / "results.yaml").read_text())
        assert own["axis"] == {"machine": "t", "name": name, "node_id": nid}
        assert own["tune"]["k_fc_star"] == a["k_fc_star"]
    total = summary["time_budget_s"]["total"]
    assert total["excitation"] == max(by[n]["time_budget_s"]["excitation"] for n in ("a", "b"))
    assert 0 < total["measure_wall"] <= total["wall"]
    assert total["excitation_sum"] > total["excitation"]
    # the axes ran concurrently: their sessions of runs overlap in time (each axis' runs
    # start before the other axis' last run ends; sequential axes would not). Single runs
    # of a free-running drive last milliseconds and need not overlap one by one on a
    # loaded machine, so the test takes the spans of the axes' whole sequences of runs.
    spans = {}
    for name in ("a", "b"):
        spans[name] = []
        for p in sorted((out / name / "captures").glob("*.stats.json")):
            meta = yaml.safe_load(p.read_text())["meta"]
            spans[name].append((meta["started_at"], meta["finished_at"]))
    assert spans["a"] and spans["b"]
    first = {n: min(s for s, _ in spans[n]) for n in spans}
    last = {n: max(e for _, e in spans[n]) for n in spans}
    assert first["a"] < last["b"] and first["b"] < last["a"], (first, last)
    assert "<td>ghost</td><td>9</td><td>failed</td>" in (out / "report.html").read_text()
    assert "&id" not in (out / "results.yaml").read_text()      # plain YAML, no aliases
    # the axes' statistics captures re-analysed by the fleet: the same K_fc*, named by axis
    from fftune.host import fleet
    rows = fleet.run_graph(fleet.discover([str(out)])[0], scheduler="sync")
    assert [(r["machine"], r["axis"], r["node_id"], r["status"]) for r in rows] == \
        [("t", "a", 5, "ok"), ("t", "b", 7, "ok")]
    assert [r["k_fc_star"] for r in rows] == [by["a"]["k_fc_star"], by["b"]["k_fc_star"]]


def test_duplicate_node_ids_are_one_line_and_nothing_written(tmp_path, capsys):
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    f = _machine_file(tmp_path, [{"name": "x", "node_id": 3}, {"name": "y", "node_id": 4},
                                 {"name": "z", "node_id": 3}])
    out = tmp_path / "out"
    assert main(["run", "--machine", f, "--out", str(out), "--port", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"fftune: error: {f}: axes[2].node_id: 3 is also the node id of axis 'x' "
                   f"(node ids must be unique on one bus)"]
    assert not out.exists()


def _ctrl_c_session(monkeypatch, sim, f, out, second_run):
    """``fftune tune --machine f`` with a Ctrl-C when the second axis starts its run: that
    run is ``second_run(self, original, *a, **kw)``, called once the main thread has set the
    machine's cancel. Returns (exit status, node ids of the runs called, of the runs
    called after the cancel that ran (did not end at once in Cancelled), figure process
    pids, the spy's SDO requests after the cancel {node: [data]})."""
    import threading

    import can

    original = DriveClient.run
    started, started_after, fired, cancelled = [], [], [], threading.Event()
    after = {5: [], 7: []}

    class SdoRequests(can.Listener):
        def on_message_received(self, msg):
            nid = msg.arbitration_id - 0x600
            if nid in after and cancelled.is_set():
                after[nid].append(bytes(msg.data))

    def run(self, *a, **kw):
        late = cancelled.is_set()
        started.append(self.opts.node_id)
        if len(set(started)) == 2 and not fired:    # both axes are measuring: Ctrl-C
            fired.append(True)
            _thread.interrupt_main()
            assert cancelled.wait(30), "the main thread did not cancel within 30 s"
            return second_run(self, original, *a, **kw)
        result = original(self, *a, **kw)   # (Cancelled at its first SDO request after the cancel)
        if late:
            started_after.append(self.opts.node_id)     # a whole run after the cancel
        return result
    monkeypatch.setattr(_drive.DriveClient, "run", run)
    from fftune.host import machine as _machine
    pools, terminate = [], _machine._FigurePool.terminate

    def record(self):                       # the figure process' pid, before it is ended
        if not pools:                       # (the first call: right after the cancel was set)
            pools.append([p.pid for p in (self._ex._processes or {}).values()])
            cancelled.set()
        terminate(self)
    monkeypatch.setattr(_machine._FigurePool, "terminate", record)
    spy = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    notifier = can.Notifier(spy, [SdoRequests()])
    # _thread.interrupt_main() does nothing while SIGINT is ignored, as it is in a test run
    # started as a background job of a non-interactive shell: Python's own handler here
    sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code = main(["tune", "--machine", f, "--port", str(sim.port), "--out", out, "--no-progress"])
        # the axis threads outlive main() by at most their join: wait for them, so that a
        # thread that never saw the cancel is counted (its runs, its SDO traffic)
        deadline = time.monotonic() + 60
        while any(t.name.startswith("fftune-axis-") and t.is_alive() for t in threading.enumerate()):
            assert time.monotonic() < deadline, "axis threads still running 60 s after Ctrl-C"
            time.sleep(0.05)
        time.sleep(0.3)                     # (the spy's last frames)
    finally:
        signal.signal(signal.SIGINT, sigint)
        notifier.stop()
        spy.shutdown()
        monkeypatch.setattr(_drive.DriveClient, "run", original)
    return code, started, started_after, pools, after


def _sdo_download(data, index, sub):
    """The value bytes of an expedited SDO download request to index:sub, else None."""
    if len(data) == 8 and data[0] & 0xE2 == 0x22 and data[1:4] == struct.pack("<HB", index, sub):
        return data[4:8 - ((data[0] >> 2) & 3)]
    return None


def _sdo_initiate(data):
    """An SDO client request that begins a transfer (CiA 301: initiate download 1, initiate
    upload 2, block upload initiate 5/0, block download initiate 6/0)."""
    ccs = data[0] >> 5
    return ccs in (1, 2) or (ccs == 5 and data[0] & 0x03 == 0) or (ccs == 6 and data[0] & 0x01 == 0)


def test_ctrl_c_stops_and_disables_every_axis(machine_sim, tmp_path, monkeypatch, capsys):
    """Ctrl-C with both axes measuring: exit 130; after the cancel no run starts and each
    node gets its stop command and its disable (0x6040 = 6) and little else (an axis that
    never saw the cancel would go on: more runs, tens of SDO requests); the figure process
    ended; every drive left stopped and disabled (a 16 s consumer: only fftune's cleanup can within the test)."""
    from fftune.host.odmap import PARAMS

    sim, d = machine_sim
    no_hb = dict(SMALL, drive={"heartbeat_ms": 4000, "fs_hz": 2560.0})  # (consumer 16 s: never enabled without a heartbeat, issue 30)
    (d / "small_no_hb.yaml").write_text(yaml.safe_dump(no_hb))
    f = _machine_file(d, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}], "m2.yaml",
                      config="small_no_hb.yaml")
    code, started, started_after, pools, after = _ctrl_c_session(
        monkeypatch, sim, f, str(tmp_path / "o"),
        lambda self, original, *a, **kw: original(self, *a, **kw))
    assert code == 130
    assert sorted(set(started)) == [5, 7] and started_after == []     # no run ran after the cancel
    cmd = PARAMS["run_command"]
    for nid, frames in after.items():
        sent = [(_sdo_download(x, cmd.index, cmd.subindex), _sdo_download(x, 0x6040, 0)) for x in frames]
        assert (b"\x02", None) in sent, (nid, frames)                 # run command: stop
        assert (None, b"\x06\x00") in sent, (nid, frames)             # controlword: shutdown
        assert (b"\x01", None) not in sent, (nid, frames)              # no start
        # transfers begun after the cancel besides the stop and the disable (the axis' own
        # cleanup and the machine's may both send those: idempotent, counted apart): the one
        # in flight at the cancel (its segments are not counted); no more
        others = [x for x, s in zip(frames, sent) if _sdo_initiate(x) and s not in ((b"\x02", None),
                                                                                   (None, b"\x06\x00"))]
        assert len(others) <= 1, (nid, frames)
        assert sent.count((b"\x02", None)) <= 2 and sent.count((None, b"\x06\x00")) <= 2, (nid, frames)
    assert not [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("fftune: error: axis")]
    # the figure process (started at once, drawing nothing yet) was ended with the axes
    assert len(pools[0]) == 1, pools
    with pytest.raises(ProcessLookupError):
        os.kill(pools[0][0], 0)
    for nid in (5, 7):
        with DriveClient(BusOptions(port=sim.port, node_id=nid, eds=EDS), heartbeat_ms=0) as c:
            assert int(c.get("run_state")) not in (1, 2)            # not settling / recording
            status = struct.unpack("<H", c.node.sdo.upload(0x6041, 0))[0]
            assert status & 0x6F != 0x27, hex(status)               # not OPERATION ENABLED
            assert int(c.get("run_last_error")) in (0, 1)               # none, or our abort command


def test_an_axis_failing_after_the_cancel_is_cancelled_not_an_error_line(machine_sim, tmp_path, monkeypatch,
                                                                       capsys):
    """An axis thread that meets the closing bus after a Ctrl-C (canopen: "Not connected to
    CAN bus") is cancelled, not failed: no `fftune: error: axis` line, which, printed by a
    thread that outlives its session, lands in the next session's output (the lost-bus
    test once saw 3 lines instead of 2)."""
    sim, d = machine_sim
    no_hb = dict(SMALL, drive={"heartbeat_ms": 4000, "fs_hz": 2560.0})  # (consumer 16 s: never enabled without a heartbeat, issue 30)
    (d / "small_no_hb3.yaml").write_text(yaml.safe_dump(no_hb))
    f = _machine_file(d, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}], "m6.yaml",
                      config="small_no_hb3.yaml")

    def late(self, original, *a, **kw):
        raise RuntimeError("Not connected to CAN bus")
    code, started, started_after, _, _ = _ctrl_c_session(monkeypatch, sim, f, str(tmp_path / "o"), late)
    assert code == 130 and sorted(set(started)) == [5, 7] and started_after == []
    err = capsys.readouterr().err
    assert not [ln for ln in err.splitlines() if ln.startswith("fftune: error: axis")], err


def test_lost_bus_fails_every_axis_with_its_reason(tmp_path, monkeypatch, capsys):
    extra = []
    for name, (nid, over, _) in PLANTS.items():
        extra += ["--axis", f"{nid}:{derived_plant(TWOMASS, over, str(tmp_path / f'plant_{name}.yaml'))}"]
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    f = _machine_file(tmp_path, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}])
    sim = start_drive_sim(TWOMASS, log_path=str(tmp_path / "drive_sim.log"), extra=extra)
    original = DriveClient.run
    started = []

    def run(self, *a, **kw):
        started.append(self.opts.node_id)
        if len(started) == 2:               # both axes are measuring: the bus goes away
            sim.proc.kill()
            sim.proc.wait()
        return original(self, *a, **kw)
    monkeypatch.setattr(_drive.DriveClient, "run", run)
    try:
        code = main(["tune", "--machine", f, "--port", str(sim.port), "--out", str(tmp_path / "o"),
                     "--no-progress", "--no-figures"])
    finally:
        sim.stop()
    assert code == 2
    summary = yaml.safe_load((tmp_path / "o" / "results.yaml").read_text())
    assert [(a["name"], a["status"]) for a in summary["axes"]] == [("a", "failed"), ("b", "failed")]
    for a in summary["axes"]:
        assert f"on node {a['node_id']}: connection lost" in a["error"] and a["k_fc_star"] is None
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("fftune: error: axis")]
    assert len(lines) == 2


def test_a_logged_machine_session_and_its_folders_analysed_by_the_fleet(machine_sim, tmp_path):
    """The CAN log of a machine session holds both nodes' runs: `fftune fleet` finds each
    node in it and replays its runs to the live K_fc* (unequal plants: a mix-up of nodes
    fails); the machine's output folders give the same, named by axis."""
    import threading

    import can

    from fftune.host import fleet

    sim, d = machine_sim
    # short raw runs (the log must hold recordings); K_fc* itself does not matter here
    raw = dict(SMALL, tune=dict(SMALL["tune"], capture="raw", period_samples=1024, periods=2,
                                frequency_hz=2.5, settle_periods=2,
                                search={"method": "root", "max_experiments": 3}))
    cfg_path = d / "small_raw.yaml"
    cfg_path.write_text(yaml.safe_dump(raw))
    f = _machine_file(d, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}], "m3.yaml",
                      config="small_raw.yaml")
    log_path = tmp_path / "m" / "session.log"
    log_path.parent.mkdir()
    spy = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    logger = can.Logger(str(log_path))
    marker = threading.Event()

    class Marker(can.Listener):
        def on_message_received(self, msg):
            if msg.arbitration_id == 0x7FE:
                marker.set()
    notifier = can.Notifier(spy, [logger, Marker()])
    try:
        code = main(["tune", "--machine", f, "--port", str(sim.port), "--out", str(tmp_path / "out"),
                     "--no-progress", "--no-figures"])
        with can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port) as tx:
            tx.send(can.Message(arbitration_id=0x7FE, data=[1], is_extended_id=False))
            assert marker.wait(10), "the marker frame never reached the logger"
    finally:
        notifier.stop()
        logger.stop()
        spy.shutdown()
    assert code in (0, 1)
    live = {nid: yaml.safe_load((tmp_path / "out" / n / "results.yaml").read_text())["tune"]
            for n, (nid, _, _) in PLANTS.items()}
    assert live[5]["ratio_at_zero"] != live[7]["ratio_at_zero"]       # unequal plants
    # SDO requests to the two nodes interleave on the bus (not one axis' session after the other)
    ids = [m.arbitration_id for m in can.LogReader(str(log_path)) if m.arbitration_id in (0x605, 0x607)]
    switches = sum(a != b for a, b in zip(ids, ids[1:]))
    assert ids.count(0x605) > 20 and ids.count(0x607) > 20 and switches >= 10, switches
    items, bad = fleet.discover([str(log_path), str(tmp_path / "out")])
    assert bad == []
    rows = fleet.run_graph(items, scheduler="sync", config_path=str(cfg_path))
    logged = {r["node_id"]: r for r in rows if r["kind"] == "canlog"}
    folders = {r["node_id"]: r for r in rows if r["kind"] == "captures"}
    assert sorted(logged) == sorted(folders) == [5, 7]
    for nid in (5, 7):
        assert logged[nid]["status"] == "ok", (logged[nid]["reason"], logged[nid]["status"])
        assert logged[nid]["machine"] == "m" and logged[nid]["axis"] == f"node{nid}"
        assert folders[nid]["axis"] == {5: "a", 7: "b"}[nid] and folders[nid]["machine"] == "t"
        for row in (logged[nid], folders[nid]):
            assert row["k_fc_star"] == live[nid]["k_fc_star"]
            assert row["ratio_at_k_fc_star"] == live[nid]["ratio_at_k_fc_star"]
            assert row["tune_experiments"] == live[nid]["search"]["experiments"]
            assert row["ratio_at_zero"] == live[nid]["ratio_at_zero"]
    assert logged[5]["ratio_at_zero"] != logged[7]["ratio_at_zero"]
    # each node's logged row is dated by its first run: the time of the first start command
    # (run command 1) to that node in the log, before its second one (issue 33's audit)
    import datetime

    from fftune.host.odmap import PARAMS
    cmd = PARAMS["run_command"]
    starts = {5: [], 7: []}
    for m in can.LogReader(str(log_path)):
        data = bytes(m.data)
        if m.arbitration_id in (0x605, 0x607) and len(data) >= 5 and data[0] & 0xE0 == 0x20 \
                and data[1:4] == struct.pack("<HB", cmd.index, cmd.subindex) and data[4] == 1:
            starts[m.arbitration_id - 0x600].append(m.timestamp)
    # a configuration that enables detect, which the log does not hold: only the logged tune
    # is replayed (the row ok, no detect columns), not a detect that finds no runs
    with_detect = dict(raw, detect=dict(raw["detect"], enabled=True))
    (d / "small_raw_detect.yaml").write_text(yaml.safe_dump(with_detect))
    again = fleet.run_graph([it for it in items if it[0] == "canlog"], scheduler="sync",
                            config_path=str(d / "small_raw_detect.yaml"))
    assert [(r["node_id"], r["status"], r["reason"], r["detect_verdict"]) for r in again] == \
        [(5, "ok", "", None), (7, "ok", "", None)]
    assert [r["k_fc_star"] for r in again] == [live[5]["k_fc_star"], live[7]["k_fc_star"]]
    for nid in (5, 7):
        assert len(starts[nid]) >= 2, starts
        t = datetime.datetime.fromisoformat(logged[nid]["date"]).timestamp()
        assert abs(t - starts[nid][0]) < 0.05 and t < starts[nid][1], (nid, t, starts[nid][:2])


@pytest.mark.parametrize("axes, expected", [
    ([{"name": "x", "node_id": 3, "plant": "no_such_plant.yaml"}],
     "axes[0].plant: no_such_plant.yaml: no such plant file"),
    ([{"name": "x", "node_id": 3}, {"name": "x", "node_id": 4}], "axes[1].name: 'x' names axes[0] too"),
    ([{"name": "x", "node_id": 128}], "axes[0].node_id: expected 1 .. 127, got 128"),
    ([{"name": "x", "node_id": 3, "overrides": {"tune": {"periods": 1}}}],
     "axes[0] (configuration with overrides): key 'tune.periods': expected an integer >= 2, got 1"),
    ([{"name": "x", "node_id": 3}, {"name": "y", "node_id": 4,
                                    "overrides": {"limits": {"max_amplitude_rad": 0.1}}}], None),
])
def test_bad_machine_file_for_the_demo_is_one_line(tmp_path, capsys, axes, expected):
    if expected is None:   # (a violation of the axis' limits: the message is plan.preflight's)
        expected = "axis 'y': "
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    f = _machine_file(tmp_path, axes)
    out = tmp_path / "out"
    assert main(["demo", "--machine", f, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    if expected.startswith("axis 'y'"):
        assert len(err) == 1 and err[0].startswith(f"fftune: error: {expected}"), err
        assert "max_amplitude_rad" in err[0] and "0.1" in err[0]
    else:
        assert err == [f"fftune: error: {f}: {expected}"]
    assert not out.exists()


def test_machine_time_budget_from_the_axes():
    from fftune.host.machine import machine_summary
    axes = [{"name": "a", "time_budget_s": {"excitation": 40.0, "bus": 2.0, "drive_wait": 10.0}},
            {"name": "b", "time_budget_s": {"excitation": 30.0, "bus": 3.0, "drive_wait": 35.0}},
            {"name": "c", "time_budget_s": None}]
    s = machine_summary({"name": "m"}, axes, 50.0, "t0")
    t = s["time_budget_s"]["total"]
    assert (t["excitation"], t["excitation_sum"]) == (40.0, 70.0)
    assert (t["bus"], t["bus_sdo_wall"]) == (3.0, 5.0)             # no bus model: the longest SDO time
    assert t["host"] == 50.0 - 3.0 - 30.0                           # b waited 30 s (its excitation) of 35
    assert (t["wall_re_longest_excitation"], t["bus_re_longest_excitation"]) == (1.25, 0.075)
    model = {"busy_s": 1.5, "frames": 10, "bits": 1500000, "bitrate": 1000000}
    t = machine_summary({"name": "m"}, axes, 50.0, "t0", bus_model=model)["time_budget_s"]["total"]
    assert (t["bus"], t["host"]) == (1.5, 50.0 - 1.5 - 30.0)
    assert sorted(machine_summary({"name": "m"}, axes, 50.0, "t0")["time_budget_s"]) == ["axis_a", "axis_b", "total"]
    t = machine_summary({"name": "m"}, axes, 50.0, "t0", measure_wall_s=44.0)["time_budget_s"]["total"]
    assert (t["measure_wall"], t["measure_re_longest_excitation"]) == (44.0, 1.1)


def test_machine_file_overrides_common_then_per_axis(tmp_path):
    from fftune.host.machine import load_machine
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    f = tmp_path / "m.yaml"
    f.write_text(yaml.safe_dump({"config": "small.yaml", "overrides": {"tune": {"periods": 3}},
                                 "axes": [{"name": "p", "node_id": 2},
                                          {"name": "q", "node_id": 9, "overrides": {"tune": {"periods": 5}}}]}))
    m = load_machine(str(f))
    assert m["name"] == "m" and m["output"] == "out/m"
    assert [(a["name"], a["node_id"], a["cfg"]["drive"]["node_id"], a["cfg"]["tune"]["periods"])
            for a in m["axes"]] == [("p", 2, 2, 3), ("q", 9, 9, 5)]
    assert m["axes"][0]["cfg"]["tune"]["frequency_hz"] == SMALL["tune"]["frequency_hz"]


def test_sigterm_stops_and_disables_every_axis(machine_sim, tmp_path):
    """`kill -TERM` of a machine session (another process): exit 143, every drive stopped and
    disabled (a 16 s consumer: only fftune's cleanup can within the test). The signal is sent when a passive
    listener on the bus has seen the start command go to both nodes."""
    import signal
    import subprocess
    import sys
    import threading

    import can

    from fftune.host.odmap import PARAMS

    sim, d = machine_sim
    no_hb = dict(SMALL, drive={"heartbeat_ms": 4000, "fs_hz": 2560.0})  # (consumer 16 s: never enabled without a heartbeat, issue 30)
    (d / "small_no_hb2.yaml").write_text(yaml.safe_dump(no_hb))
    f = _machine_file(d, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}], "m4.yaml",
                      config="small_no_hb2.yaml")
    cmd = PARAMS["run_command"]
    started, both = set(), threading.Event()

    class StartSeen(can.Listener):
        def on_message_received(self, msg):
            data = bytes(msg.data)
            if msg.arbitration_id in (0x605, 0x607) and len(data) >= 5 and data[0] & 0xE0 == 0x20 \
                    and data[1:4] == struct.pack("<HB", cmd.index, cmd.subindex) and data[4] == 1:
                started.add(msg.arbitration_id - 0x600)
                if len(started) == 2:
                    both.set()
    spy = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    notifier = can.Notifier(spy, [StartSeen()])
    fftune = os.path.join(os.path.dirname(sys.executable), "fftune")
    proc = subprocess.Popen([fftune, "tune", "--machine", f, "--port", str(sim.port), "--out",
                             str(tmp_path / "o"), "--no-progress", "--no-figures"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert both.wait(30), f"start commands seen for nodes {sorted(started)}"
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        notifier.stop()
        spy.shutdown()
    assert proc.returncode == 143, out + err
    assert err.strip().splitlines()[-1] == "fftune: terminated"
    for nid in (5, 7):
        with DriveClient(BusOptions(port=sim.port, node_id=nid, eds=EDS), heartbeat_ms=0) as c:
            assert int(c.get("run_state")) not in (1, 2)
            status = struct.unpack("<H", c.node.sdo.upload(0x6041, 0))[0]
            assert status & 0x6F != 0x27, hex(status)


def test_an_axis_refused_by_its_drives_limits_fails_before_it_is_enabled(machine_sim, tmp_path, capsys):
    sim, d = machine_sim
    f = _machine_file(d, [{"name": "a", "node_id": 5,
                           "overrides": {"tune": {"search": {"k_fc_max": 20.0}}}}], "m5.yaml")
    assert main(["tune", "--machine", f, "--port", str(sim.port), "--out", str(tmp_path / "o"),
                 "--no-progress", "--no-figures"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("fftune: error:")]
    assert len(lines) == 1 and lines[0].startswith("fftune: error: axis 'a' (node 5): ")
    assert "k_fc_max" in lines[0] and "20" in lines[0], lines[0]
    summary = yaml.safe_load((tmp_path / "o" / "results.yaml").read_text())
    assert [(a["name"], a["status"]) for a in summary["axes"]] == [("a", "failed")]
    assert not (tmp_path / "o" / "a" / "captures").exists()
    with DriveClient(BusOptions(port=sim.port, node_id=5, eds=EDS), heartbeat_ms=0) as c:
        status = struct.unpack("<H", c.node.sdo.upload(0x6041, 0))[0]
        assert status & 0x6F != 0x27, hex(status)                  # never enabled
