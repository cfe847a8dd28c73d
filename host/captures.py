"""Capture files of a session: one HDF5 file per run, in the format of :mod:`fftune.analysis.capture`.

:class:`CaptureStore` names each run's file after its key (``captures/<key>.h5``), writes
it as soon as the run arrives (the format's writer is atomic and never overwrites) with
the metadata the brief asks for, and finds it again on resume: a run whose file exists
with the same request is loaded instead of measured; a file with a different request
stops the session (another configuration wrote into this directory).
"""
import contextlib
import datetime
import glob
import json
import os
import shutil

import numpy as np

from fftune.analysis import capture as _capture
from fftune.analysis.errors import FftuneError
from fftune.analysis.stats import HarmonicStats, LineStats
from fftune.host import __version__
from fftune.host.atomic import write_atomic
from fftune.host.drive import RunRecord

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
        # made with the first capture: a session that fails before its first experiment
        # leaves no directory behind
        self.dir = os.path.join(out_dir, "captures")

    def path(self, key):
        return os.path.join(self.dir, f"{key}.h5")

    def stats_path(self, key):
        """The on-drive statistics of run ``key`` (JSON, beside or instead of the .h5)."""
        return os.path.join(self.dir, f"{key}.stats.json")

    def load(self, key, request):
        """The RunRecord captured under ``key`` with ``request``, or None if not captured.
        Raw samples and/or the drive's statistics, as captured."""
        path, spath = self.path(key), self.stats_path(key)
        rec = None
        if os.path.exists(path):
            run = _capture.read_run(path)
            if not _same_request(run.meta.get("metadata", {}).get("request", {}), _jsonable(request)):
                raise FftuneError(f"{path}: captured with other parameters than this session asks "
                                  f"for (another configuration?); use another --out or remove the file")
            rec = record_from_capture(run)
        if os.path.exists(spath):
            srec = _load_stats(spath, request)
            if rec is None:
                rec = srec
            else:
                rec.stats, rec.line_stats = srec.stats, srec.line_stats
        return rec

    def save(self, key, rec, *, experiment, request, config, identity, level_index=0,
             realization=0):
        os.makedirs(self.dir, exist_ok=True)
        ident_text = json.dumps({k: identity.get(k) for k in
                                 ("vendor_id", "product_code", "revision", "serial", "device_name")},
                                sort_keys=True)
        meta = {
            "experiment": experiment,
            "fs_hz": float(rec.fs_hz),
            "n_period": int(rec.period_samples),
            # The drive records only the record periods; its settle periods are in
            # parameters['exc_settle_periods'].
            "settle_periods": 0,
            "record_periods": int(rec.record_periods),
            "level_index": int(level_index),
            "realization": int(realization),
            "parameters": _jsonable(rec.parameters),
            "firmware_version": str(identity.get("firmware_version", "")),
            "eds_identity": ident_text,
            "started_at": _iso(rec.t_start),
            "finished_at": _iso(rec.t_end),
            "metadata": {
                "fftune_version": __version__,
                "key": key,
                "request": _jsonable(request),
                "identity": _jsonable(identity),
                "run_counter": int(rec.run_counter),
                "drive_settle_periods": int(rec.settle_periods),
                "config": _jsonable({k: v for k, v in config.items() if k != "_source"}),
                "config_file": config.get("_source"),
                "layout": LAYOUT,
            },
        }
        line_stats = getattr(rec, "line_stats", None)
        if rec.stats is not None or line_stats is not None:
            doc = {"format": "fftune-stats", "version": 1, "meta": _jsonable(meta),
                   "stats": None if rec.stats is None else rec.stats.to_dict(),
                   "line_stats": None if line_stats is None else line_stats.to_dict()}
            try:
                write_atomic(self.stats_path(key), json.dumps(doc, indent=1), overwrite=False)
            except FileExistsError:
                raise FftuneError(f"{self.stats_path(key)}: exists; captures are never overwritten") from None
        if not rec.signals:
            return  # statistics only (capture: stats)
        try:
            _capture.write_run(self.path(key), rec.signals, meta)
        except FileExistsError:
            raise FftuneError(f"{self.path(key)}: exists; captures are never overwritten") from None


# A statistics capture holds a few lines per harmonic or excited line: kB, at most a few MB.
MAX_STATS_BYTES = 64 << 20


def read_stats_document(path):
    """The JSON document of a ``.stats.json`` capture, read through the one loader of user
    files (:func:`fftune.host.config.read_text`: a regular file of at most MAX_STATS_BYTES,
    UTF-8; a FIFO or device under the name is refused, not waited on); one FftuneError line
    naming the file otherwise. Every reader of statistics captures goes through here."""
    from fftune.host.config import read_text

    text = read_text(path, "statistics capture", max_bytes=MAX_STATS_BYTES)
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise FftuneError(f"{path}: not a readable statistics capture ({type(exc).__name__}: "
                          f"{str(exc)[:120]})") from None
    if not isinstance(doc, dict):
        raise FftuneError(f"{path}: not a readable statistics capture (a JSON "
                          f"{type(doc).__name__}, expected an object)")
    return doc


