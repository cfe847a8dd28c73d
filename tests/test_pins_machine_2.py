"""A machine's stop, status and bus pacing on drive_sim (host/machine.py; issue 33's
hand-written bug audit, docs/testing.md): an axis thread stuck past the machine's join
after Ctrl-C is still stopped and disabled by the machine itself (the last axis too), an
axis whose search does not converge is 'unconverged' with exit status 1, and the bus'
SDO pacer shares the heartbeat's period among the machine's axes (the drive_sim of
tests/test_machine.py: two nodes, 5 and 7; seconds each); the machine file's host id
checked against the axes' node ids (not its heartbeat period).
"""
import _thread
import os
import signal
import struct
import threading
import time

import pytest
import yaml

from fftune.host import drive as _drive
from fftune.host.cli import main
from fftune.host.drive import BusOptions, DriveClient
from host_fixtures import EDS, drive_sim_missing_reason
from test_machine import SMALL, _machine_file, machine_sim  # noqa: F401  (the module's drive_sim)

needs_drive_sim = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                     reason=drive_sim_missing_reason() or "")


def _enabled(sim, nid):
    with DriveClient(BusOptions(port=sim.port, node_id=nid, eds=EDS), heartbeat_ms=0) as c:
        status = struct.unpack("<H", c.node.sdo.upload(0x6041, 0))[0]
        return status & 0x6F == 0x27, int(c.get("run_state"))


@needs_drive_sim
def test_ctrl_c_with_the_last_axis_stuck_the_machine_disables_it(machine_sim, tmp_path, monkeypatch):
    """Ctrl-C while the last axis' thread is stuck (it sees no cancel for longer than the
    machine's 10 s join): the machine stops and disables that drive itself before it
    returns (exit 130), not the axis' thread later. A 16 s consumer: within the test only
    fftune's cleanup can disable the drive."""
    sim, d = machine_sim
    no_hb = dict(SMALL, drive={"heartbeat_ms": 4000, "fs_hz": 2560.0})
    (d / "small_stuck.yaml").write_text(yaml.safe_dump(no_hb))
    f = _machine_file(d, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}], "m_stuck.yaml",
                      config="small_stuck.yaml")
    original = DriveClient.run
    a_running, release, fired = threading.Event(), threading.Event(), []

    def run(self, *args, **kw):
        if self.opts.node_id == 7:
            assert a_running.wait(30), "axis a never started a run"
            if not fired:
                fired.append(True)
                _thread.interrupt_main()            # Ctrl-C, both drives enabled
                release.wait(40)                    # stuck: no SDO request, no cancel seen
        else:
            a_running.set()
        return original(self, *args, **kw)
    monkeypatch.setattr(_drive.DriveClient, "run", run)
    sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code = main(["tune", "--machine", f, "--port", str(sim.port), "--out", str(tmp_path / "o"),
                     "--no-progress", "--no-figures"])
        # main() has returned, axis b's thread still waits in its run: only the machine's own
        # cleanup can have left node 7 disabled by now
        assert any(t.name == "fftune-axis-b" and t.is_alive() for t in threading.enumerate())
        state = {nid: _enabled(sim, nid) for nid in (5, 7)}
    finally:
        signal.signal(signal.SIGINT, sigint)
        release.set()
        deadline = time.monotonic() + 30
        while any(t.name.startswith("fftune-axis-") and t.is_alive() for t in threading.enumerate()) \
                and time.monotonic() < deadline:
            time.sleep(0.05)
    assert fired and code == 130
    for nid, (enabled, run_state) in state.items():
        assert not enabled, f"node {nid} still OPERATION ENABLED after the machine returned"
        assert run_state not in (1, 2), (nid, run_state)


