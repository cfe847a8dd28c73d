"""Capture files: one HDF5 file per experiment run (format in docs/capture-format.md).

The host writes them (:func:`write_run`) while it runs experiments; ``fftune analyze``
and :func:`load_experiment` read them back. Writing is atomic (temporary file in the
same directory, then a no-clobber rename); an existing file is never overwritten.
"""
import csv
import datetime as _dt
import hashlib
import io as _io
import json
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fftune.analysis.errors import FftuneError, InputError, OutputExistsError

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "STANDARD_SIGNALS", "REQUIRED_META",
           "CaptureRun", "ExperimentData", "write_run", "read_run", "list_runs",
           "load_experiment", "export_mat", "export_csv", "atomic_write", "matlab_name",
           "SIGNAL_UNITS"]

FORMAT_NAME = "fftune-capture"
FORMAT_VERSION = 2  # 2 = 1 + the checksum user block (1 is still read)
STANDARD_SIGNALS = ("reference", "plant_input", "motor_angle", "load_angle", "error")
REQUIRED_META = ("fs_hz", "n_period", "settle_periods", "record_periods", "experiment")
_INT_META = ("n_period", "settle_periods", "record_periods", "level_index", "realization")
_STR_META = ("experiment", "firmware_version", "eds_identity", "started_at", "finished_at")
_JSON_META = ("parameters", "metadata")
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