def _load_stats(path, request):
    """A RunRecord without samples from a ``.stats.json`` capture (:func:`read_stats_document`)."""
    doc = read_stats_document(path)
    try:
        meta = doc["meta"]
        stats = None if doc["stats"] is None else HarmonicStats.from_dict(doc["stats"])
        lines = doc.get("line_stats")
        line_stats = None if lines is None else LineStats.from_dict(lines)
        if stats is None and line_stats is None:
            raise ValueError("neither harmonic nor line statistics in it")
    except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError) as exc:
        raise FftuneError(f"{path}: not a readable statistics capture ({type(exc).__name__}: "
                          f"{str(exc)[:120]})") from None
    try:
        extra = meta.get("metadata", {})
        same = _same_request(extra.get("request", {}), _jsonable(request))
    except (AttributeError, TypeError) as exc:
        raise FftuneError(f"{path}: not a readable statistics capture (its metadata: {exc})") from None
    if not same:
        raise FftuneError(f"{path}: captured with other parameters than this session asks "
                          f"for (another configuration?); use another --out or remove the file")

    def ts(s):
        return datetime.datetime.fromisoformat(s).timestamp() if s else 0.0
    try:
        return RunRecord(signals={}, parameters=meta.get("parameters", {}), fs_hz=float(meta["fs_hz"]),
                         period_samples=int(meta["n_period"]),
                         settle_periods=int(extra.get("drive_settle_periods", 0)),
                         record_periods=int(meta["record_periods"]),
                         run_counter=int(extra.get("run_counter", 0)),
                         t_start=ts(meta.get("started_at")), t_end=ts(meta.get("finished_at")), meta=meta,
                         stats=stats, line_stats=line_stats)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise FftuneError(f"{path}: not a readable statistics capture (its metadata: "
                          f"{type(exc).__name__}: {str(exc)[:120]})") from None


def _iso(t):
    return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).isoformat(timespec="milliseconds")


def record_from_capture(run):
    """A :class:`fftune.host.drive.RunRecord` from a :class:`fftune.analysis.capture.CaptureRun`."""
    meta = run.meta
    extra = meta.get("metadata", {})

    def ts(s):
        return datetime.datetime.fromisoformat(s).timestamp() if s else 0.0
    return RunRecord(signals={k: np.asarray(v, dtype=np.float64) for k, v in run.signals.items()},
                     parameters=meta.get("parameters", {}), fs_hz=float(meta["fs_hz"]),
                     period_samples=int(meta["n_period"]),
                     settle_periods=int(extra.get("drive_settle_periods", 0)),
                     record_periods=int(meta["record_periods"]),
                     run_counter=int(extra.get("run_counter", 0)),
                     t_start=ts(meta.get("started_at")), t_end=ts(meta.get("finished_at")), meta=meta)


def export_captures(source, fmt, to_dir=None):
    """Export capture file(s) with :func:`fftune.analysis.capture.export_mat` / ``export_csv``
    (one file per run, never overwriting); returns the files written."""
    if os.path.isdir(source):
        files = [str(p) for p in _capture.list_runs(source)]
        if not files:
            raise FftuneError(f"{source}: no capture files (*.h5)")
    elif os.path.exists(source):
        files = [source]
    else:
        raise FftuneError(f"{source}: no such capture file or directory")
    if to_dir is not None:
        from fftune.host.config import check_output_dir
        check_output_dir(to_dir, create=False)      # (a file in the way: one line, nothing made)
    out, made = [], []
    try:
        for f in files:
            base = os.path.splitext(os.path.basename(f))[0]
            d = to_dir or os.path.dirname(os.path.abspath(f))
            if not os.path.isdir(d):
                top = os.path.abspath(d)            # the highest folder made here
                while not os.path.exists(os.path.dirname(top)):
                    top = os.path.dirname(top)
                made.append(top)
                os.makedirs(d, exist_ok=True)
            target = os.path.join(d, f"{base}.{fmt}")
            try:
                if fmt == "mat":
                    _capture.export_mat(f, target)
                else:
                    _capture.export_csv(f, target)
            except FileExistsError:
                raise FftuneError(f"{target}: exists; exports are never overwritten") from None
            out.append(str(target))
    except BaseException:
        # a refused capture: the exports of this call removed again, and the folders it made
        # (all or nothing: a directory of captures is exported whole or not at all)
        for target in out:
            with contextlib.suppress(OSError):
                os.remove(target)
        for top in made:
            shutil.rmtree(top, ignore_errors=True)
        raise
    return out