@needs_drive_sim
def test_an_unconverged_axis_is_reported_and_exits_1(machine_sim, tmp_path, capsys):
    """Axis a's search may take 3 experiments (too few to converge), axis b the small
    configuration's 8: a is 'unconverged' (its stop reason the error), b 'ok', exit 1."""
    sim, d = machine_sim
    f = _machine_file(d, [{"name": "a", "node_id": 5,
                           "overrides": {"tune": {"search": {"max_experiments": 3}}}},
                          {"name": "b", "node_id": 7}], "m_unconv.yaml")
    out = tmp_path / "o"
    code = main(["tune", "--machine", f, "--port", str(sim.port), "--out", str(out), "--no-progress",
                 "--no-figures"])
    text = capsys.readouterr()
    summary = yaml.safe_load((out / "results.yaml").read_text())
    by = {a["name"]: a for a in summary["axes"]}
    own = yaml.safe_load((out / "a" / "results.yaml").read_text())["tune"]["search"]
    assert own["converged"] is False and own["stop_reason"]
    assert (by["a"]["status"], by["a"]["converged"], by["a"]["error"]) == \
        ("unconverged", False, f"not converged: {own['stop_reason']}")
    assert (by["b"]["status"], by["b"]["converged"], by["b"]["error"]) == ("ok", True, None)
    assert code == 1, text.out + text.err
    line = [ln for ln in text.out.splitlines() if ln.startswith("  a ")]
    assert len(line) == 1 and " unconverged " in line[0], text.out


@needs_drive_sim
def test_the_sdo_pacer_shares_the_heartbeat_period_among_the_axes(machine_sim, tmp_path, monkeypatch):
    """At 20 kbit/s with a 100 ms heartbeat and three axes, the bus' pacer lets
    floor(1.5 x 100 ms / (3 x one 8-byte frame)) SDO frames go back to back; the frame
    (CAN 2.0A, 8 data bytes, worst-case stuffing, interframe space) is 135 bit times. The
    axes' nodes are absent (each fails at its probe): the pacer is made before them."""
    from fftune.host import machine as mc

    sim, d = machine_sim
    bursts = []
    pacer_init = _drive._SdoPacer.__init__

    def spy(self, network, bitrate, burst):
        bursts.append((bitrate, burst))
        pacer_init(self, network, bitrate, burst)
    monkeypatch.setattr(_drive._SdoPacer, "__init__", spy)
    fast = {"drive": {"sdo_timeout_s": 0.3, "sdo_retries": 1}}
    f = _machine_file(d, [{"name": n, "node_id": nid, "overrides": fast}
                          for n, nid in (("p", 21), ("q", 22), ("r", 23))], "m_pace.yaml")
    machine = mc.load_machine(f)
    opts = BusOptions(interface="socketcand", channel="can0", host=sim.host, port=sim.port, node_id=21,
                      eds=EDS, model_bitrate=20000)
    summary = mc.run_machine(machine, opts, str(tmp_path / "o"), figures=False, log=lambda s: None,
                             log_error=lambda s: None)
    assert [a["status"] for a in summary["axes"]] == ["failed"] * 3
    # SOF, id, RTR, IDE, r0, DLC, data, CRC, delimiters, ACK, EOF, IFS; 24 stuff bits at most
    frame_s = (1 + 11 + 1 + 1 + 1 + 4 + 64 + 15 + 1 + 1 + 1 + 7 + 3 + 24) / 20000.0  # 135 bits
    want = int(1.5 * 0.100 / (3 * frame_s))          # 150 ms / 20.25 ms: 7 (one axis alone: 22)
    assert want == 7
    assert bursts == [(20000, want)]


