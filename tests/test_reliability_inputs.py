"""Bad inputs: corrupted and truncated capture files and CAN logs, malformed configs.

Every case goes through the `fftune` command line (fftune.host.cli.main) as a user meets it: exit code 2, one line
``fftune: error: ...`` naming the file, no traceback, nothing written. For capture files
also in-process: 300 seeded corruptions (flipped bytes anywhere, truncations) each read back
either exactly as written or rejected with an InputError, never as other numbers.
"""
import json
import os
import random
import threading

import numpy as np
import pytest

from fftune.analysis import capture
from fftune.analysis.errors import InputError
from test_reliability_support import EDS, REPO, needs_drive, start_drive

N, T, P = 64, 1, 3


def _meta():
    return {"fs_hz": 2560.0, "n_period": N, "settle_periods": T, "record_periods": P,
            "experiment": "detect", "level_index": 0, "realization": 0,
            "parameters": {"exc_amplitude": 0.5, "kfc": 0.1}, "firmware_version": "0.1.0",
            "eds_identity": json.dumps({"vendor_id": 4087}), "started_at": "2026-01-01T00:00:00+00:00",
            "metadata": {"note": "reliability"}}


def _signals():
    rng = np.random.default_rng(5)
    return {name: rng.standard_normal((T + P) * N) for name in ("reference", "plant_input", "motor_angle")}


class _Result:
    def __init__(self, returncode, stderr):
        self.returncode, self.stderr = returncode, stderr


def _fftune(args, capsys):
    """`fftune ARGS` in this process (an exception other than the CLI's own error handling
    propagates and fails the test, as a traceback would)."""
    from fftune.host.cli import main

    capsys.readouterr()
    try:
        code = main(list(args))
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    return _Result(code, capsys.readouterr().err)


def _assert_clear_error(res, names):
    err = res.stderr.strip()
    assert res.returncode == 2, f"exit {res.returncode}: {err[-800:]}"
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("fftune: error: "), err
    assert any(n in lines[0] for n in names), f"error does not name {names}: {lines[0]}"


@pytest.fixture(scope="module")
def good_capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("cap")
    path = capture.write_run(d / "run.h5", _signals(), _meta())
    return str(path)


def test_corrupted_capture_files_never_read_as_other_data(good_capture, tmp_path):
    raw = open(good_capture, "rb").read()
    ref = capture.read_run(good_capture)
    rng = random.Random(2024)
    outcome = {"identical": 0, "rejected": 0}
    for k in range(300):
        b = bytearray(raw)
        if k % 5 == 4:
            b = b[:rng.randrange(len(b))]  # truncated
        else:
            off = rng.randrange(len(b))
            for i in range(rng.choice((1, 4, 16))):
                if off + i < len(b):
                    b[off + i] ^= rng.randrange(1, 256)
        path = tmp_path / f"c{k}.h5"
        path.write_bytes(bytes(b))
        try:
            run = capture.read_run(path)
        except InputError as exc:
            assert "\n" not in str(exc) and str(path) in str(exc)
            outcome["rejected"] += 1
            continue
        # accepted: bytes outside the data and metadata (HDF5 slack) were hit
        assert run.signals.keys() == ref.signals.keys()
        for name in ref.signals:
            np.testing.assert_array_equal(run.signals[name], ref.signals[name])
        assert {k: v for k, v in run.meta.items() if k != "path"} == \
            {k: v for k, v in ref.meta.items() if k != "path"}
        outcome["identical"] += 1
    assert outcome["rejected"] >= 150, outcome
    print(f"capture corruptions: {outcome}")


@pytest.mark.parametrize("case", ["truncated_half", "truncated_header", "empty", "flipped_data",
                                  "text_file", "directory"])