def _now_iso():
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path, write, *, overwrite=False, suffix=".tmp"):
    """Write ``path`` atomically: ``write(tmp_path)`` then rename into place.

    Parameters
    ----------
    path : str or Path
    write : callable
        Called with the temporary path (same directory) to produce the content.
    overwrite : bool
        If False (default) an existing ``path`` is an error and is left untouched; the
        final step is a hard link (fails if the name exists) so a file appearing
        meanwhile is not clobbered either. If True, ``os.replace``.

    Raises
    ------
    FftuneError
        The file exists (and overwrite is False) or cannot be written.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise OutputExistsError(f"{path}: file exists (refusing to overwrite)")
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise FftuneError(f"{path}: directory {directory} does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=directory)
    except OSError as exc:
        raise FftuneError(f"{path}: cannot write in {directory} ({exc.strerror or exc})") from None
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())         # mkstemp makes 0600; give the usual mode
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise OutputExistsError(f"{path}: file exists (refusing to overwrite)") from None
            except OSError:          # file system without hard links: check-then-replace
                if path.exists():
                    raise OutputExistsError(f"{path}: file exists (refusing to overwrite)") from None
                os.replace(tmp, path)
    except FftuneError:
        raise
    except OSError as exc:
        raise FftuneError(f"{path}: cannot write ({exc.strerror or exc})") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


@dataclass
class CaptureRun:
    """One capture file read back.

    Attributes
    ----------
    path : Path
    signals : dict of str -> ndarray (float32, 1-D)
        Each holds (settle_periods + record_periods) * n_period samples.
    meta : dict
        fs_hz, n_period, settle_periods, record_periods, experiment, level_index,
        realization, parameters (dict), firmware_version, eds_identity, started_at,
        finished_at, metadata (dict), format_version.
    """

    path: Path
    signals: dict
    meta: dict

    def periods(self, name):
        """Signal ``name`` shaped (settle_periods + record_periods, n_period)."""
        return self.signals[name].reshape(-1, self.meta["n_period"])


def _validate_meta(meta, where):
    missing = [k for k in REQUIRED_META if k not in meta]
    if missing:
        raise InputError(f"{where}: missing metadata {', '.join(missing)}")
    out = {}
    fs = meta["fs_hz"]
    if not isinstance(fs, (int, float, np.floating, np.integer)) or not np.isfinite(fs) or fs <= 0:
        raise InputError(f"{where}: fs_hz must be a positive number, got {fs!r}")
    out["fs_hz"] = float(fs)
    for key in _INT_META:
        value = meta.get(key, 0)
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
                or value < 0:
            raise InputError(f"{where}: {key} must be an integer >= 0, got {value!r}")
        out[key] = int(value)
    if out["n_period"] < 1 or out["record_periods"] < 1:
        raise InputError(f"{where}: n_period and record_periods must be >= 1")
    for key in _STR_META:
        value = meta.get(key, "")
        if not isinstance(value, str):
            raise InputError(f"{where}: {key} must be a string, got {type(value).__name__}")
        out[key] = value
    if not out["experiment"]:
        raise InputError(f"{where}: experiment (kind) must not be empty")
    for key in ("started_at", "finished_at"):
        if out[key]:
            try:
                _dt.datetime.fromisoformat(out[key])
            except ValueError:
                raise InputError(f"{where}: {key} {out[key]!r} is not an ISO 8601 time") from None
    for key in _JSON_META:
        value = meta.get(key, {})
        if not isinstance(value, dict):
            raise InputError(f"{where}: {key} must be a mapping (JSON object), got "
                             f"{type(value).__name__}")
        try:
            json.dumps(value)
        except (TypeError, ValueError, RecursionError) as exc:
            raise InputError(f"{where}: {key} is not JSON-serialisable ({exc})") from None
        out[key] = value
    unknown = set(meta) - set(out)
    if unknown:
        raise InputError(f"{where}: unknown metadata key(s) {', '.join(sorted(unknown))} "
                         f"(put free-form data under 'metadata')")
    return out


# Version 2 files start with a 512-byte HDF5 user block (HDF5 itself skips it) holding
# "fftune-capture 2 sha256=<hex>\n": the SHA-256 of everything after the block. It is checked
# BEFORE libhdf5 parses the file: a damaged file is refused with one clear line, instead of
# being read as other numbers (HDF5 keeps no checksum of its own) or making libhdf5 hang or
# crash on its damaged structures (one flipped byte in an attribute header is enough).
_USERBLOCK = 512
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_HEADER = re.compile(rb"fftune-capture (\d+) sha256=([0-9a-f]{64})\n\0*\Z")


def _sha256_after_userblock(fh):
    h = hashlib.sha256()
    fh.seek(_USERBLOCK)
    for chunk in iter(lambda: fh.read(1 << 20), b""):
        h.update(chunk)
    return h.hexdigest()


def _verify_file(path, where):
    """Check the user-block checksum of a version-2 file (version 1: nothing to check)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(_USERBLOCK)
            if head[:8] == _HDF5_SIGNATURE:
                return  # version 1: written without the checksum block
            m = _HEADER.match(head) if len(head) == _USERBLOCK else None
            if m is None:
                raise InputError(f"{where}: not an HDF5 capture file (or its header is damaged)")
            if _sha256_after_userblock(fh) != m.group(2).decode():
                raise InputError(f"{where}: checksum mismatch: the file was changed, truncated or "
                                 f"damaged after it was written")
    except OSError as exc:
        raise InputError(f"{where}: cannot read: {exc.strerror}") from None