def test_the_host_id_of_the_bus_heartbeat_is_no_axis_node_id(tmp_path):
    """host_node_id 5 is axis a's node id: refused, naming the axis and the key. A
    heartbeat period of 7 ms beside an axis of node 7 is no clash (a period is no id)."""
    from fftune.analysis.errors import FftuneError
    from fftune.host import machine as mc

    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    f = _machine_file(tmp_path, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}], "m_id.yaml")
    raw = yaml.safe_load(open(f))
    raw["overrides"] = {"drive": {"host_node_id": 5}}
    (tmp_path / "m_id.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(FftuneError) as exc:
        mc.load_machine(f)
    assert str(exc.value) == (f"{f}: axes[0] (configuration with overrides): key 'drive.host_node_id': "
                              f"must differ from drive.node_id")
    raw["overrides"] = {"drive": {"host_node_id": 126, "heartbeat_ms": 7}}
    (tmp_path / "m_id.yaml").write_text(yaml.safe_dump(raw))
    m = mc.load_machine(f)
    assert [(a["name"], a["cfg"]["drive"]["host_node_id"], a["cfg"]["drive"]["heartbeat_ms"]) for a in m["axes"]] \
        == [("a", 126, 7), ("b", 126, 7)]
    assert os.path.basename(m["file"]) == "m_id.yaml"


def test_bus_busy_time_at_the_rate_the_bus_model_ran(tmp_path):
    """drive_sim's exit line is the measurement: its bits at its own bit rate (here 250 kbit/s,
    beside the 500 kbit/s asked for), not at the rate requested."""
    from fftune.host import machine as mc

    log = tmp_path / "drive_sim.log"
    log.write_text("drive_sim: listening\nCAN bus model: 2468 frames, 333333 bits at 250000 bit/s\n")
    m = mc._bus_model_figures(str(log), 500000)
    assert (m["frames"], m["bits"], m["bitrate"], m["busy_s"]) == (2468, 333333, 250000, 1.333)


def test_run_machine_refuses_an_axis_whose_node_id_is_the_bus_heartbeats(tmp_path):
    """A machine dict built elsewhere (not through load_machine, which refuses it): every
    axis with host id 7, axis b on node 7. Refused before the bus is opened (port 1: nothing
    listens there, and nothing is tried)."""
    from fftune.analysis.errors import FftuneError
    from fftune.host import machine as mc

    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    f = _machine_file(tmp_path, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 8}], "m_built.yaml")
    m = mc.load_machine(f)
    for ax in m["axes"]:
        ax["cfg"]["drive"]["host_node_id"] = 7
    m["axes"][1]["node_id"] = 7
    with pytest.raises(FftuneError) as exc:
        mc.run_machine(m, BusOptions(port=1, node_id=5, eds=EDS), str(tmp_path / "o"), figures=False,
                       log=lambda s: None, log_error=lambda s: None)
    assert str(exc.value) == ("axis 'b': drive.host_node_id / drive.heartbeat_ms (7, 100 ms) differ from the "
                              "bus' (7, 100 ms) or name the axis itself")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("bitrate, ok", [(1000000, True), (1e6, True), (10000, True), (1000001, False),
                                         (9999, False)])
def test_machine_sim_bitrate_bounds_inclusive(tmp_path, bitrate, ok):
    """sim.bitrate 10 kbit/s .. 1 Mbit/s, both ends included (1e6 written as a float too)."""
    from fftune.analysis.errors import FftuneError
    from fftune.host import machine as mc

    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    path = tmp_path / "m_rate.yaml"
    path.write_text(yaml.safe_dump({"machine": "t", "config": "small.yaml", "sim": {"bitrate": bitrate},
                                    "axes": [{"name": "a", "node_id": 5}]}))
    if ok:
        assert mc.load_machine(str(path))["bitrate"] == int(bitrate)
    else:
        with pytest.raises(FftuneError) as exc:
            mc.load_machine(str(path))
        assert str(exc.value) == (f"{path}: key 'sim.bitrate': expected 10000 .. 1000000 bit/s, got {bitrate}")


