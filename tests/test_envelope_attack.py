"""Issue 30, second pass: the envelope probed as an attacker would, at every entry point.

Each probe is one user input that once hung, crashed with a traceback, was silently
accepted or left folders behind. Every failure must be one ``fftune: error: ...`` line with
exit status 2, nothing moved, the working folder unchanged. The rules live in one place each
(fftune.host.config: regular_file / read_text / ConfigLoader / read_plant / output_session;
fftune.host.cli.Parser; fftune.host.drive.add_bus_arguments; fftune.analysis.io's declared
shapes); the tests reach them through the commands.
"""
import contextlib
import os
import signal
import socket
import zipfile

import numpy as np
import pytest

from fftune.host.cli import main
from host_fixtures import REPO, drive_sim_missing_reason

TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")
needs_drive = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                 reason=str(drive_sim_missing_reason()))


@contextlib.contextmanager
def _deadline(seconds=20):
    """A probe that would block (a FIFO opened for reading) fails the test instead of hanging."""
    def fire(signum, frame):
        raise TimeoutError(f"the command blocked for {seconds} s")
    old = signal.signal(signal.SIGALRM, fire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _tree(path):
    out = set()
    for root, dirs, files in os.walk(path):
        for name in dirs + files:
            out.add(os.path.relpath(os.path.join(root, name), path))
    return out


def _refused(capsys, argv, *needles, cwd=None):
    """``fftune argv`` is one error line containing ``needles``, exit 2, and the folder
    ``cwd`` holds exactly what it held before."""
    before = _tree(cwd) if cwd else None
    with _deadline():
        rc = main(argv)
    err = capsys.readouterr().err.splitlines()
    assert rc == 2, (argv, err)
    assert len(err) == 1 and err[0].startswith("fftune: error: "), (argv, err)
    for needle in needles:
        assert needle in err[0], (argv, needle, err[0])
    if cwd:
        assert _tree(cwd) == before, (argv, _tree(cwd) ^ before)
    return err[0]


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def work(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    os.mkfifo(tmp_path / "fifo.yaml")
    (tmp_path / "adir").mkdir()
    return tmp_path


# ---- files that are not regular files -------------------------------------------------
@pytest.mark.parametrize("argv", [
    ["run", "--config", "fifo.yaml"],
    ["plan", "--offline", "--config", "fifo.yaml"],
    ["demo", "--config", "fifo.yaml"],
    ["sim", "--config", "fifo.yaml"],
    ["track", "--config", "fifo.yaml"],
    ["demo-track", "--config", "fifo.yaml"],
    ["paper", "--config", "fifo.yaml"],
    ["run", "--machine", "fifo.yaml"],
    ["demo", "--machine", "fifo.yaml"],
    ["sim", "--machine", "fifo.yaml"],
    ["demo", "--plant", "fifo.yaml"],
    ["sim", "--plant", "fifo.yaml"],
    ["demo-track", "--plant", "fifo.yaml"],
    ["paper", "--sim-plant", "fifo.yaml"],
    ["import-canlog", "fifo.log"],
    ["run", "--dry-run", "--eds", "fifo.yaml"],
])
def test_a_fifo_is_refused_without_waiting_for_a_writer(work, capsys, argv):
    os.mkfifo(work / "fifo.log")
    _refused(capsys, argv, "is a FIFO (named pipe), expected a file", cwd=work)


@pytest.mark.parametrize("argv, needle", [
    (["run", "--dry-run", "--config", "/dev/zero"], "is a character device"),
    (["run", "--dry-run", "--eds", "/dev/zero"], "is a character device"),
    (["run", "--dry-run", "--eds", "adir"], "adir: cannot read EDS: is a directory"),
    (["demo-track", "--plant", "adir"], "adir: cannot read plant configuration: is a directory"),
    (["import-canlog", "adir.log"], "is a directory"),
])
def test_devices_and_directories_are_refused(work, capsys, argv, needle):
    (work / "adir.log").mkdir()
    _refused(capsys, argv, needle, cwd=work)


def test_machine_files_it_names_go_through_the_one_loader(work, capsys):
    (work / "bomb.yaml").write_text("a: &a [x, x, x, x, x, x, x, x, x, x]\n"
                                    + "".join(f"{c}: &{c} [{', '.join([f'*{p}'] * 10)}]\n"
                                              for p, c in zip("abcdef", "bcdefg")))
    (work / "m.yaml").write_text("machine: m\naxes:\n  - {name: x, node_id: 1, plant: bomb.yaml}\n")
    _refused(capsys, ["run", "--machine", "m.yaml"], "axes[0].plant: bomb.yaml", "alias bomb", cwd=work)
    (work / "m.yaml").write_text("machine: m\naxes:\n  - {name: x, node_id: 1, plant: fifo.yaml}\n")
    _refused(capsys, ["demo", "--machine", "m.yaml"], "axes[0].plant", "FIFO", cwd=work)
    (work / "m.yaml").write_text("machine: m\nconfig: /dev/zero\naxes:\n  - {name: x, node_id: 1}\n")
    _refused(capsys, ["sim", "--machine", "m.yaml"], "key 'config'", "character device", cwd=work)


@pytest.mark.parametrize("plant, needle", [
    ("plant: [1, 2]\n", "key 'plant': expected a section of key: number"),
    ("plant:\n  j1: .nan\n", "key 'plant.j1': expected a finite number, got nan"),
    ("plant:\n  j1: yes\n", "key 'plant.j1': expected a finite number, got True"),
    ("- 1\n", "expected sections of key: number"),
])
def test_a_plant_of_the_wrong_shape_is_refused_before_drive_sim_starts(work, capsys, plant, needle):
    (work / "p.yaml").write_text(plant)
    for argv in (["demo-track", "--plant", "p.yaml"], ["sim", "--plant", "p.yaml"],
                 ["paper", "--sim-plant", "p.yaml"]):
        _refused(capsys, argv, "p.yaml: plant configuration", needle, cwd=work)


# ---- YAML: duplicate keys, unknown keys, numbers out of the drive's ranges ------------
@pytest.mark.parametrize("text, needle", [
    ("output: a\noutput: b\n", "dup.yaml:2: invalid YAML: duplicate key 'output' (first on line 1)"),
    ("drive:\n  node_id: 2\n  heartbeat_ms: 100\n  node_id: 3\n", "dup.yaml:4:"),
    ("drive: {controller: {kp: 20, kp: 2}}\n", "duplicate key 'kp'"),
])
def test_a_key_given_twice_is_refused(work, capsys, text, needle):
    (work / "dup.yaml").write_text(text)
    for argv in (["plan", "--offline", "--config", "dup.yaml"], ["track", "--config", "dup.yaml"]):
        _refused(capsys, argv, needle, cwd=work)
    (work / "m.yaml").write_text("machine: m\naxes:\n  - {name: x, node_id: 1, node_id: 2}\n")
    _refused(capsys, ["run", "--machine", "m.yaml"], "m.yaml:3:", "duplicate key 'node_id'", cwd=work)


def test_a_merge_key_may_still_be_overridden(work, capsys):
    from fftune.host.config import load_config

    (work / "c.yaml").write_text("drive:\n  <<: {node_id: 2, heartbeat_ms: 50}\n  node_id: 3\n")
    cfg = load_config("c.yaml")
    assert (cfg["drive"]["node_id"], cfg["drive"]["heartbeat_ms"]) == (3, 50)


@pytest.mark.parametrize("text, key, hint", [
    ("limits:\n  max_amplitude_deg: 3\n", "limits.max_amplitude_deg", "did you mean 'max_amplitude_rad'?"),
    ("detct:\n  enabled: false\n", "detct", "did you mean 'detect'?"),
    ("drive:\n  heartbeat_s: 1\n", "drive.heartbeat_s", "did you mean 'heartbeat_ms'?"),
])
def test_an_unknown_key_names_the_nearest_one(work, capsys, text, key, hint):
    (work / "t.yaml").write_text(text)
    _refused(capsys, ["plan", "--offline", "--config", "t.yaml"], f"key '{key}': unknown key ({hint}",
             cwd=work)


@pytest.mark.parametrize("gain, value, limit", [
    ("kp", "1e300", "100000.0"), ("kd", "2.0e4", "10000.0"), ("tau_d", "1.5", "1.0"),
    ("u_max", "1000.5", "1000.0"),
])
def test_controller_gains_within_the_drives_own_ranges(work, capsys, gain, value, limit):
    """configs/od.yaml's high limits: a gain above one would be refused by the drive only
    after it was enabled."""
    (work / "g.yaml").write_text(f"drive:\n  controller: {{{gain}: {value}}}\n")
    for argv in (["plan", "--offline", "--config", "g.yaml"], ["track", "--config", "g.yaml"]):
        _refused(capsys, argv, f"key 'drive.controller.{gain}': expected a number <= {limit}", cwd=work)
    (work / "m.yaml").write_text(f"machine: m\noverrides: {{drive: {{controller: {{{gain}: {value}}}}}}}\n"
                                 f"axes:\n  - {{name: x, node_id: 1}}\n")
    _refused(capsys, ["run", "--machine", "m.yaml"], f"drive.controller.{gain}", limit, cwd=work)


def test_controller_gains_at_the_limit_are_accepted(work):
    from fftune.host.config import load_config, od_param_high

    (work / "g.yaml").write_text("drive:\n  controller: {kp: 1.0e5, kd: 1.0e4, tau_d: 1.0, u_max: 1000}\n")
    c = load_config("g.yaml")["drive"]["controller"]
    assert c == {"kp": od_param_high("KP"), "kd": od_param_high("KD"), "tau_d": 1.0, "u_max": 1000.0}


# ---- command-line options ---------------------------------------------------------------
@pytest.mark.parametrize("option, value, needle", [
    ("-b", "0", "argument -b/--bitrate: 0: expected 10000 .. 1000000 bit/s"),
    ("-b", "99999999", "argument -b/--bitrate: 99999999: expected 10000 .. 1000000 bit/s"),
    ("--node-id", "0", "argument --node-id: 0: expected 1 .. 127"),
    ("--node-id", "128", "argument --node-id: 128: expected 1 .. 127"),
    ("--node-id", "abc", "argument --node-id: expected an integer 1 .. 127, got 'abc'"),
    ("--port", "70000", "argument --port: 70000: expected"),
])
@pytest.mark.parametrize("command", ["run", "plan", "track", "demo", "sim", "demo-track"])
def test_bus_options_out_of_range_are_one_line(work, capsys, command, option, value, needle):
    _refused(capsys, [command, option, value, "--config", "none.yaml"], f"{command}: {needle}", cwd=work)


def test_argparse_errors_are_one_line(work, capsys):
    _refused(capsys, ["track"], "track: the following arguments are required: --config", cwd=work)
    _refused(capsys, ["bogus"], "argument COMMAND: invalid choice: 'bogus'", cwd=work)
    _refused(capsys, ["import-canlog", "x.log", "--node-id", "200"], "--node-id: 200: expected 1 .. 127",
             cwd=work)


def test_port_zero_means_a_free_port_for_the_simulated_drive_only(work, capsys):
    _refused(capsys, ["run", "--port", "0"], "argument --port: 0: expected 1 .. 65535", cwd=work)
    from fftune.host.cli import build_parser
    assert build_parser().parse_args(["sim", "--port", "0"]).port == 0


# ---- nothing left behind when a command that moves an axis is refused -----------------
def test_unreachable_drive_leaves_no_folder(work, capsys):
    port = str(_free_port())
    (work / "t.yaml").write_text("output: out/deep/track\n")
    _refused(capsys, ["track", "--config", "t.yaml", "--port", port], "drive not reachable", cwd=work)
    (work / "m.yaml").write_text("machine: 5\noutput: out/deep\naxes:\n  - {name: x, node_id: 1}\n")
    _refused(capsys, ["run", "--machine", "m.yaml", "--port", port], "drive not reachable", cwd=work)
    # an existing output folder keeps exactly what it held
    (work / "keep").mkdir()
    (work / "keep" / "old.txt").write_text("earlier\n")
    _refused(capsys, ["track", "--config", "t.yaml", "--port", port, "--out", "keep"],
             "drive not reachable", cwd=work)
    assert (work / "keep" / "old.txt").read_text() == "earlier\n"


def test_output_session_removes_what_it_made_and_puts_back_the_earlier(tmp_path):
    from fftune.host.config import output_session

    earlier = tmp_path / "o"
    earlier.mkdir()
    (earlier / "results.yaml").write_text("earlier\n")
    with pytest.raises(RuntimeError), output_session(str(earlier), set_aside=True) as out:
        assert not os.path.exists(os.path.join(out, "results.yaml"))
        assert (tmp_path / "o.previous" / "results.yaml").exists()
        open(os.path.join(out, "drive_sim.log"), "w").close()
        raise RuntimeError("refused before the first experiment")
    assert _tree(tmp_path) == {"o", "o/results.yaml"}
    with pytest.raises(RuntimeError), output_session(str(tmp_path / "a" / "b" / "c")) as out:
        raise RuntimeError("refused")
    assert _tree(tmp_path) == {"o", "o/results.yaml"}
    # measured: kept (a capture in an axis' folder, as a machine writes them)
    with pytest.raises(RuntimeError), output_session(str(tmp_path / "m")) as out:
        os.makedirs(os.path.join(out, "x", "captures"))
        open(os.path.join(out, "x", "captures", "run0.h5"), "w").close()
        raise RuntimeError("failed after a run")
    assert (tmp_path / "m" / "x" / "captures" / "run0.h5").exists()
    # an earlier session's results in the folder do not make this one "measured"
    old = tmp_path / "m" / "x" / "captures" / "run0.h5"
    os.utime(old, (1e9, 1e9))
    with pytest.raises(RuntimeError), output_session(str(tmp_path / "m")) as out:
        open(os.path.join(out, "drive_sim.log"), "w").close()
        raise RuntimeError("refused")
    assert not (tmp_path / "m" / "drive_sim.log").exists() and old.exists()
    with pytest.raises(Exception, match="exists and is not a directory"):
        with output_session(str(earlier / "results.yaml")):
            pass


@needs_drive
def test_demo_refused_by_the_drives_limits_leaves_no_parent_folder(work, capsys):
    """The demo connects (drive_sim writes its log into the output folder), the plan is
    refused by the drive's fs: the folder and the parents it made are gone."""
    (work / "c.yaml").write_text("output: out/a/b\nquantify: {frequencies_hz: [1000]}\n"
                                 "detect: {enabled: false}\ntune: {enabled: false}\n")
    _refused(capsys, ["demo", "--config", "c.yaml", "--no-progress"], "quantify", "fs/2", cwd=work)


# ---- CAN logs and captures --------------------------------------------------------------
def test_canlog_non_finite_timestamp_and_size(work, capsys, monkeypatch):
    (work / "nan.log").write_text("(nan) can0 601#4000200000000000\n")
    _refused(capsys, ["import-canlog", "nan.log", "--out", "o"], "frame 1: timestamp nan is not a finite number",
             cwd=work)
    import fftune.host.canlog as canlog
    monkeypatch.setattr(canlog, "MAX_CANLOG_BYTES", 40)
    text = "(0.000000) can0 601#4000200000000000\n" * 3
    (work / "big.log").write_text(text)
    _refused(capsys, ["import-canlog", "big.log", "--out", "o"],
             f"big.log: cannot read CAN log: {len(text)} bytes, at most 40", cwd=work)


def _npz_declaring(path, shape):
    """An .npz whose one array's header declares ``shape`` over 64 bytes of data."""
    import io

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("u.npy", head.getvalue() + b"\0" * 64)
        z.writestr("y.npy", head.getvalue() + b"\0" * 64)


def test_captures_declaring_more_than_a_signal_holds_are_refused_unread(work, capsys, monkeypatch):
    from fftune.analysis.capture import MAX_CAPTURE_SAMPLES

    _npz_declaring(work / "huge.npz", (10 ** 11,))
    _refused(capsys, ["analyze", "bla", "huge.npz", "--fs", "1000", "--period", "64"],
             "variable 'u' declares 100000000000 values", "nothing was read", cwd=work)
    _npz_declaring(work / "edge.npz", (MAX_CAPTURE_SAMPLES + 1,))
    _refused(capsys, ["analyze", "hosidf", "edge.npz", "--fs", "1000", "--period", "64"],
             f"declares {MAX_CAPTURE_SAMPLES + 1} values", cwd=work)
    # .mat: the declared shape from the headers (whosmat), with the limit lowered so that the
    # file stays small; a file at the limit is read
    import scipy.io

    import fftune.analysis.capture as capture
    monkeypatch.setattr(capture, "MAX_CAPTURE_SAMPLES", 1000)
    scipy.io.savemat(work / "big.mat", {"u": np.zeros(1001), "y": np.zeros(1001)}, do_compression=True)
    _refused(capsys, ["analyze", "bla", "big.mat", "--fs", "1000", "--period", "64"],
             "variable 'u' declares 1001 values (shape (1, 1001))", cwd=work)
    from fftune.analysis.io import load_mat
    scipy.io.savemat(work / "ok.mat", {"u": np.arange(1000.0), "y": np.ones(1000)})
    assert load_mat(work / "ok.mat").signals["u"][999] == 999.0


# ---- the host's heartbeat id, python-can's configuration, timeouts ----------------------
def test_a_node_id_equal_to_the_host_heartbeat_id_is_refused_from_the_command_line(work, capsys):
    """The configuration's node id passed its check (1 != 127); ``--node-id 127`` replaced
    it afterwards: the drive's consumer would watch its own heartbeat's COB-ID."""
    for argv in (["run", "--dry-run", "--node-id", "127"], ["plan", "--node-id", "127"],
                 ["track", "--config", "t.yaml", "--node-id", "127"]):
        (work / "t.yaml").write_text("output: o\n")
        _refused(capsys, argv, "node id 127 is the host's heartbeat id (drive.host_node_id = 127)",
                 "0x77F", cwd=work)


def test_the_client_refuses_ids_and_heartbeat_out_of_range():
    from fftune.analysis.errors import FftuneError
    from fftune.host.drive import BusOptions, DriveClient

    for kw, needle in (({"heartbeat_ms": 20000}, "heartbeat_ms 20000: expected 0 .. 16383"),
                       ({"heartbeat_ms": True}, "heartbeat_ms True"),
                       ({"host_node_id": 0}, "host node id 0: expected 1 .. 127"),
                       ({"host_node_id": 5}, "node id 5 is the host's heartbeat id")):
        with pytest.raises(FftuneError, match=needle):
            DriveClient(BusOptions(node_id=5), progress=False, **kw)
    with pytest.raises(FftuneError, match="node id 128: expected 1 .. 127"):
        DriveClient(BusOptions(node_id=128), progress=False)


@pytest.mark.parametrize("name, value, needle", [
    ("CAN_BITRATE", "abc", "bitrate 'abc': expected an integer 10000 .. 1000000"),
    ("CAN_BITRATE", "5000000", "bitrate '5000000'"),
])
def test_python_can_configuration_from_the_environment_is_checked(work, capsys, monkeypatch, name, value, needle):
    monkeypatch.setenv("CAN_INTERFACE", "socketcand")
    monkeypatch.setenv(name, value)
    _refused(capsys, ["run", "--dry-run"], "python-can configuration", needle, cwd=work)


def test_run_timeout_is_bounded(work, capsys):
    (work / "t.yaml").write_text("drive: {run_timeout_s: 1.0e+300}\n")
    _refused(capsys, ["plan", "--offline", "--config", "t.yaml"],
             "key 'drive.run_timeout_s': expected a number <= 86400.0", cwd=work)


# ---- captures written by an earlier session, exports ------------------------------------
def _captures(folder, n=2):
    from fftune.analysis.capture import write_run

    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        write_run(folder / f"r{i}.h5", {"reference": np.arange(64.0) * (i + 1), "plant_input": np.ones(64)},
                  dict(fs_hz=1000.0, n_period=32, settle_periods=0, record_periods=2, experiment="detect"))


def test_export_is_all_or_nothing(work, capsys):
    _captures(work / "caps")
    (work / "caps" / "r2.h5").write_bytes(b"\x00" * 600)      # damaged: refused
    _refused(capsys, ["export", "caps", "--to", "x/y"], "capture caps/r2.h5", cwd=work)
    _refused(capsys, ["export", "caps", "--format", "csv"], "capture caps/r2.h5", cwd=work)
    (work / "afile").write_text("x\n")
    _refused(capsys, ["export", "caps", "--to", "afile"], "output directory afile: exists and is not a directory",
             cwd=work)
    (work / "caps" / "r2.h5").unlink()
    assert main(["export", "caps", "--to", "x"]) == 0
    assert sorted(os.listdir(work / "x")) == ["r0.mat", "r1.mat"]


@pytest.mark.parametrize("content, needle", [
    (None, "is a FIFO"),
    ("[" * 100_000 + "]" * 100_000, "RecursionError"),
    ('{"meta": 5, "stats": {}}', "not a readable statistics capture"),
])
def test_a_damaged_statistics_capture_is_one_line(tmp_path, content, needle):
    from fftune.analysis.errors import FftuneError
    from fftune.host.captures import _load_stats

    path = tmp_path / "tune-x.stats.json"
    if content is None:
        os.mkfifo(path)
    else:
        path.write_text(content)
    with _deadline(), pytest.raises(FftuneError, match=needle):
        _load_stats(str(path), {})


def test_fleet_reads_statistics_captures_with_the_one_loader(tmp_path):
    """The fleet's metadata probe reads .stats.json through the loader every session uses:
    a FIFO under the name is a reason, not a wait; a damaged one names its file; the next
    readable capture still gives the metadata."""
    from fftune.host.fleet import _first_meta

    fifo = tmp_path / "tune-a.stats.json"
    os.mkfifo(fifo)
    deep = tmp_path / "tune-b.stats.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    bare = tmp_path / "tune-c.stats.json"
    bare.write_text("[1, 2]")
    good = tmp_path / "tune-d.stats.json"
    good.write_text('{"meta": {"fs_hz": 2000.0, "n_period": 512}, "stats": null}')
    with _deadline():
        meta, problems = _first_meta([str(fifo), str(deep), str(bare), str(good)])
    assert meta == {"fs_hz": 2000.0, "n_period": 512}
    assert len(problems) == 3
    assert problems[0].startswith("tune-a.stats.json: ") and "is a FIFO" in problems[0]
    assert problems[1].startswith("tune-b.stats.json: ") and "RecursionError" in problems[1]
    assert problems[2].startswith("tune-c.stats.json: ") and "a JSON list" in problems[2]


def test_fleet_reads_results_yaml_with_the_one_loader(tmp_path):
    from fftune.host.fleet import _names_for

    folder = tmp_path / "mach" / "ax"
    (folder / "captures").mkdir(parents=True)
    (folder / "results.yaml").write_text(
        "a: &a [x, x, x, x, x, x, x, x, x, x]\n"
        + "".join(f"{c}: &{c} [{', '.join([f'*{p}'] * 10)}]\n" for p, c in zip("abcdef", "bcdefg")))
    from fftune.analysis.errors import FftuneError
    with pytest.raises(FftuneError, match="alias bomb"):        # (fleet makes it the row's reason)
        _names_for(str(folder / "captures"))
    (folder / "results.yaml").write_text("axis: {name: y, machine: m2, node_id: 3}\n")
    assert _names_for(str(folder / "captures"))[:3] == ("m2", "y", 3)


def test_a_capture_with_too_many_datasets_is_refused_before_one_is_read(tmp_path, monkeypatch):
    """Each compressed dataset may hold up to MAX_CAPTURE_SAMPLES and inflate from a few kB:
    their number is bounded too, checked before any is read."""
    import h5py

    from fftune.analysis.capture import MAX_CAPTURE_DATASETS, read_run

    def forged(n):
        path = tmp_path / f"c{n}.h5"
        with h5py.File(path, "w") as f:
            for key, value in (("format", "fftune-capture"), ("format_version", 1), ("fs_hz", 1000.0),
                               ("n_period", 32), ("settle_periods", 0), ("record_periods", 2),
                               ("experiment", "detect")):
                f.attrs[key] = value
            for i in range(n):
                f.create_dataset(f"s{i}", data=np.full(64, float(i), dtype="<f4"), compression="gzip")
        return path

    read = []
    original = h5py.Dataset.__getitem__
    monkeypatch.setattr(h5py.Dataset, "__getitem__", lambda self, key: read.append(key) or original(self, key))
    with pytest.raises(Exception, match=f"{MAX_CAPTURE_DATASETS + 1} datasets, at most {MAX_CAPTURE_DATASETS}"):
        read_run(forged(MAX_CAPTURE_DATASETS + 1))
    assert read == []
    run = read_run(forged(MAX_CAPTURE_DATASETS))
    assert len(run.signals) == MAX_CAPTURE_DATASETS and run.signals["s7"][63] == 7.0


def test_environment_and_doc_template_that_are_not_regular_files(work, capsys, monkeypatch):
    os.mkfifo(work / "d.template.md")
    _refused(capsys, ["paper", "--short", "--doc", "d.md"], "d.template.md: cannot read --doc template: is a FIFO",
             cwd=work)
    monkeypatch.setenv("FFTUNE_DRIVE_SIM", str(work / "adir"))       # a directory is "executable"
    for argv in (["demo"], ["sim"], ["demo-track"]):
        _refused(capsys, argv, "FFTUNE_DRIVE_SIM=", "adir: not an executable file", cwd=work)


# ---- a forged CAN log: values the drive never sends --------------------------------------
def _logged_session(samples, *, with_period=True, command=b"\x01"):
    import struct

    from fftune.host.sdo_sniffer import SdoTransfer

    def tr(t, direction, index, sub, data):
        return SdoTransfer(timestamp=t, node_id=1, direction=direction, index=index, subindex=sub,
                           data=data, mode="expedited")
    out = [tr(0.1, "download", 0x2001, 8, struct.pack("<I", 2)),
           tr(0.2, "download", 0x2001, 7, struct.pack("<I", 0)),
           tr(0.3, "download", 0x2020, 1, struct.pack("<I", 0x03)),     # reference, plant_input
           tr(0.4, "upload", 0x2000, 8, struct.pack("<f", 1000.0)),
           tr(0.5, "download", 0x2010, 1, command),
           tr(0.9, "upload", 0x2021, 0, np.asarray(samples, dtype="<f4").tobytes())]
    if with_period:
        out.insert(0, tr(0.0, "download", 0x2001, 5, struct.pack("<I", 32)))
    return out


def test_a_forged_can_log_is_one_line_per_damage():
    from fftune.analysis.errors import FftuneError
    from fftune.host.canlog import session_from_transfers
    from fftune.host.odmap import DEFAULT_EDS

    x = np.column_stack([np.arange(64.0), -np.arange(64.0) / 4])      # 64 samples x 2 signals
    sess = session_from_transfers(_logged_session(x), DEFAULT_EDS)
    (requested, rec), = sess.runs
    assert rec.period_samples == 32 and rec.record_periods == 2 and rec.fs_hz == 1000.0
    assert rec.signals["plant_input"][63] == -15.75 and rec.signals["reference"][5] == 5.0
    bad = x.copy()
    bad[5, 1] = np.nan
    with pytest.raises(FftuneError, match=r"t=0.900: signal plant_input sample 5 is nan: not a finite number"):
        session_from_transfers(_logged_session(bad), DEFAULT_EDS)
    with pytest.raises(FftuneError, match="holds no exc_period of the run"):
        session_from_transfers(_logged_session(x, with_period=False), DEFAULT_EDS)
    with pytest.raises(FftuneError, match=r"SDO download of 0x2010:1 at t=0.500: cannot be replayed"):
        session_from_transfers(_logged_session(x, command=b""), DEFAULT_EDS)


@pytest.mark.parametrize("command", ["sim", "demo", "demo-track"])
def test_the_simulated_drives_address_is_checked_before_it_starts(work, capsys, command):
    """drive_sim binds an IPv4 address (inet_pton): anything else was drive_sim's own error
    line after fftune had made the output folder (or replaced itself by drive_sim)."""
    for host in ("256.1.1.1", "localhost", "::1"):
        _refused(capsys, [command, "--host", host], f"--host '{host}': the simulated drive binds", cwd=work)


@pytest.mark.parametrize("key, value, limit", [
    ("max_step_rel", "1.0e+300", "10.0"), ("max_step_abs", "101", "100.0"), ("kv_max_step", "1.0e+9", "100.0"),
    ("rms_limit_rad", "1.0e+4", "1000.0"), ("rollback_ratio", "1.0e+300", "1000.0"),
])
def test_track_limits_have_upper_bounds(work, capsys, key, value, limit):
    (work / "t.yaml").write_text(f"track:\n  limits: {{{key}: {value}}}\n")
    _refused(capsys, ["track", "--config", "t.yaml"],
             f"key 'track.limits.{key}': expected a number <= {limit}", cwd=work)


def test_an_error_line_stays_one_line_whatever_the_name(work, capsys):
    """A file name or a YAML key with a newline or a terminal escape sequence was printed as
    is: two lines, a recoloured terminal; a 5000-character name filled the screen."""
    (work / "k.yaml").write_text('"a\\nb\\x1b[31mred": 1\n')
    line = _refused(capsys, ["plan", "--offline", "--config", "k.yaml"], "key 'a\\nb\\x1b[31mred': unknown key",
                    cwd=work)
    assert "\x1b" not in line
    _refused(capsys, ["run", "--config", "a\nb.yaml"], "a\\nb.yaml: cannot read configuration", cwd=work)
    line = _refused(capsys, ["run", "--config", "x" * 5000], "File name too long", cwd=work)
    assert len(line) <= 2000 + len("fftune: error: ") and " ... " in line


def test_an_eds_above_its_size_limit_is_refused_before_it_is_parsed(work, capsys):
    from fftune.host.config import MAX_EDS_BYTES

    (work / "big.eds").write_text("[DeviceInfo]\n;" + "x" * MAX_EDS_BYTES + "\n")
    (work / "one.log").write_text("(0.000000) can0 601#4000200000000000\n")
    size = os.path.getsize(work / "big.eds")
    for argv in (["run", "--dry-run", "--eds", "big.eds"], ["import-canlog", "one.log", "--eds", "big.eds", "--out", "o"]):
        _refused(capsys, argv, f"big.eds: cannot read EDS: {size} bytes, at most {MAX_EDS_BYTES}", cwd=work)


@pytest.mark.parametrize("text, needle", [
    ("machine: m\naxis:\n  - {name: x, node_id: 1}\n", "m.yaml: key 'axis': unknown key (did you mean 'axes'?"),
    ("machine: m\naxes:\n  - {name: x, node_id: 1, plnt: p.yaml}\n",
     "m.yaml: axes[0]: key 'plnt': unknown key (did you mean 'plant'?"),
])
def test_a_machine_files_unknown_key_names_the_nearest_one(work, capsys, text, needle):
    (work / "m.yaml").write_text(text)
    _refused(capsys, ["run", "--machine", "m.yaml"], needle, cwd=work)


def test_a_csv_with_more_rows_than_a_signal_holds_is_refused_before_parsing(work, capsys, monkeypatch):
    import fftune.analysis.capture as capture

    monkeypatch.setattr(capture, "MAX_CAPTURE_SAMPLES", 100)
    (work / "long.csv").write_text("u,y\n" + "1,2\n" * 1200)
    _refused(capsys, ["analyze", "bla", "long.csv", "--fs", "1000", "--period", "64"],
             "long.csv: 1201 lines, at most 100 samples a signal", cwd=work)
    from fftune.analysis.io import load_csv
    (work / "ok.csv").write_text("u,y\n" + "".join(f"{i},{-i}\n" for i in range(1000)))
    assert load_csv(work / "ok.csv").signals["y"][999] == -999.0


@needs_drive
def test_paper_checks_the_simulation_plant_before_the_set_up_part_runs(work, capsys):
    """A value out of drive_sim's range in ``--sim-plant`` failed only after the set-up part
    had measured (its captures left behind); drive_sim, the one source of the ranges, is asked
    first."""
    (work / "p.yaml").write_text(open(TWOMASS).read().replace("  j1: 1.0e-4", "  j1: -1.0"))
    _refused(capsys, ["paper", "--short", "--sim-plant", "p.yaml", "--no-progress"],
             "p.yaml:18: plant.j1 = -1.0: out of range", cwd=work)


@pytest.mark.parametrize("literal, digits", [("9" * 5000, 5000), ("0x" + "f" * 300, 302), ("-" + "1" * 31, 31)])
def test_an_integer_literal_of_thousands_of_digits_is_one_line(work, capsys, literal, digits):
    """5000 digits: Python's int() refuses them (a ValueError traceback); 300 hex digits
    overflowed math.isfinite (an OverflowError traceback). The loader refuses more than 30."""
    (work / "i.yaml").write_text(f"drive:\n  node_id: {literal}\n")
    for argv in (["plan", "--offline", "--config", "i.yaml"], ["track", "--config", "i.yaml"]):
        _refused(capsys, argv, f"i.yaml:2: invalid YAML: integer of {digits} digits (at most 30)", cwd=work)
    (work / "ok.yaml").write_text("drive:\n  node_id: 000000000000000000000000000003\n")
    from fftune.host.config import load_config
    assert load_config("ok.yaml")["drive"]["node_id"] == 3


@pytest.mark.parametrize("value, needle", [
    ("2001-13-45", "c.yaml:1: invalid YAML: cannot read '2001-13-45' as timestamp: month must be in 1..12"),
    ("!!int 'abc'", "cannot read 'abc' as int"),
    ("!!float 'abc'", "cannot read 'abc' as float"),
    ("!!bool 'maybe'", "cannot read 'maybe' as bool"),
    ("!!timestamp '2001-01-01T99:00:00'", "hour must be in 0..23"),
])
def test_a_scalar_yaml_cannot_build_is_one_line(work, capsys, value, needle):
    """PyYAML's constructors raise ValueError / KeyError on these (a traceback before)."""
    (work / "c.yaml").write_text(f"output: {value}\n")
    for argv in (["plan", "--offline", "--config", "c.yaml"], ["track", "--config", "c.yaml"]):
        _refused(capsys, argv, needle, cwd=work)
    (work / "m.yaml").write_text(f"machine: m\noutput: {value}\naxes: [{{name: x, node_id: 1}}]\n")
    _refused(capsys, ["run", "--machine", "m.yaml"], "m.yaml:2: invalid YAML: cannot read", cwd=work)
