"""`fftune import-canlog` bad input: one error line, exit 2 (the round trip of a live
session is in tests/test_host_drive_sim.py)."""
import os

import can
import pytest

from fftune.host.cli import main
from host_fixtures import EDS


def test_missing_log_is_named(tmp_path, capsys):
    assert main(["import-canlog", str(tmp_path / "none.log"), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip().endswith("none.log: no such CAN log")


def test_unknown_log_format_is_named(tmp_path, capsys):
    f = tmp_path / "session.xyz"
    f.write_text("hello\n")
    assert main(["import-canlog", str(f), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "session.xyz: not a CAN log format python-can reads" in err and "Traceback" not in err


@pytest.mark.skipif(not os.path.exists(EDS), reason=f"EDS not generated ({EDS} missing; make setup)")
def test_log_without_runs_is_refused(tmp_path, capsys):
    f = tmp_path / "idle.log"
    with can.Logger(str(f)) as log:
        log(can.Message(arbitration_id=0x701, data=[0x05], is_extended_id=False, timestamp=1.0))
        log(can.Message(arbitration_id=0x601, data=[0x40, 0x00, 0x10, 0, 0, 0, 0, 0],
                        is_extended_id=False, timestamp=1.1))
        log(can.Message(arbitration_id=0x581, data=[0x43, 0x00, 0x10, 0, 0x92, 0x01, 0x02, 0],
                        is_extended_id=False, timestamp=1.2))
    assert main(["import-canlog", str(f), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "idle.log: no complete run (start command + recorder upload) of node 1" in err
    assert "(1 SDO transfers)" in err


@pytest.mark.skipif(not os.path.exists(EDS), reason=f"EDS not generated ({EDS} missing; make setup)")
def test_log_of_a_statistics_session_says_why_it_cannot_be_replayed(tmp_path, capsys):
    """A session on the drive's statistics uploads 0x2043 / 0x2041, not recordings: the
    error says so and where the analysis is."""
    f = tmp_path / "stats.log"
    with can.Logger(str(f)) as log:
        log(can.Message(arbitration_id=0x601, data=[0x40, 0x43, 0x20, 0, 0, 0, 0, 0],
                        is_extended_id=False, timestamp=1.1))
        log(can.Message(arbitration_id=0x581, data=[0x43, 0x43, 0x20, 0, 0x02, 0, 0, 0],
                        is_extended_id=False, timestamp=1.2))
    assert main(["import-canlog", str(f), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "1 uploads of the drive's statistics 0x2041/0x2043" in err[0]
    assert "results.yaml holds the analysis" in err[0]