@pytest.mark.parametrize("n, ok", [(8, True), (9, False), (1, True)])
def test_machine_of_up_to_eight_axes(tmp_path, n, ok):
    from fftune.analysis.errors import FftuneError
    from fftune.host import machine as mc

    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    f = _machine_file(tmp_path, [{"name": f"ax{i}", "node_id": 10 + 3 * i} for i in range(n)], "m_n.yaml")
    if ok:
        assert [a["node_id"] for a in mc.load_machine(f)["axes"]] == [10 + 3 * i for i in range(n)]
    else:
        with pytest.raises(FftuneError) as exc:
            mc.load_machine(f)
        assert str(exc.value) == f"{f}: key 'axes': {n} axes, at most 8 on one simulated bus"


def _raw_machine(tmp_path, **top):
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    raw = dict({"machine": "t", "config": "small.yaml", "axes": [{"name": "a", "node_id": 5}]}, **top)
    path = tmp_path / "m_keys.yaml"
    path.write_text(yaml.safe_dump(raw))
    return str(path)


def _error(path):
    from fftune.analysis.errors import FftuneError
    from fftune.host import machine as mc

    with pytest.raises(FftuneError) as exc:
        mc.load_machine(path)
    return str(exc.value)


def test_machine_file_key_errors_name_the_first_key_cut_to_60_and_its_nearest_key(tmp_path):
    """(the lead's surviving mutants: the cut lengths, which unknown key the hint is for)"""
    long_key = "z" * 59 + "QRSTU"                                    # 64 characters
    f = _raw_machine(tmp_path, **{long_key: 1})
    assert _error(f).startswith(f"{f}: key '{'z' * 59}Q': unknown key (expected one of: axes, config, ")
    f = _raw_machine(tmp_path, axez=1, ouptut=2)                       # sorted: axez first
    assert _error(f).startswith(f"{f}: key 'axez': unknown key (did you mean 'axes'? expected one of: ")
    f = _raw_machine(tmp_path, axes=[{"name": "a", "node_id": 5, "nmae": 1, "plnat": 2}])
    assert _error(f).startswith(f"{f}: axes[0]: key 'nmae': unknown key (did you mean 'name'? expected one of: ")


def test_plant_override_errors_cut_section_and_key_to_40(tmp_path):
    section, key = "s" * 39 + "TUV", "k" * 39 + "XYZ"                   # 42 characters each
    f = _raw_machine(tmp_path, axes=[{"name": "a", "node_id": 5, "plant_overrides": {section: {key: "x"}}}])
    assert _error(f) == (f"{f}: axes[0].plant_overrides.{'s' * 39}T.{'k' * 39}X: expected a finite number, "
                         f"got 'x'")
    f = _raw_machine(tmp_path, axes=[{"name": "a", "node_id": 5, "plant_overrides": {"plant": None}}])
    assert _error(f).startswith(f"{f}: axes[0].plant_overrides.plant: expected {{key: number}}, got ")


def test_a_failing_figure_job_is_one_error_line_and_the_wait_ends(tmp_path):
    """The figure process' job of an axis fails (its tune data is not what the figures
    need): wait() returns that axis' error, says it once, and ends (the lead's surviving
    mutant: a `continue` instead of the `break` after the error waits forever)."""
    from fftune.host import machine as mc

    errors_logged = []
    pool = mc._FigurePool(lambda s: None, errors_logged.append)
    done = {}
    try:
        pool.submit("ax1", 12, str(tmp_path), "tune", {"not": "tune data"}, {"tune": {}})
        th = threading.Thread(target=lambda: done.update(result=pool.wait()), daemon=True)
        th.start()
        th.join(60)
        assert not th.is_alive(), "wait() did not return after the job failed"
    finally:
        if "result" not in done:
            pool.terminate()
    figs, errors = done["result"]
    assert figs == {"ax1": {}} and list(errors) == ["ax1"] and errors["ax1"].startswith("figures of tune: ")
    assert errors_logged == [f"fftune: error: axis 'ax1' (node 12): {errors['ax1']}"]


