"""Capture files of a session: one HDF5 file per run, in the format of :mod:`analysis.capture`.

:class:`CaptureStore` names each run's file after its key (``captures/<key>.h5``), writes
it as soon as the run arrives (the format's writer is atomic and never overwrites) with
the metadata the brief asks for, and finds it again on resume: a run whose file exists
with the same request is loaded instead of measured; a file with a different request
stops the session (another configuration wrote into this directory).
"""
import datetime
import glob
import json
import os

import numpy as np

from analysis import capture as _capture
from analysis.errors import FftuneError
from host import __version__
from host.drive import RunRecord

LAYOUT = ("one float32 value per sample from the drive's recorder, stored as float64; "
          "record_periods x period_samples samples per signal after settle_periods "
          "(not recorded)")


def _jsonable(x):
    """A JSON-serialisable copy (numpy scalars and arrays to Python)."""
    return json.loads(json.dumps(x, default=lambda o: o.item() if hasattr(o, "item") and np.ndim(o) == 0
                                 else o.tolist() if hasattr(o, "tolist") else str(o)))


def _same_request(a, b):
    if set(a) != set(b):
        return False
    for k in a:
        x, y = a[k], b[k]
        if isinstance(x, (int, float)) and isinstance(y, (int, float)):
            if np.float32(x) != np.float32(y):
                return False
        elif x != y:
            return False
    return True


class CaptureStore:
    """The ``captures/`` directory of an output directory."""

    def __init__(self, out_dir):
        self.dir = os.path.join(out_dir, "captures")
        os.makedirs(self.dir, exist_ok=True)

    def path(self, key):
        return os.path.join(self.dir, f"{key}.h5")

    def load(self, key, request):
        """The RunRecord captured under ``key`` with ``request``, or None if not captured."""
        path = self.path(key)
        if not os.path.exists(path):
            return None
        run = _capture.read_run(path)
        meta = run.meta
        if not _same_request(meta.get("request", {}), _jsonable(request)):
            raise FftuneError(f"{path}: captured with other parameters than this session asks "
                              f"for (another configuration?); use another --out or remove the file")
        return record_from_capture(run)

    def save(self, key, rec, *, experiment, request, config, identity):
        meta = {
            "fftune_version": __version__,
            "experiment": experiment,
            "key": key,
            "request": _jsonable(request),
            "drive_parameters": _jsonable(rec.parameters),
            "identity": _jsonable(identity),
            "firmware_version": identity.get("firmware_version"),
            "config": _jsonable({k: v for k, v in config.items() if k != "_source"}),
            "config_file": config.get("_source"),
            "t_start": datetime.datetime.fromtimestamp(rec.t_start).isoformat(timespec="milliseconds"),
            "t_end": datetime.datetime.fromtimestamp(rec.t_end).isoformat(timespec="milliseconds"),
            "run_counter": int(rec.run_counter),
            "fs_hz": float(rec.fs_hz),
            "period_samples": int(rec.period_samples),
            "settle_periods": int(rec.settle_periods),
            "record_periods": int(rec.record_periods),
            "signals": list(rec.signals),
            "layout": LAYOUT,
        }
        try:
            _capture.write_run(self.path(key), rec.signals, fs=rec.fs_hz, meta=meta)
        except FileExistsError:
            raise FftuneError(f"{self.path(key)}: exists; captures are never overwritten") from None


def record_from_capture(run):
    """A :class:`host.drive.RunRecord` from a capture read by :func:`analysis.capture.read_run`."""
    meta = run.meta

    def ts(s):
        return datetime.datetime.fromisoformat(s).timestamp()
    return RunRecord(signals={k: np.asarray(v, dtype=np.float64) for k, v in run.signals.items()},
                     parameters=meta.get("drive_parameters", {}), fs_hz=float(meta["fs_hz"]),
                     period_samples=int(meta["period_samples"]),
                     settle_periods=int(meta["settle_periods"]),
                     record_periods=int(meta["record_periods"]), run_counter=int(meta["run_counter"]),
                     t_start=ts(meta["t_start"]), t_end=ts(meta["t_end"]), meta=meta)


def export_captures(source, fmt, to_dir=None):
    """Export capture file(s) to ``.mat`` (scipy.io) or ``.csv``; returns the files written."""
    import scipy.io
    from host.atomic import write_atomic

    if os.path.isdir(source):
        files = sorted(glob.glob(os.path.join(source, "*.h5")))
        if not files:
            raise FftuneError(f"{source}: no capture files (*.h5)")
    elif os.path.exists(source):
        files = [source]
    else:
        raise FftuneError(f"{source}: no such capture file or directory")
    out = []
    for f in files:
        run = _capture.read_run(f)
        base = os.path.splitext(os.path.basename(f))[0]
        d = to_dir or os.path.dirname(os.path.abspath(f))
        os.makedirs(d, exist_ok=True)
        names = list(run.signals)
        if fmt == "mat":
            target = os.path.join(d, base + ".mat")
            tmp = os.path.join(d, f".tmp-{base}.mat")
            mdict = {n: np.asarray(run.signals[n]) for n in names}
            mdict["fs_hz"] = float(run.meta.get("fs_hz", np.nan))
            mdict["metadata_json"] = json.dumps(run.meta)
            scipy.io.savemat(tmp, mdict, do_compression=True)
            os.replace(tmp, target)
        else:
            target = os.path.join(d, base + ".csv")
            fs = float(run.meta.get("fs_hz", 1.0))
            n = len(run.signals[names[0]])
            cols = [np.arange(n) / fs] + [np.asarray(run.signals[k]) for k in names]
            lines = ["time_s," + ",".join(names)]
            arr = np.column_stack(cols)
            lines += [",".join(f"{v:.9g}" for v in row) for row in arr]
            write_atomic(target, "\n".join(lines) + "\n")
        out.append(target)
    return out
