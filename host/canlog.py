"""Offline CAN logs: from a recorded session with the drive back to run records.

A CAN traffic log written by common tools (python-can's formats through
:class:`can.LogReader`: candump ``.log``, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ``.db``)
is decoded into SDO transfers (:mod:`fftune.host.sdo_sniffer`), and those into the same
:class:`fftune.host.drive.RunRecord` objects a live session produces: the parameter writes up to a
run's start command, the parameters read back after it, and the recorder data uploaded.

:class:`ReplayDrive` serves those runs through the drive-client interface, so the very
experiment code of a live session (``fftune.host.experiments``) analyses a log and reaches the
live result (same recorded bytes, same computation).
"""
import math
import os
from dataclasses import dataclass, field

import numpy as np

from fftune.analysis.errors import FftuneError
from fftune.host.config import MAX_CANLOG_BYTES, MAX_EDS_BYTES, regular_file
from fftune.host.drive import RunRecord
from fftune.host.odmap import PARAMS, SIGNAL_BITS
from fftune.host.sdo_sniffer import SdoSniffer

_BY_OBJ = {(e.index, e.subindex): a for a, e in PARAMS.items()}
_RECORDER_DATA = (0x2021, 0)


def read_transfers(path, node_id=1):
    """SDO transfers of ``node_id`` in the CAN log ``path`` (any python-can log format)."""
    import can

    if not os.path.lexists(path):
        raise FftuneError(f"{path}: no such CAN log")
    regular_file(path, "CAN log", MAX_CANLOG_BYTES)      # (a FIFO would wait for a writer)
    sniffer = SdoSniffer([node_id])
    n_frames = 0
    try:
        reader = can.LogReader(path)
    except (ValueError, NotImplementedError) as exc:
        raise FftuneError(f"{path}: not a CAN log format python-can reads "
                          f"(.log, .asc, .blf, .trc, .csv, .db): {exc}") from None
    try:
        for msg in reader:
            if msg.is_error_frame or msg.is_remote_frame:
                continue
            n_frames += 1
            if not math.isfinite(msg.timestamp):
                raise FftuneError(f"{path}: frame {n_frames}: timestamp {msg.timestamp!r} is not a "
                                  f"finite number")
            sniffer.feed(msg.arbitration_id, msg.data, msg.timestamp)
    except FftuneError:
        raise
    except Exception as exc:  # the reader's own parse errors
        raise FftuneError(f"{path}: cannot decode the CAN log after {n_frames} frames: "
                          f"{type(exc).__name__}: {exc}") from None
    finally:
        stop = getattr(reader, "stop", None)
        if stop:
            stop()
    if n_frames == 0:
        raise FftuneError(f"{path}: no CAN data frames in the log")
    if sniffer.problems:
        raise FftuneError(f"{path}: {sniffer.problems[0]}")
    return sniffer.transfers


def _decode(od, index, sub, data):
    try:
        obj = od[index]
        var = obj[sub] if hasattr(obj, "subindices") else obj
    except KeyError:
        return None
    try:
        return var.decode_raw(data)
    except Exception:
        return None


@dataclass
class LoggedSession:
    """Everything a log tells about one drive session."""

    runs: list                      # of (requested: dict, RunRecord)
    identity: dict = field(default_factory=dict)
    truth: dict = field(default_factory=dict)
    writes: int = 0
    aborts: list = field(default_factory=list)


def session_from_transfers(transfers, eds_path, node_id=1):
    """Reassemble runs: writes before a start command, readback and recorder upload after."""
    import canopen

    if eds_path and os.path.exists(eds_path):
        regular_file(eds_path, "EDS", MAX_EDS_BYTES)
    try:
        od = canopen.import_od(eds_path, node_id)
    except FileNotFoundError:
        raise FftuneError(f"EDS not found: {eds_path}") from None
    except Exception as exc:
        raise FftuneError(f"EDS {eds_path}: cannot import: {exc}") from None
    sess = LoggedSession(runs=[])
    state = {}        # alias -> last value written or read
    requested = {}    # alias -> value written since the previous run
    started = None    # (requested, state at start, t)
    for tr in transfers:
        try:
            started, requested = _replay_transfer(sess, od, tr, state, requested, started)
        except FftuneError:
            raise
        except (TypeError, ValueError, KeyError, OverflowError) as exc:
            # a value the drive never sends (a forged or damaged log): one line naming it
            raise FftuneError(f"logged SDO {tr.direction} of 0x{tr.index:04X}:{tr.subindex} at "
                              f"t={tr.timestamp:.3f}: cannot be replayed ({type(exc).__name__}: "
                              f"{str(exc)[:80]})") from None
    return sess