@needs_drive_sim
def test_demo_machine_draws_figures_counts_the_bus_and_keeps_the_earlier_output(tmp_path, capsys):
    """`fftune demo --machine` with a 500 kbit/s bus model: each axis' tune figure drawn, the
    bus' busy time from drive_sim's exit line (its bits at its bit rate) in the summary, an
    earlier output folder kept as <out>.previous (the lead's surviving mutants: figures,
    `if bitrate`, set_aside)."""
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    path = tmp_path / "m_demo.yaml"
    path.write_text(yaml.safe_dump({"machine": "d", "config": "small.yaml", "sim": {"bitrate": 500000},
                                    "axes": [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}]}))
    out = tmp_path / "o"
    out.mkdir()
    (out / "earlier.txt").write_text("an earlier session")
    code = main(["demo", "--machine", str(path), "--out", str(out)])
    text = capsys.readouterr()
    assert code == 0, text.out + text.err
    assert (tmp_path / "o.previous" / "earlier.txt").read_text() == "an earlier session"
    assert not (out / "earlier.txt").exists()
    summary = yaml.safe_load((out / "results.yaml").read_text())
    bm = summary["bus_model"]
    assert bm["bitrate"] == 500000 and bm["frames"] > 100 and bm["busy_s"] == round(bm["bits"] / 500000, 3)
    assert summary["time_budget_s"]["total"]["bus"] == bm["busy_s"]
    for name in ("a", "b"):
        assert (out / name / "figure7_tuning.png").stat().st_size > 1000


def test_terminate_removes_half_written_figures_of_every_folder_even_after_a_missing_one(tmp_path):
    """Ctrl-C: terminate() removes the figure process' half-written ``.tmp-*`` files in every
    axis folder it drew into; a folder that has gone (removed by the user) does not end the
    clean-up of the folders after it (the lead's surviving mutant: `break` for `continue`)."""
    from fftune.host import machine as mc

    pool = mc._FigurePool(lambda s: None, lambda s: None)
    gone, kept = tmp_path / "gone", tmp_path / "kept"
    kept.mkdir()
    (kept / ".tmp-tune_hosidf.png").write_bytes(b"half")
    (kept / "detect_bla.png").write_bytes(b"whole")
    pool._dirs.extend([str(gone), str(kept)])
    pool.terminate()
    assert sorted(p.name for p in kept.iterdir()) == ["detect_bla.png"]


@pytest.mark.parametrize("name, ok", [("", False), ("a" * 64, True), ("a" * 65, False), ("b-2_x", True)])
def test_axis_names_are_1_to_64_letters_digits_dashes_underscores(tmp_path, name, ok):
    # an axis name is a folder name: empty and longer than 64 refused, one line naming it
    from fftune.analysis.errors import FftuneError
    from fftune.host import machine as mc

    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    f = _machine_file(tmp_path, [{"name": "a0", "node_id": 5}, {"name": name, "node_id": 7}], "m_n.yaml")
    if ok:
        assert [a["name"] for a in mc.load_machine(f)["axes"]] == ["a0", name]
    else:
        with pytest.raises(FftuneError, match=r"axes\[1\]\.name: expected a name of letters, digits, - and _"):
            mc.load_machine(f)


def test_a_broken_figure_process_is_the_axis_error_and_the_wait_ends(tmp_path):
    """The figure process cannot take a job (it has gone): that axis' figures are its error,
    said once, and wait() returns; the other work is not stopped by an exception."""
    from fftune.host import machine as mc

    errors_logged = []
    pool = mc._FigurePool(lambda s: None, errors_logged.append)
    pool._ex.shutdown(wait=True)                          # (as a dead process pool refuses jobs)
    pool.submit("ax2", 9, str(tmp_path), "tune", {"some": "tune data"}, {"tune": {}})
    figs, errors = pool.wait()
    assert list(errors) == ["ax2"] and errors["ax2"].startswith("figures of tune: RuntimeError")
    assert errors_logged == [f"fftune: error: axis 'ax2' (node 9): {errors['ax2']}"]


