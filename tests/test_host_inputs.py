"""Host inputs, files and deployment edges (issue 21 items 4, 5, 6, and the resume row).

Item 4: config ranges, YAML aliases and depth, CSV capture metadata, --lines, --json: each one
``fftune: error:`` line (exit 2) within seconds and bounded memory. Item 5: outputs follow the
umask; a run that fails before its first experiment leaves no output directory (and the
demo puts an earlier one back). Item 6: ``fftune sim`` simulates the plant ``fftune demo``
does for the same configuration; without ``-i`` the CLI honours python-can's configuration.
Resume: captures taken with another set of controller keys are never reused.
"""
import argparse
import os
import resource
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from fftune.analysis.errors import FftuneError
from fftune.host.captures import CaptureStore
from fftune.host.cli import main
from fftune.host.drive import BusOptions, DriveClient, RunRecord, quiet_can_loggers
from host_fixtures import free_port
from test_reliability_support import EDS, REPO, needs_drive

DEMO = os.path.join(REPO, "configs", "demo.yaml")
PLANT = os.path.join(REPO, "configs", "plant_twomass.yaml")


def _one_line(err, *needles):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fftune: error: "), err[-2000:]
    assert len(lines[0]) < 400, lines[0][:400]          # no huge value printed
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"
    return lines[0]