def test_bad_capture_file_on_the_command_line(good_capture, tmp_path, case, capsys):
    raw = open(good_capture, "rb").read()
    path = tmp_path / "bad.h5"
    if case == "truncated_half":
        path.write_bytes(raw[:len(raw) // 2])
    elif case == "truncated_header":
        path.write_bytes(raw[:40])
    elif case == "empty":
        path.write_bytes(b"")
    elif case == "flipped_data":
        b = bytearray(raw)
        for off in range(len(b) - 600, len(b) - 580):  # inside the last dataset's values
            b[off] ^= 0x5A
        path.write_bytes(bytes(b))
    elif case == "text_file":
        path.write_text("time,u,y\n0,1,2\n")
    elif case == "directory":
        path.mkdir()
    out = tmp_path / "exported"
    res = _fftune(["export", str(path), "--format", "csv", "--to", str(out)], capsys)
    _assert_clear_error(res, ["bad.h5"])
    assert not out.exists() or not os.listdir(out), "something was written from a bad capture"
    res = _fftune(["analyze", "bla", str(path), "--json", str(tmp_path / "r.json")], capsys)
    _assert_clear_error(res, ["bad.h5"])
    assert not (tmp_path / "r.json").exists()


# ---- CAN logs --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def session_log(tmp_path_factory):
    """A candump log of a short live session (a second python-can client on the bus)."""
    if not os.path.exists(EDS):
        pytest.skip("firmware_sim/build/gen/fftune_drive.eds not generated")
    import can
    from fftune.host.drive import BusOptions, DriveClient, quiet_can_loggers

    quiet_can_loggers()
    d = tmp_path_factory.mktemp("canlog")
    drive = start_drive(d)
    path = str(d / "session.log")
    bus = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=drive.port)
    logger = can.Logger(path)
    stop = threading.Event()

    def pump():
        while not stop.is_set():
            msg = bus.recv(0.05)
            if msg is not None:
                logger.on_message_received(msg)

    t = threading.Thread(target=pump, daemon=True)
    t.start()
    try:
        with DriveClient(BusOptions(port=drive.port, eds=EDS), heartbeat_ms=250, progress=False) as cli:
            cli.enable()
            cli.run(dict(exc_kind=1, exc_amplitude=0.2, exc_period=256, exc_settle_periods=0,
                         exc_record_periods=2), signals=("reference", "plant_input", "motor_angle"))
    finally:
        import time
        time.sleep(0.3)
        stop.set()
        t.join(2)
        logger.stop()
        bus.shutdown()
        drive.stop()
    assert os.path.getsize(path) > 10000
    return path


def _cut_mid_transfer(lines):
    """Lines up to the middle of the recorder upload (block upload of 0x2021)."""
    starts = [i for i, ln in enumerate(lines) if "#A4212000" in ln.upper().replace(" ", "")]
    assert starts, "no block upload of 0x2021 in the log"
    return lines[:starts[-1] + 60]


@needs_drive
@pytest.mark.parametrize("case", ["cut_mid_upload", "cut_mid_line", "garbage_lines", "random_bytes",
                                  "empty", "random_blf", "unknown_suffix", "missing"])
def test_bad_can_logs_on_the_command_line(session_log, tmp_path, case, capsys):
    lines = open(session_log).read().splitlines(keepends=True)
    rng = random.Random(len(case))
    name = "bad.log"
    data = None
    if case == "cut_mid_upload":
        data = "".join(_cut_mid_transfer(lines))
    elif case == "cut_mid_line":
        text = "".join(_cut_mid_transfer(lines))
        data = text[:-7]
    elif case == "garbage_lines":
        data = "".join(ln if rng.random() > 0.05 else "(12x.5) can0 7GG#ZZ\n" for ln in lines)
    elif case == "random_bytes":
        data = bytes(rng.getrandbits(8) for _ in range(20000))
    elif case == "empty":
        data = ""
    elif case == "random_blf":
        name = "bad.blf"
        data = b"LOGG" + bytes(rng.getrandbits(8) for _ in range(5000))
    elif case == "unknown_suffix":
        name = "bad.xyz"
        data = "".join(lines)
    path = tmp_path / name
    if data is not None:
        (path.write_bytes if isinstance(data, bytes) else path.write_text)(data)
    out = tmp_path / "out"
    res = _fftune(["import-canlog", str(path), "--eds", EDS, "--steps", "detect", "--out", str(out),
                   "--no-progress", "--no-figures"], capsys)
    _assert_clear_error(res, [name])


# ---- configs -----------------------------------------------------------------------------

BAD_CONFIGS = {
    "yaml_syntax": "detect: [1, 2\n",
    "not_a_mapping": "- 1\n- 2\n",
    "wrong_type": None,  # the demo config with a string where a number belongs
    "unknown_key": None,
    "negative_level": None,
    "binary": b"\x00\xff\xfe" * 100,
}


@pytest.mark.parametrize("case", sorted(BAD_CONFIGS) + ["missing", "directory"])
def test_malformed_configs_on_the_command_line(tmp_path, case, capsys):
    import yaml

    path = tmp_path / "bad.yaml"
    demo = yaml.safe_load(open(os.path.join(REPO, "configs", "demo.yaml")))
    if case == "wrong_type":
        demo["detect"]["period_samples"] = "lots"
        path.write_text(yaml.safe_dump(demo))
    elif case == "unknown_key":
        demo["detect"]["periodz"] = 3
        path.write_text(yaml.safe_dump(demo))
    elif case == "negative_level":
        demo["detect"]["rms_levels"] = [-1.0]
        path.write_text(yaml.safe_dump(demo))
    elif case == "directory":
        path.mkdir()
    elif case != "missing":
        data = BAD_CONFIGS[case]
        (path.write_bytes if isinstance(data, bytes) else path.write_text)(data)
    out = tmp_path / "out"
    # port 9: nothing listens there; the config must be refused before any connection
    res = _fftune(["detect", "--config", str(path), "--out", str(out), "--port", "9",
                   "--no-progress", "--no-figures"], capsys)
    _assert_clear_error(res, ["bad.yaml"])
    assert not out.exists(), "output directory created for a bad config"