def test_run_machine_draws_figures_unless_told_not_to():
    import inspect

    from fftune.host import machine as mc
    assert inspect.signature(mc.run_machine).parameters["figures"].default is True


def test_an_axis_config_file_is_read_and_its_errors_are_named_with_the_axis(tmp_path):
    # an axis with a configuration of its own: its values are used (not the machine's), and
    # a broken file is one line naming the axis' key and the file
    from fftune.analysis.errors import FftuneError
    from fftune.host import machine as mc

    own = dict(SMALL)
    own["tune"] = {**SMALL.get("tune", {}), "frequency_hz": 2.5}
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    (tmp_path / "own.yaml").write_text(yaml.safe_dump(own))
    f = _machine_file(tmp_path, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7, "config": "own.yaml"}],
                      "m_c.yaml")
    m = mc.load_machine(f)
    assert [a["cfg"]["tune"]["frequency_hz"] for a in m["axes"]] == \
        [mc.load_machine(f)["axes"][0]["cfg"]["tune"]["frequency_hz"], 2.5]
    assert m["axes"][0]["cfg"]["tune"]["frequency_hz"] != 2.5
    (tmp_path / "own.yaml").write_text("tune: [1, 2\n")
    with pytest.raises(FftuneError, match=r"axes\[1\]\.config: .*own\.yaml"):
        mc.load_machine(f)


def test_an_axis_plant_file_that_is_not_a_plant_is_named_with_the_axis(tmp_path):
    from fftune.analysis.errors import FftuneError
    from fftune.host import machine as mc

    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    (tmp_path / "bad_plant.yaml").write_text("plant: [1, 2]\n")
    f = _machine_file(tmp_path, [{"name": "a", "node_id": 5, "plant": "bad_plant.yaml"}], "m_p.yaml")
    with pytest.raises(FftuneError, match=r"axes\[0\]\.plant: .*bad_plant\.yaml"):
        mc.load_machine(f)


def test_run_machine_shows_no_progress_bars_unless_asked():
    import inspect

    from fftune.host import machine as mc
    assert inspect.signature(mc.run_machine).parameters["progress"].default is False


@pytest.mark.parametrize("nid, shown", [(True, "True"), (False, "False"), (3.5, "3.5"), ("3", "'3'"), (0, "0")])
def test_an_axis_node_id_is_an_integer_not_a_yaml_boolean(tmp_path, nid, shown):
    """`node_id: true` is YAML's boolean (Python's 1): no node id, refused like 3.5 or 0."""
    f = _raw_machine(tmp_path, axes=[{"name": "a", "node_id": nid}])
    assert _error(f) == f"{f}: axes[0].node_id: expected 1 .. 127, got {shown}"


def test_a_plant_override_section_that_is_no_mapping_is_named_cut_to_40(tmp_path):
    section = "s" * 39 + "TUV"                                          # 42 characters
    f = _raw_machine(tmp_path, axes=[{"name": "a", "node_id": 5, "plant_overrides": {section: 7}}])
    assert _error(f).startswith(f"{f}: axes[0].plant_overrides.{'s' * 39}T: expected {{key: number}}, got ")


def test_a_step_figures_time_is_the_drawing_time(tmp_path, monkeypatch):
    """The figure process' log line `figures of STEP: N drawn in X s`: X is the drawing time."""
    from fftune.host import machine as mc
    from fftune.host import report

    def slow_figures(out_dir, **data):
        time.sleep(0.12)
        return {"a": ("a.png", "A"), "b": ("b.png", "B")}
    monkeypatch.setattr(report, "make_figures", slow_figures)
    t0 = time.monotonic()
    figs, seconds = mc._draw_step_figures(str(tmp_path), "detect", object(), {})
    assert sorted(figs) == ["a", "b"] and 0.12 <= seconds <= time.monotonic() - t0