def write_run(path, signals, meta):
    """Write one experiment run to a new HDF5 capture file, atomically.

    Parameters
    ----------
    path : str or Path
        Target file (``.h5``); must not exist.
    signals : dict of str -> array_like
        Recorded signals (standard names: reference, plant_input, motor_angle,
        load_angle, error; others allowed if lower-case identifiers), each 1-D with
        (settle_periods + record_periods) * n_period samples; stored as float32.
    meta : dict
        Required: fs_hz, n_period, settle_periods, record_periods, experiment.
        Optional: level_index, realization (int), firmware_version, eds_identity,
        started_at, finished_at (ISO 8601 strings; finished_at defaults to now),
        parameters (drive parameters read back, dict), metadata (free-form dict).

    Returns
    -------
    Path
    """
    import h5py

    path = Path(path)
    where = f"capture {path}"
    meta = dict(meta)
    meta.setdefault("finished_at", _now_iso())
    m = _validate_meta(meta, where)
    if not signals:
        raise InputError(f"{where}: no signal to write")
    n_samples = (m["settle_periods"] + m["record_periods"]) * m["n_period"]
    data = {}
    for name, values in signals.items():
        if not isinstance(name, str) or not _NAME.match(name):
            raise InputError(f"{where}: signal name {name!r} must be a lower-case identifier")
        arr = np.asarray(values)
        if arr.ndim != 1 or arr.size != n_samples:
            raise InputError(f"{where}: signal {name} has shape {arr.shape}, expected "
                             f"({n_samples},) = (settle_periods + record_periods) x n_period")
        if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
            raise InputError(f"{where}: signal {name} is not real numeric ({arr.dtype})")
        arr = arr.astype(np.float32)
        if not np.isfinite(arr).all():
            raise InputError(f"{where}: signal {name} contains NaN or inf (or overflows float32)")
        data[name] = arr

    def write(tmp):
        with h5py.File(tmp, "w", userblock_size=_USERBLOCK) as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["format_version"] = FORMAT_VERSION
            for key in ("fs_hz",) + _INT_META + _STR_META:
                f.attrs[key] = m[key]
            for key in _JSON_META:
                f.attrs[key] = json.dumps(m[key], sort_keys=True)
            for name, arr in data.items():
                f.create_dataset(name, data=arr)
        with open(tmp, "r+b") as fh:
            header = f"fftune-capture {FORMAT_VERSION} sha256={_sha256_after_userblock(fh)}\n".encode()
            fh.seek(0)
            fh.write(header.ljust(_USERBLOCK, b"\0"))

    return atomic_write(path, write, suffix=".h5.tmp")


def read_run(path):
    """Read a capture file written by :func:`write_run`.

    Returns
    -------
    CaptureRun

    Raises
    ------
    InputError
        Not a capture file, wrong version, missing or inconsistent attributes.
    """
    import h5py

    path = Path(path)
    where = f"capture {path}"
    if not path.is_file():
        raise InputError(f"{where}: no such file")
    _verify_file(path, where)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{where}: not an HDF5 file ({exc})") from None
    try:
        return _read_open(f, path, where)
    except InputError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
        # h5py on a damaged file (truncated, overwritten structures)
        raise InputError(f"{where}: damaged HDF5 file ({type(exc).__name__}: {exc})") from None
    finally:
        f.close()


# A signal holds at most this many samples: 64 MiB of float32 (a drive's recorder holds far
# fewer; settle periods are not recorded in full by any fftune step). Checked, with the
# dataset's shape, dtype and stored size, before a dataset is read: a forged file of a few kB
# may declare gigabytes.
MAX_CAPTURE_SAMPLES = 1 << 24
# ... and a file at most this many datasets (the recorder's 5 signals and a few more): a
# forged file of many compressed datasets, each within the limit, is refused before one is read.
MAX_CAPTURE_DATASETS = 16


def _check_dataset(ds, name, n_samples, file_bytes, where):
    """Shape, dtype and size of dataset ``ds`` as declared, checked without reading it."""
    shape = ds.shape
    if shape is None or len(shape) != 1 or shape[0] != n_samples:
        raise InputError(f"{where}: dataset {name} has shape {shape}, expected ({n_samples},)")
    dt = ds.dtype
    if dt.kind != "f" or dt.itemsize not in (4, 8):
        raise InputError(f"{where}: dataset {name} has dtype {dt}, expected float32 (or float64)")
    declared = n_samples * dt.itemsize
    if ds.compression is None and ds.id.get_storage_size() < declared:
        raise InputError(f"{where}: dataset {name} declares {declared} bytes, the file stores "
                         f"{ds.id.get_storage_size()} of them (damaged or forged)")
    if ds.compression is None and declared > file_bytes:
        raise InputError(f"{where}: dataset {name} declares {declared} bytes, more than the file's "
                         f"{file_bytes}")