def _fftune_bounded(args, timeout_s=30, memory_bytes=1 << 30):
    """`fftune ARGS` in a child with at most ``memory_bytes`` of address space, timed."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", "import sys; from fftune.host.cli import main; "
                           "sys.exit(main(sys.argv[1:]))"] + list(args),
                          capture_output=True, text=True, timeout=timeout_s, preexec_fn=limit)
    return proc.returncode, proc.stderr, time.monotonic() - t0


# ---- item 4: configuration ranges ------------------------------------------------------
@pytest.mark.parametrize("text, needles", [
    ("quantify:\n  frequencies_hz: {start: 1e-300, stop: 1e300, step: 1e-300}\n",
     ("quantify.frequencies_hz", "more than 1e308 values", "at most 10000")),
    ("quantify:\n  frequencies_hz: {start: 1, stop: .inf, step: 1}\n",
     ("quantify.frequencies_hz.stop", "finite", "inf")),
    ("detect:\n  rms_levels: {start: 0.1, stop: 1, count: 1e10}\n",
     ("detect.rms_levels.count", "10000000000 values", "at most 10000")),
    ("quantify:\n  frequencies_hz: {start: 1, stop: 1e12, step: 1}\n",
     ("quantify.frequencies_hz", "1e+12 values", "at most 10000")),
    ("quantify:\n  rms_levels: {start: .nan, stop: 1, count: 3}\n",
     ("quantify.rms_levels.start", "finite")),
    ("quantify:\n  frequencies_hz: {start: 10, stop: 1, step: 1}\n",
     ("quantify.frequencies_hz", "stop < start")),
    ("detect:\n  band_hz: [1, .inf]\n", ("detect.band_hz", "inf")),
])
def test_ranges_are_bounded(tmp_path, capsys, text, needles):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    t0 = time.monotonic()
    assert main(["run", "--config", str(path), "-i", "socketcand", "--port", str(free_port()),
                 "--out", str(tmp_path / "out")]) == 2
    assert time.monotonic() - t0 < 5 and not (tmp_path / "out").exists()
    _one_line(capsys.readouterr().err, str(path), *needles)


def test_heartbeat_whose_consumer_time_does_not_fit_is_refused_not_clipped(tmp_path):
    from fftune.host.config import validate
    assert validate({"drive": {"heartbeat_ms": 16383}})["drive"]["heartbeat_ms"] == 16383
    with pytest.raises(FftuneError, match=r"key 'drive.heartbeat_ms': expected an integer <= 16383, got 20000"):
        validate({"drive": {"heartbeat_ms": 20000}}, "p")


def test_range_at_the_limit_is_accepted_and_yaml_1_2_numbers_are_numbers(tmp_path):
    from fftune.host.config import MAX_RANGE_POINTS, expand_values
    assert len(expand_values({"start": 1, "stop": MAX_RANGE_POINTS, "step": 1}, "p", "k")) == MAX_RANGE_POINTS
    with pytest.raises(FftuneError, match="at most 10000"):
        expand_values({"start": 1, "stop": MAX_RANGE_POINTS + 1, "step": 1}, "p", "k")
    with pytest.raises(FftuneError, match="10001 values: at most 10000"):
        expand_values([1.0] * (MAX_RANGE_POINTS + 1), "p", "k")
    from fftune.host.config import safe_yaml_load
    assert safe_yaml_load("a: 1e-3\nb: 2E6\nc: 1_000\nd: 1e\n", "x") == {"a": 1e-3, "b": 2e6, "c": 1000, "d": "1e"}


# ---- item 4: YAML alias bombs and depth --------------------------------------------------
def _laughs(levels, key="rms_levels"):
    lines = ['x0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, levels):
        lines.append(f"x{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    return "\n".join(lines) + f"\ndetect:\n  {key}: *a{levels - 1}\n"


@pytest.mark.parametrize("text, needles", [
    (_laughs(9), ("YAML nodes", "alias", "100000")),
    ("detect:\n  rms_levels: " + "[" * 100_000 + "\n", ("nested deeper than 32",)),
    ("a: " + "{b: " * 50_000 + "\n", ("nested deeper than 32",)),
], ids=["billion-laughs", "100000-brackets", "50000-braces"])
def test_yaml_bombs_are_one_line_in_bounded_time_and_memory(tmp_path, text, needles):
    path = tmp_path / "bomb.yaml"
    path.write_text(text)
    code, err, elapsed = _fftune_bounded(["run", "--config", str(path), "-i", "socketcand",
                                          "--port", str(free_port())])
    assert code == 2, err[-2000:]
    _one_line(err, str(path), *needles)
    assert elapsed < 15


def test_aliased_value_in_an_error_message_is_shown_truncated(tmp_path, capsys):
    """81 lists of 9 (below the node limit) behind one alias: its repr is half a megabyte."""
    row = "[" + ", ".join(['["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]'] * 9) + "]"
    path = tmp_path / "c.yaml"
    path.write_text("detect:\n  band_hz: &a [" + ", ".join([row] * 9) + "]\n"
                    "quantify:\n  rms_levels: [" + ", ".join(["*a"] * 100) + "]\n")
    assert main(["run", "--config", str(path), "-i", "socketcand", "--port", str(free_port())]) == 2
    _one_line(capsys.readouterr().err, "detect.band_hz", "...")


def test_oversized_config_is_refused_unread(tmp_path, capsys):
    path = tmp_path / "big.yaml"
    path.write_text("output: out/x\n" + "# " + "x" * (1 << 20) + "\n")
    assert main(["run", "--config", str(path), "-i", "socketcand", "--port", str(free_port())]) == 2
    _one_line(capsys.readouterr().err, "at most 1048576")


# ---- item 4: CSV capture metadata, --lines, --json ---------------------------------------
def _csv(tmp_path, meta, name="m.csv", n=64, periods=4):
    t = np.arange(periods * n)
    u = np.sin(2 * np.pi * 3 * t / n)
    y = 0.5 * u + 0.01 * u ** 3
    path = tmp_path / name
    rows = "\n".join(f"{float(a)!r},{float(b)!r}" for a, b in zip(u, y))
    path.write_text(f"# fftune capture: {meta}\nu,y\n{rows}\n")
    return str(path)


@pytest.mark.parametrize("meta, needles", [
    ('{"fs_hz": "abc", "n_period": 64}', ("fs_hz", "'abc'")),
    ('[1, 2]', ("expected a JSON object", "list")),
    ('{"fs_hz": 100, "n_period": "x"}', ("n_period", "'x'")),
    ('{"fs_hz": 100, "n_period": 0}', ("n_period", "got 0")),
    ('{"fs_hz": 100, "n_period": 1e400}', ("n_period", "inf")),
    ('{"fs_hz": 100, "n_period": 64.5}', ("n_period", "64.5")),
    ('{"fs_hz": NaN, "n_period": 64}', ("fs_hz", "nan")),
    ('{"fs_hz": 100, "n_period": 64, "record_periods": -1}', ("record_periods", "-1")),
    ('{"fs_hz": 100, "realizations": 99999999999999999999}', ("realizations",)),
    ('{"fs_hz": 100, ' + '"a": ' + '[' * 5000 + ']' * 5000 + '}', ("fftune metadata comment",)),
], ids=["fs-abc", "list", "n-x", "n-0", "n-inf", "n-64.5", "fs-nan", "record-1", "m-huge", "deep"])
def test_csv_capture_metadata_errors_are_one_line(tmp_path, capsys, meta, needles):
    path = _csv(tmp_path, meta)
    assert main(["analyze", "hosidf", path]) == 2
    _one_line(capsys.readouterr().err, f"{path} line 1", *needles)


def test_csv_capture_metadata_good_is_used(tmp_path, capsys):
    path = _csv(tmp_path, '{"fs_hz": 100, "n_period": 64, "record_periods": 3, "settle_periods": 1}')
    assert main(["analyze", "hosidf", path]) == 0
    assert "f0 = 4.6875 Hz" in capsys.readouterr().out        # 3 cycles of 64 samples at 100 Hz


@pytest.mark.parametrize("content, needles", [
    ("3 99999999999999999999\n", ("line 1", "99999999999999999999", "2147483647")),
    ("3\n5 " + "9" * 5000 + "\n", ("line 2", "is not an integer DFT bin", "...")),
    ("3, 0\n", ("bin 0", "1 .. 2147483647")),
], ids=["huge", "5000-digits", "zero"])
def test_lines_file_values_are_bounded(tmp_path, capsys, content, needles):
    data = _csv(tmp_path, '{"fs_hz": 100, "n_period": 64}')
    lines = tmp_path / "lines.txt"
    lines.write_text(content)
    assert main(["analyze", "bla", data, "--lines", str(lines)]) == 2
    _one_line(capsys.readouterr().err, str(lines), *needles)


@pytest.mark.parametrize("target, needles", [
    ("{tmp}/missing/x.json", ("--json", "does not exist")),
    ("{tmp}", ("--json", "is a directory")),
    ("/proc/fftune-x.json", ("/proc",)),
    ("", ("--json", "empty file name")),
])
def test_json_target_that_cannot_be_written(tmp_path, capsys, target, needles):
    data = _csv(tmp_path, '{"fs_hz": 100, "n_period": 64}')
    assert main(["analyze", "hosidf", data, "--json", target.format(tmp=tmp_path)]) == 2
    _one_line(capsys.readouterr().err, *needles)


def test_json_write_failure_after_the_check_is_one_line(tmp_path):
    from fftune.analysis.cli import _write_json
    with pytest.raises(FftuneError, match=r"/proc/fftune-y.json: cannot write in /proc"):
        _write_json("/proc/fftune-y.json", {"a": 1})


# ---- item 5: modes and directories -------------------------------------------------------
@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o027, 0o640), (0o077, 0o600)])
def test_outputs_follow_the_umask(tmp_path, mask, mode):
    from fftune.host.atomic import write_atomic
    from fftune.host.report import write_results
    from fftune.host.sim import derived_plant

    old = os.umask(mask)
    try:
        write_atomic(str(tmp_path / "report.html"), "<html></html>")
        write_results(str(tmp_path), {"a": 1})
        derived_plant(PLANT, {"plant": {"viscous": 2e-3}}, str(tmp_path / "plant.yaml"))
    finally:
        os.umask(old)
    for name in ("report.html", "results.yaml", "plant.yaml"):
        assert os.stat(tmp_path / name).st_mode & 0o777 == mode, name


@needs_drive
@pytest.mark.parametrize("earlier", [False, True])
def test_demo_refused_before_its_first_experiment_leaves_the_output_as_it_was(tmp_path, capsys, earlier):
    out = tmp_path / "demo"
    if earlier:
        out.mkdir()
        (out / "results.yaml").write_text("earlier\n")
    raw = yaml.safe_load(open(DEMO))
    raw["detect"]["rms_levels"] = [300, 1000]          # V typed for mV: u_max is the drive's
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    assert main(["demo", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 2
    _one_line(capsys.readouterr().err, "detect.rms_levels[0]", "300 V rms", "10 V")
    if earlier:
        assert os.listdir(out) == ["results.yaml"] and (out / "results.yaml").read_text() == "earlier\n"
    else:
        assert not out.exists()
    assert not (tmp_path / "demo.previous").exists()


# ---- item 6: fftune sim's plant, python-can's configuration -----------------------------
def _read_truth(port):
    quiet_can_loggers()
    with DriveClient(BusOptions(port=port, eds=EDS), heartbeat_ms=0, progress=False) as c:
        return float(c.get("sim_fv_volt")), float(c.get("sim_fc_volt"))


@needs_drive
def test_fftune_sim_simulates_the_demo_plant(tmp_path):
    """`fftune sim` + `fftune run` measure the plant `fftune demo` does: by default both take
    configs/demo.yaml, whose sim.overrides raise the viscous friction of the base plant."""
    from fftune.host.sim import derived_plant, start_drive_sim

    with open(DEMO) as fh:
        sim_cfg = yaml.safe_load(fh)["sim"]
    assert sim_cfg["overrides"]["plant"]["viscous"] != yaml.safe_load(open(PLANT))["plant"]["viscous"]
    demo_plant = derived_plant(PLANT, sim_cfg["overrides"], str(tmp_path / "plant.yaml"))
    sim = start_drive_sim(demo_plant, log_path=str(tmp_path / "d.log"))
    try:
        expected = _read_truth(sim.port)
    finally:
        sim.stop()
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "fftune.host.cli", "sim", "--port", str(port)],
                            cwd=str(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "listening on socketcand" in line, proc.stderr.read() if proc.poll() is not None else line
        assert _read_truth(port) == pytest.approx(expected, rel=1e-6)
    finally:
        proc.kill()
        proc.communicate()
    assert os.listdir(tmp_path) == ["plant.yaml", "d.log"] or sorted(os.listdir(tmp_path)) == ["d.log", "plant.yaml"]


def test_fftune_sim_config_plant_overrides_and_bus(tmp_path, monkeypatch):
    """`fftune sim --config FILE`: its sim.plant with sim.overrides (handed to drive_sim as a
    memory file, nothing written), its sim.bitrate and drive.node_id; --plant and -b win."""
    import fftune.host.sim as sim_mod

    seen = []
    monkeypatch.setattr(sim_mod.os, "execv", lambda exe, cmd: seen.append(cmd))
    stage = os.path.join(REPO, "configs", "plant_stage.yaml")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"sim:\n  plant: {stage}\n  overrides:\n    plant: {{viscous: 3.5e-3}}\n"
                   f"  bitrate: 250000\ndrive:\n  node_id: 4\n")
    assert main(["sim", "--config", str(cfg), "--port", "0"]) == 0
    assert main(["sim", "--config", str(cfg), "--port", "0", "--plant", PLANT, "-b", "500000"]) == 0
    from fftune.host.config import safe_yaml_load   # (drive_sim reads 2e-05 as a number too)
    for cmd, base, bitrate in zip(seen, (stage, PLANT), ("250000", "500000")):
        plant = cmd[cmd.index("--config") + 1]
        with open(plant) as fh:
            doc = safe_yaml_load(fh.read(), plant)
        assert doc["plant"]["viscous"] == 3.5e-3
        with open(base) as fh:
            base_doc = safe_yaml_load(fh.read(), base)
        assert {k: v for k, v in doc["plant"].items() if k != "viscous"} == \
            {k: v for k, v in base_doc["plant"].items() if k != "viscous"}
        assert cmd[cmd.index("--bitrate") + 1] == bitrate and cmd[cmd.index("--node-id") + 1] == "4"
    assert not [f for f in os.listdir(tmp_path) if f != "c.yaml"]


def _bus_args(argv=()):
    p = argparse.ArgumentParser()
    from fftune.host.drive import add_bus_arguments
    add_bus_arguments(p)
    return p.parse_args(list(argv))


@pytest.fixture
def can_env(tmp_path, monkeypatch):
    """No python-can configuration but what a test sets (HOME without ~/.canrc)."""
    import can
    monkeypatch.setenv("HOME", str(tmp_path))
    for name in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(can, "rc", {})
    return monkeypatch


def test_python_can_environment_is_honoured_without_dash_i(can_env):
    assert BusOptions.from_args(_bus_args()).interface == "socketcand"     # nothing configured
    can_env.setenv("CAN_INTERFACE", "virtual")
    can_env.setenv("CAN_CHANNEL", "fftune-env-bus")
    can_env.setenv("CAN_BITRATE", "250000")
    opts = BusOptions.from_args(_bus_args())
    assert (opts.interface, opts.channel, opts.bitrate) == ("virtual", "fftune-env-bus", 250000)
    assert opts.bus_kwargs() == {"interface": "virtual", "channel": "fftune-env-bus", "bitrate": 250000}
    # the command line wins
    opts = BusOptions.from_args(_bus_args(["-i", "socketcand", "--port", "4000"]))
    assert (opts.interface, opts.port, opts.bitrate) == ("socketcand", 4000, None)
    opts = BusOptions.from_args(_bus_args(["-c", "other"]))
    assert (opts.interface, opts.channel) == ("virtual", "other")


def test_python_can_config_file_is_honoured(can_env, tmp_path):
    (tmp_path / ".canrc").write_text("[default]\ninterface = virtual\nchannel = fftune-file-bus\n")
    opts = BusOptions.from_args(_bus_args())
    assert (opts.interface, opts.channel) == ("virtual", "fftune-file-bus")


def test_run_uses_the_python_can_environment(can_env, tmp_path, capsys):
    can_env.setenv("CAN_INTERFACE", "virtual")
    can_env.setenv("CAN_CHANNEL", "fftune-empty-bus")
    out = tmp_path / "out"
    raw = yaml.safe_load(open(DEMO))
    raw["drive"]["sdo_timeout_s"] = 0.1          # (the probe's wait on a bus without a node)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    assert main(["run", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 2
    _one_line(capsys.readouterr().err, "interface virtual, channel fftune-empty-bus")
    assert not out.exists()


def test_broken_python_can_configuration_is_one_line(can_env, capsys):
    can_env.setenv("CAN_INTERFACE", "no-such-interface")
    assert main(["run", "--config", DEMO]) == 2
    _one_line(capsys.readouterr().err, "python-can configuration", "no-such-interface")


# ---- resume: the request's key set is compared ------------------------------------------
def _record():
    return RunRecord(signals={"motor_angle": np.linspace(0.0, 1.0, 8)}, parameters={"fs": 2560.0},
                     fs_hz=2560.0, period_samples=8, settle_periods=0, record_periods=1,
                     run_counter=1, t_start=0.0, t_end=1.0)


@pytest.mark.parametrize("stored, asked", [
    ({"kp": 20.0, "exc_amplitude": 0.5}, {"kp": 20.0, "exc_amplitude": 0.5, "u_max": 5.0}),
    ({"kp": 20.0, "exc_amplitude": 0.5, "u_max": 5.0}, {"kp": 20.0, "exc_amplitude": 0.5}),
    ({"kp": 20.0, "exc_amplitude": 0.5}, {"kd": 20.0, "exc_amplitude": 0.5}),
])
def test_captures_with_another_set_of_controller_keys_are_not_reused(tmp_path, stored, asked):
    store = CaptureStore(str(tmp_path))
    store.save("quantify-A00", _record(), experiment="quantify", request=stored, config={},
               identity={})
    assert store.load("quantify-A00", dict(stored)) is not None       # the same request resumes
    with pytest.raises(FftuneError, match="captured with other parameters"):
        store.load("quantify-A00", asked)


def test_statistics_captures_compare_the_key_set_too(tmp_path):
    from fftune.analysis.stats import HarmonicStats
    rec = _record()
    rec.signals = {}
    rec.stats = HarmonicStats(periods=1, harmonics=1, mean={"motor_angle": np.array([1 + 1j])},
                              var={"motor_angle": np.array([0.0])})
    store = CaptureStore(str(tmp_path))
    store.save("tune-A", rec, experiment="tune", request={"kfc": 0.1}, config={}, identity={})
    assert store.load("tune-A", {"kfc": 0.1}) is not None
    with pytest.raises(FftuneError, match="captured with other parameters"):
        store.load("tune-A", {"kfc": 0.1, "u_max": 5.0})


@pytest.mark.parametrize("key", ["parameters", "metadata"])
def test_capture_json_metadata_must_be_a_mapping(tmp_path, key):
    from fftune.analysis import capture
    from fftune.analysis.errors import InputError
    meta = {"fs_hz": 2560.0, "n_period": 8, "settle_periods": 0, "record_periods": 1,
            "experiment": "detect", key: [1, 2]}
    with pytest.raises(InputError, match=f"{key} must be a mapping"):
        capture.write_run(tmp_path / "r.h5", {"u": np.zeros(8)}, meta)
    assert not (tmp_path / "r.h5").exists()


def test_output_dir_is_checked_without_being_made(tmp_path):
    from fftune.host.config import check_output_dir
    target = tmp_path / "a" / "b"
    assert check_output_dir(str(target), create=False) == str(target) and not (tmp_path / "a").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(FftuneError, match="is not a directory"):
        check_output_dir(str(tmp_path / "file" / "out"), create=False)
    with pytest.raises(FftuneError, match="exists and is not a directory"):
        check_output_dir(str(tmp_path / "file"), create=False)
    assert check_output_dir(str(target)) == str(target) and target.is_dir()


def test_import_canlog_that_fails_leaves_no_output_directory(tmp_path, capsys):
    log = tmp_path / "session.log"
    log.write_text("(0.0) can0 123#00\n")            # no SDO transfer of node 1
    out = tmp_path / "out"
    cfg = tmp_path / "c.yaml"
    cfg.write_text("output: out/x\n")
    assert main(["import-canlog", str(log), "--config", str(cfg), "--out", str(out), "--no-figures"]) == 2
    _one_line(capsys.readouterr().err, str(log))
    assert not out.exists()


def test_fftune_sim_serves_the_bus_python_can_names(can_env, monkeypatch, capsys):
    """`fftune sim` and `fftune run` without -i meet on the bus python-can's configuration
    names; one the simulated drive cannot serve falls back to socketcand, said so."""
    import fftune.host.sim as sim_mod

    seen = []
    monkeypatch.setattr(sim_mod.os, "execv", lambda exe, cmd: seen.append(cmd))
    can_env.setenv("CAN_INTERFACE", "socketcan")
    can_env.setenv("CAN_CHANNEL", "vcan7")
    assert main(["sim"]) == 0
    assert seen[-1][1:3] == ["--can", "socketcan:vcan7"]
    assert BusOptions.from_args(_bus_args()).bus_kwargs() == {"interface": "socketcan", "channel": "vcan7"}
    assert main(["sim", "-i", "socketcand", "--port", "4001"]) == 0          # -i wins
    assert seen[-1][1:3] == ["--can", "socketcand:127.0.0.1:4001"]
    can_env.setenv("CAN_INTERFACE", "virtual")
    capsys.readouterr()
    assert main(["sim", "--port", "4002"]) == 0
    assert seen[-1][1:3] == ["--can", "socketcand:127.0.0.1:4002"]
    assert "names interface virtual, which the simulated drive cannot serve" in capsys.readouterr().err


@pytest.mark.parametrize("value, shown", [(0, "0"), (np.inf, "inf"), (np.nan, "nan"), (2.5, "2.5"),
                                          (1e300, "1e+300")])
def test_npz_layout_scalars_are_bounded(tmp_path, capsys, value, shown):
    t = np.arange(256)
    path = tmp_path / "d.npz"
    np.savez(path, u=np.sin(2 * np.pi * 3 * t / 64), y=np.cos(2 * np.pi * 3 * t / 64), fs=100.0,
             n_period=value)
    assert main(["analyze", "hosidf", str(path)]) == 2
    _one_line(capsys.readouterr().err, str(path), "'n_period'", shown)