def _replay_transfer(sess, od, tr, state, requested, started):
    """One logged transfer into ``sess`` / ``state``; returns (started, requested)."""
    if tr.abort_code is not None:
        sess.aborts.append(tr)
        return started, requested
    key = (tr.index, tr.subindex)
    value = _decode(od, tr.index, tr.subindex, tr.data) if key != _RECORDER_DATA else None
    alias = _BY_OBJ.get(key)
    if tr.direction == "upload":
        if key == (0x1018, 1):
            sess.identity["vendor_id"] = int(value)
        elif key == (0x1018, 2):
            sess.identity["product_code"] = int(value)
        elif key == (0x1018, 3):
            sess.identity["revision"] = int(value)
        elif key == (0x1018, 4):
            sess.identity["serial"] = int(value)
        elif key == (0x100A, 0):
            sess.identity["firmware_version"] = str(value)
        elif key == (0x1008, 0):
            sess.identity["device_name"] = str(value)
        elif alias and alias.startswith("sim_"):
            sess.truth[alias] = float(value)
        elif alias:
            state[alias] = value
        if key == _RECORDER_DATA and started is not None:
            req, t_start = started
            sess.runs.append((req, _record(tr, state, t_start)))
            started = None
        return started, requested
    # download
    if alias is None:
        return started, requested
    sess.writes += 1
    if alias == "run_command":
        if int(value) == 1:
            started = (dict(requested), tr.timestamp)
            requested = {}
        return started, requested
    state[alias] = value
    requested[alias] = value
    return started, requested


def _record(tr, state, t_start):
    where = f"logged recorder upload at t={tr.timestamp:.3f}"
    for alias in ("exc_period", "exc_record_periods", "exc_settle_periods"):
        if alias not in state:
            raise FftuneError(f"{where}: the log holds no {alias} of the run (a session cut short?)")
    mask = int(state.get("rec_signals", 0x07))
    order = [n for n, b in sorted(SIGNAL_BITS.items(), key=lambda kv: kv[1]) if mask >> b & 1]
    n = int(state["exc_period"])
    rec_periods = int(state["exc_record_periods"])
    fs = float(state.get("fs", 0.0))
    if not order or n < 1 or rec_periods < 1 or not (math.isfinite(fs) and fs >= 0):
        raise FftuneError(f"{where}: signals mask {mask}, period {n}, {rec_periods} record periods, "
                          f"fs {fs!r}: not a run the drive makes")
    expected = rec_periods * n * len(order) * 4
    if len(tr.data) != expected:
        raise FftuneError(f"logged recorder upload at t={tr.timestamp:.3f}: {len(tr.data)} bytes, "
                          f"expected {rec_periods * n} samples x {len(order)} signals x 4 = {expected}")
    arr = np.frombuffer(tr.data, dtype="<f4").reshape(rec_periods * n, len(order))
    bad = np.argwhere(~np.isfinite(arr))
    if bad.size:        # (the drive stops a run on a non-finite measurement: never uploaded)
        raise FftuneError(f"{where}: signal {order[bad[0][1]]} sample {int(bad[0][0])} is "
                          f"{arr[bad[0][0], bad[0][1]]}: not a finite number")
    params = {a: v for a, v in state.items()}
    return RunRecord(signals={s: arr[:, i].astype(np.float64) for i, s in enumerate(order)},
                     parameters=params, fs_hz=float(state.get("fs", 0.0)), period_samples=n,
                     settle_periods=int(state["exc_settle_periods"]), record_periods=rec_periods,
                     run_counter=int(state.get("run_counter", 0)), t_start=t_start, t_end=tr.timestamp)


def _same(a, b):
    if isinstance(a, float) or isinstance(b, float):
        return np.float32(a) == np.float32(b)
    return int(a) == int(b)


class ReplayDrive:
    """The drive-client interface over the runs of a logged session.

    ``run(parameters)`` returns the next logged run whose state at its start matches every
    requested parameter (float32 comparison: what went over the bus). Parameters not
    requested explicitly are not compared.
    """

    def __init__(self, session, source):
        self.session = session
        self.source = source
        self.used = set()
        self.current = {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        pass

    def close(self):
        pass

    def enable(self):
        pass

    def identity(self):
        return dict(self.session.identity, bus=f"CAN log {self.source}")

    def plant_truth(self):
        return dict(self.session.truth) or None

    def set_parameters(self, values):
        self.current.update(values)

    def set(self, name, value):
        self.current[name] = value

    def get(self, name):
        if name in self.current:
            return self.current[name]
        for _, rec in self.session.runs:
            if name in rec.parameters:
                return rec.parameters[name]
        raise FftuneError(f"{self.source}: parameter '{name}' never appears in the log")

    def read_parameters(self):
        return dict(self.current)

    def run(self, parameters, signals=None, desc="run"):
        want = dict(self.current)
        want.update(parameters)
        for i, (_, rec) in enumerate(self.session.runs):
            if i in self.used:
                continue
            if all(k in rec.parameters and _same(rec.parameters[k], v) for k, v in want.items()
                   if k in PARAMS):
                self.used.add(i)
                self.current.update(parameters)
                return rec
        shown = ", ".join(f"{k}={v}" for k, v in sorted(parameters.items()))
        raise FftuneError(f"{self.source}: no logged run with {shown} "
                          f"({len(self.session.runs)} runs in the log, {len(self.used)} matched; "
                          "give the configuration and --steps the session used)")