def _read_open(f, path, where):
    import h5py

    with f:
        if f.attrs.get("format") != FORMAT_NAME:
            raise InputError(f"{where}: not an fftune capture file (attribute 'format' is "
                             f"{f.attrs.get('format')!r})")
        version = int(f.attrs.get("format_version", -1))
        if version not in (1, FORMAT_VERSION):
            raise InputError(f"{where}: format_version {version} not supported "
                             f"(this fftune reads 1 and {FORMAT_VERSION})")
        meta = {}
        for key in ("fs_hz",) + _INT_META + _STR_META:
            if key in f.attrs:
                value = f.attrs[key]
                meta[key] = value.item() if hasattr(value, "item") else value
                if isinstance(meta[key], bytes):
                    meta[key] = meta[key].decode()
        for key in _JSON_META:
            try:
                meta[key] = json.loads(f.attrs.get(key, "{}"))
            except (TypeError, ValueError, RecursionError):
                raise InputError(f"{where}: attribute {key} is not valid JSON") from None
        meta = _validate_meta(meta, where)
        meta["format_version"] = version
        n_samples = (meta["settle_periods"] + meta["record_periods"]) * meta["n_period"]
        if n_samples > MAX_CAPTURE_SAMPLES:
            raise InputError(f"{where}: declares {n_samples} samples a signal ((settle_periods + "
                             f"record_periods) x n_period), at most {MAX_CAPTURE_SAMPLES} "
                             f"(fftune.analysis.capture.MAX_CAPTURE_SAMPLES)")
        file_bytes = os.path.getsize(path)
        if len(f) > MAX_CAPTURE_DATASETS:
            raise InputError(f"{where}: {len(f)} datasets, at most {MAX_CAPTURE_DATASETS} "
                             f"(fftune.analysis.capture.MAX_CAPTURE_DATASETS)")
        signals = {}
        for name, ds in f.items():
            if not isinstance(ds, h5py.Dataset):
                continue
            _check_dataset(ds, name, n_samples, file_bytes, where)
            signals[name] = ds[()].astype(np.float32, copy=False)
    if not signals:
        raise InputError(f"{where}: holds no signal dataset")
    return CaptureRun(path=path, signals=signals, meta=meta)


def list_runs(directory):
    """Capture files (``*.h5``, ``*.hdf5``) in ``directory``, sorted by name."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(f"{directory}: not a directory")
    return sorted(p for p in directory.iterdir()
                  if p.suffix in (".h5", ".hdf5") and not p.name.startswith("."))


@dataclass
class ExperimentData:
    """The runs of one experiment (one kind, one level) assembled into arrays.

    Attributes
    ----------
    signals : dict of str -> ndarray, shape (M, T + P, N)
        Realizations (ordered by their ``realization`` index), periods, samples.
    fs_hz : float
    n_period, settle_periods, record_periods : int
    experiment : str
    level_index : int
    runs : list of CaptureRun
    """

    signals: dict
    fs_hz: float
    n_period: int
    settle_periods: int
    record_periods: int
    experiment: str
    level_index: int
    runs: list = field(default_factory=list)


def load_experiment(directory, *, experiment=None, level_index=None):
    """Assemble a directory of capture runs into (M, T + P, N) arrays.

    Parameters
    ----------
    directory : str or Path
    experiment : str, optional
        Keep only runs of this kind (required if the directory mixes kinds).
    level_index : int, optional
        Keep only runs of this level (required if the directory mixes levels).

    Returns
    -------
    ExperimentData

    Raises
    ------
    InputError
        No runs, mixed kinds/levels without a selection, inconsistent layout (fs,
        n_period, periods, signal names) or duplicate/missing realization indices;
        the message names the offending file.
    """
    runs = [read_run(p) for p in list_runs(directory)]
    if experiment is not None:
        runs = [r for r in runs if r.meta["experiment"] == experiment]
    if level_index is not None:
        runs = [r for r in runs if r.meta["level_index"] == level_index]
    if not runs:
        import glob
        import os
        n_stats = len(glob.glob(os.path.join(glob.escape(str(directory)), "*.stats.json")))
        raise InputError(f"{directory}: no capture run"
                         + (f" of experiment {experiment!r}" if experiment else "")
                         + (f" at level {level_index}" if level_index is not None else "")
                         + (f" with samples ({n_stats} statistics-only captures .stats.json: the "
                            f"session's results.yaml holds their analysis; samples need capture: "
                            f"raw or both)" if n_stats else ""))
    kinds = sorted({r.meta["experiment"] for r in runs})
    if len(kinds) > 1:
        raise InputError(f"{directory}: runs of several experiments ({', '.join(kinds)}): "
                         f"choose one with --experiment NAME (experiment= in the library)")
    levels = sorted({r.meta["level_index"] for r in runs})
    if len(levels) > 1:
        raise InputError(f"{directory}: runs at several levels ({levels}): choose one level "
                         f"with --level L (level_index= in the library)")
    runs.sort(key=lambda r: r.meta["realization"])
    first = runs[0]
    keys = ("fs_hz", "n_period", "settle_periods", "record_periods")
    for run in runs[1:]:
        for key in keys:
            if run.meta[key] != first.meta[key]:
                raise InputError(f"{run.path}: {key} = {run.meta[key]} differs from "
                                 f"{first.path.name} ({first.meta[key]})")
        if set(run.signals) != set(first.signals):
            raise InputError(f"{run.path}: signals {sorted(run.signals)} differ from "
                             f"{first.path.name} ({sorted(first.signals)})")
    indices = [r.meta["realization"] for r in runs]
    if indices != list(range(len(runs))):
        raise InputError(f"{directory}: realization indices {indices} are not 0 .. {len(runs) - 1} "
                         f"each once")
    n = first.meta["n_period"]
    signals = {name: np.stack([r.signals[name].reshape(-1, n) for r in runs])
               for name in first.signals}
    return ExperimentData(signals=signals, fs_hz=first.meta["fs_hz"], n_period=n,
                          settle_periods=first.meta["settle_periods"],
                          record_periods=first.meta["record_periods"],
                          experiment=first.meta["experiment"], level_index=levels[0],
                          runs=runs)


def _run_of(run_or_path):
    return run_or_path if isinstance(run_or_path, CaptureRun) else read_run(run_or_path)


# Units of the standard signals (docs/capture-format.md); other signals get "".
SIGNAL_UNITS = {"reference": "rad", "plant_input": "V", "motor_angle": "rad",
                "load_angle": "rad", "error": "rad"}
_META_UNITS = {"fs_hz": "Hz", "n_period": "samples", "settle_periods": "periods",
               "record_periods": "periods"}
_MATLAB_NAME_MAX = 63           # MATLAB's namelengthmax
_MATLAB_KEYWORDS = frozenset((
    "break case catch classdef continue else elseif end for function global if otherwise "
    "parfor persistent return spmd switch try while").split())


def matlab_name(text, prefix="x"):
    """A valid MATLAB identifier for ``text``: letters, digits and '_', starting with a
    letter, at most 63 characters, not a keyword (other characters become '_').

    Examples
    --------
    >>> matlab_name("detect-L00-M01"), matlab_name("2nd run"), matlab_name("end")
    ('detect_L00_M01', 'x2nd_run', 'x_end')
    """
    name = re.sub(r"[^A-Za-z0-9_]", "_", str(text))
    if not name or not name[0].isalpha():
        name = prefix + name
    if name in _MATLAB_KEYWORDS:
        name = f"{prefix}_{name}"
    return name[:_MATLAB_NAME_MAX]


def _mat_value(value):
    """A metadata value as MATLAB sees it best: numbers (and bools) as double, text as
    char, dicts as structs (keys made valid names), numeric lists as double arrays."""
    if isinstance(value, dict):
        return _mat_struct(value)
    if isinstance(value, str):
        return value
    if value is None:
        return np.zeros((0, 0))
    arr = np.asarray(value)
    if arr.dtype.kind in "biuf":
        return arr.astype(np.float64)
    return json.dumps(value, sort_keys=True, default=str)   # mixed lists: text


def _mat_struct(mapping):
    out = {}
    for key, value in mapping.items():
        name = matlab_name(key)
        while name in out:                       # two keys that map to one name
            name = (name + "_")[:_MATLAB_NAME_MAX] if len(name) < _MATLAB_NAME_MAX \
                else name[:-1] + "_"
        out[name] = _mat_value(value)
    return out


def mat_content(run, name):
    """The variables ``export_mat`` writes: ``{name: struct}`` (see :func:`export_mat`)."""
    meta = run.meta
    struct = {
        "fs_hz": np.float64(meta["fs_hz"]),
        "n_period": np.float64(meta["n_period"]),
        "settle_periods": np.float64(meta["settle_periods"]),
        "record_periods": np.float64(meta["record_periods"]),
        "level_index": np.float64(meta.get("level_index", 0)),
        "realization": np.float64(meta.get("realization", 0)),
        "experiment": meta["experiment"],
        "signals": {matlab_name(k): np.asarray(v, dtype=np.float64).reshape(-1, 1)
                    for k, v in run.signals.items()},
        "units": {**_META_UNITS, **{matlab_name(k): SIGNAL_UNITS.get(k, "")
                                    for k in run.signals}},
        "parameters": _mat_struct(meta.get("parameters", {}) or {}),
        "metadata_json": json.dumps(meta.get("metadata", {}), sort_keys=True),
        "firmware_version": meta.get("firmware_version", ""),
        "eds_identity": meta.get("eds_identity", ""),
        "started_at": meta.get("started_at", ""),
        "finished_at": meta.get("finished_at", ""),
        "format_version": np.float64(meta.get("format_version", FORMAT_VERSION)),
    }
    return {name: struct}


def export_mat(run_or_path, out_path, *, overwrite=False, name=None):
    """Export a capture run to a MATLAB .mat file (v5, scipy.io.savemat), atomically.

    The file holds ONE struct per capture, named after the output file (``name``, made a
    valid MATLAB identifier: ``detect-L00-M01.mat`` -> ``detect_L00_M01``), so that
    ``load`` of several exports into one workspace keeps them apart. Every number is a
    double (MATLAB divides an integer type by a double in integer arithmetic:
    ``fs_hz / n_period`` must give 2.5, not 3). Fields:

    ``fs_hz``, ``n_period``, ``settle_periods``, ``record_periods``, ``level_index``,
    ``realization``
        Scalars (double).
    ``signals``
        Struct of column vectors (double), one per recorded signal.
    ``units``
        Struct of char: the unit of each signal and of the layout fields.
    ``experiment``, ``firmware_version``, ``eds_identity``, ``started_at``, ``finished_at``
        Text.
    ``parameters``
        Struct of the drive parameters read back (numbers as double).
    ``metadata_json``
        The free-form metadata as JSON text (``jsondecode`` in MATLAB).

    Parameters
    ----------
    run_or_path : CaptureRun or path
    out_path : path
        The .mat file; an existing file is refused unless ``overwrite``.
    name : str, optional
        Name of the struct; default the stem of ``out_path``.

    Returns
    -------
    Path
        ``out_path``.
    """
    import scipy.io

    run = _run_of(run_or_path)
    var = matlab_name(Path(out_path).stem if name is None else name, prefix="capture_")
    content = mat_content(run, var)
    return atomic_write(out_path, lambda tmp: scipy.io.savemat(tmp, content, format="5",
                                                               long_field_names=True),
                        overwrite=overwrite, suffix=".mat")


def export_csv(run_or_path, out_path, *, overwrite=False):
    """Export a capture run to CSV, atomically.

    The first line is a comment ``# fftune capture: {json metadata}``, the second the
    header (signal names), then one row per sample. ``fftune analyze`` reads it back
    (comment lines are skipped).

    Parameters
    ----------
    run_or_path : CaptureRun or path
    out_path : path
        The .csv file; an existing file is refused unless ``overwrite``.

    Returns
    -------
    Path
        ``out_path``.
    """
    run = _run_of(run_or_path)
    names = list(run.signals)
    table = np.column_stack([run.signals[n].astype(np.float64) for n in names])

    def write(tmp):
        buf = _io.StringIO()
        buf.write("# fftune capture: " + json.dumps(run.meta, sort_keys=True) + "\n")
        csv.writer(buf, lineterminator="\n").writerow(names)
        np.savetxt(buf, table, delimiter=",", fmt="%.9g")
        Path(tmp).write_text(buf.getvalue())

    return atomic_write(out_path, write, overwrite=overwrite, suffix=".csv")
