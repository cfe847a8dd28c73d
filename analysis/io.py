"""Load measured signals for the offline analysis: CSV, NPZ, MAT and capture files.

Every loader returns :class:`LoadedSignals`: named 1-D float64 signals (NPZ arrays are
flattened in C order, i.e. row after row; MATLAB matrices column after column, MATLAB's
own x(:); both kept in ``matrices`` so that the CLI can check the layout against N) plus
what the file says about the layout (sample rate, samples per period ...). Errors name the
file, and for CSV the line and column.
"""
import csv
import io as _io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fftune.analysis.errors import InputError

__all__ = ["LoadedSignals", "load_signals", "load_csv", "load_npz", "load_mat",
           "load_capture", "load_capture_directory", "load_lines"]


@dataclass
class LoadedSignals:
    """Signals read from one file.

    Attributes
    ----------
    path : Path
    signals : dict of str -> ndarray (float64, 1-D)
    fs_hz : float or None
        Sample rate if the file states it (capture files; a scalar ``fs`` or ``fs_hz``
        in NPZ/MAT; the metadata comment of an exported CSV).
    layout : dict
        n_period, settle_periods, record_periods, realizations if the file states them.
    matrices : dict of str -> ndarray
        MAT and NPZ files: the signals that were matrices (2-D or more), as read (the CLI
        picks the order that puts whole periods together, or refuses).
    matrix_order : str
        How ``signals`` flattened them: 'F' (MATLAB, column after column) or 'C' (numpy,
        row after row).
    time_column : str or None
        CSV: the time column (``t``, ``time``, ``time_s``, ``t_s``), if there is one.
    time_fs_hz : float or None
        The sample rate its spacing gives (1 / median spacing).
    """

    path: Path
    signals: dict
    fs_hz: float = None
    layout: dict = field(default_factory=dict)
    matrices: dict = field(default_factory=dict)
    matrix_order: str = "C"
    time_column: str = None
    time_fs_hz: float = None


def _finite_or_raise(path, name, arr):
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise InputError(f"{path}: signal {name!r} has NaN or inf at sample {int(bad[0])}")


def _numeric(path, name, value):
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise InputError(f"{path}: variable {name!r} is not real numeric (dtype {arr.dtype})")
    return arr.astype(np.float64).reshape(-1)


# Largest count a capture's layout may name (samples per period, periods, realizations):
# the record holds far fewer samples; a larger number is a damaged or foreign comment.
_LAYOUT_MAX = 2 ** 31 - 1
_LINES_FILE_MAX_BYTES = 16 << 20
_LAYOUT_MIN = {"n_period": 1, "settle_periods": 0, "record_periods": 1, "realizations": 1}


def _shown(value, width=60):
    text = repr(value)
    return text if len(text) <= width else text[:width - 3] + "..."


def _meta_from_comment(path, lineno, text):
    """The ``# fftune capture: {...}`` metadata: a JSON object whose ``fs_hz`` (if any) is a
    finite positive number and whose layout counts are integers in range; anything else is
    one InputError naming the file, the line and the key."""
    where = f"{path} line {lineno}: fftune metadata comment"
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError):
        raise InputError(f"{where}: not JSON") from None
    if not isinstance(meta, dict):
        raise InputError(f"{where}: expected a JSON object {{...}}, got a {type(meta).__name__}")
    fs = meta.get("fs_hz")
    if fs is not None:
        if isinstance(fs, bool) or not isinstance(fs, (int, float)) or not np.isfinite(fs) or fs <= 0:
            raise InputError(f"{where}: fs_hz must be a positive number (Hz), got {_shown(fs)}")
    for key, low in _LAYOUT_MIN.items():
        if key in meta and not _layout_ok(key, meta[key]):
            raise InputError(f"{where}: {key} must be an integer {low} .. {_LAYOUT_MAX}, "
                             f"got {_shown(meta[key])}")
    return meta


def _layout_ok(key, v):
    """A layout count (``_LAYOUT_MIN``): an integer (or integral float) within range."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    if isinstance(v, float) and not (np.isfinite(v) and v.is_integer()):
        return False
    return _LAYOUT_MIN[key] <= v <= _LAYOUT_MAX


def _layout_from_meta(meta):
    layout = {}
    for key in ("n_period", "settle_periods", "record_periods", "realizations"):
        if key in meta:
            layout[key] = int(meta[key])
    return layout


def _is_number(text):
    try:
        float(text)
    except ValueError:
        return False
    return True


def load_csv(path):
    """CSV with a header line of column names; lines starting with '#' are skipped.

    A first comment ``# fftune capture: {...}`` (written by
    :func:`fftune.analysis.capture.export_csv`) provides fs_hz and the layout.
    """
    path = Path(path)
    meta = {}
    try:
        if path.stat().st_size > _MAX_TEXT_BYTES:
            raise InputError(f"{path}: {path.stat().st_size} bytes: a CSV file holds at most "
                             f"{_MAX_TEXT_BYTES}")
        text = path.read_text()
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text (CSV) file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    from fftune.analysis.capture import MAX_CAPTURE_SAMPLES
    n_lines = text.count("\n")
    if n_lines > MAX_CAPTURE_SAMPLES + 1000:      # (rows: samples of a signal; comments)
        raise InputError(f"{path}: {n_lines} lines, at most {MAX_CAPTURE_SAMPLES} samples a signal "
                         f"(fftune.analysis.capture.MAX_CAPTURE_SAMPLES); nothing was parsed")
    lines = text.splitlines()
    header_index = None
    for i, line in enumerate(lines):
        if line.startswith("# fftune capture:"):
            meta = _meta_from_comment(path, i + 1, line.split(":", 1)[1])
        if line.strip() and not line.lstrip().startswith("#"):
            header_index = i
            break
    if header_index is None:
        raise InputError(f"{path}: empty CSV (no header line)")
    header = [h.strip() for h in next(csv.reader([lines[header_index]]))]
    if any(not h for h in header) or len(set(header)) != len(header):
        raise InputError(f"{path} line {header_index + 1}: header needs distinct, non-empty "
                         f"column names, got {header}")
    if all(_is_number(h) for h in header):
        raise InputError(f"{path} line {header_index + 1}: the first line must be a header of "
                         f"column names, got numbers")
    ncol = len(header)
    table = None
    try:                                   # fast path; the slow one below locates errors
        table = np.loadtxt(_io.StringIO("\n".join(lines[header_index + 1:])), delimiter=",",
                           comments="#", ndmin=2, dtype=np.float64)
        if table.shape[1] != ncol or table.shape[0] == 0:
            table = None
    except ValueError:
        table = None
    if table is None:
        table = _parse_rows(path, lines, header_index, header)
    bad = np.argwhere(~np.isfinite(table))
    if bad.size:
        row, col = bad[0]
        # map the data row back to its line number
        data_lines = [k for k in range(header_index + 1, len(lines))
                      if lines[k].strip() and not lines[k].lstrip().startswith("#")]
        raise InputError(f"{path} line {data_lines[row] + 1}, column {header[col]!r}: "
                         f"NaN or inf")
    signals = {name: table[:, j].copy() for j, name in enumerate(header)}
    fs = meta.get("fs_hz")
    time_column, time_fs = _time_column(path, signals)
    return LoadedSignals(path=path, signals=signals, fs_hz=None if fs is None else float(fs),
                         layout=_layout_from_meta(meta), time_column=time_column,
                         time_fs_hz=time_fs)


_TIME_NAMES = ("t", "time", "time_s", "t_s")


def _time_column(path, signals):
    """(name, sample rate) of a CSV time column (1 / its median step, robust to a logger's
    jitter), or (None, None) when there is none or it does not increase."""
    name = next((n for n in signals if n.strip().lower() in _TIME_NAMES), None)
    if name is None or signals[name].size < 2:
        return None, None
    step = float(np.median(np.diff(signals[name])))
    if not step > 0:
        return None, None
    return name, 1.0 / step


def _parse_rows(path, lines, header_index, header):
    ncol = len(header)
    rows = []
    for lineno in range(header_index + 1, len(lines)):
        line = lines[lineno]
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split(",")
        if len(fields) != ncol:
            raise InputError(f"{path} line {lineno + 1}: {len(fields)} fields, the header has "
                             f"{ncol}")
        try:
            rows.append([float(x) for x in fields])
        except ValueError:
            for j, x in enumerate(fields):
                try:
                    float(x)
                except ValueError:
                    raise InputError(f"{path} line {lineno + 1}, column {header[j]!r}: "
                                     f"{x.strip()!r} is not a number") from None
    if not rows:
        raise InputError(f"{path}: no data rows after the header")
    return np.array(rows, dtype=np.float64)


def _from_mapping(path, items, matlab=False):
    signals, fs, layout, matrices = {}, None, {}, {}
    for name, value in items:
        arr = np.asarray(value)
        if arr.dtype.kind in "US":
            continue                              # strings: metadata we do not need
        if arr.size == 1 and arr.dtype.kind in "biuf":
            scalar = float(arr.reshape(-1)[0])
            if name in ("fs", "fs_hz"):
                fs = scalar
            elif name in _LAYOUT_MIN:
                v = arr.reshape(-1)[0].item()
                if not _layout_ok(name, v):
                    raise InputError(f"{path}: variable {name!r} must be an integer "
                                     f"{_LAYOUT_MIN[name]} .. {_LAYOUT_MAX}, got {_shown(v)}")
                layout[name] = int(v)
            continue
        if arr.ndim >= 2 and sum(d > 1 for d in arr.shape) >= 2:
            # a matrix: flattened in the file's own order (MATLAB: column after column,
            # numpy: row after row); the CLI checks the orientation against N
            matrices[name] = arr
            signals[name] = _numeric(path, name, np.asarray(arr).reshape(
                -1, order="F" if matlab else "C"))
        else:
            signals[name] = _numeric(path, name, arr)
        _finite_or_raise(path, name, signals[name])
    if not signals:
        raise InputError(f"{path}: holds no numeric signal")
    if fs is not None and not (np.isfinite(fs) and fs > 0):
        raise InputError(f"{path}: fs = {fs} is not a positive sample rate")
    return LoadedSignals(path=Path(path), signals=signals, fs_hz=fs, layout=layout,
                         matrices=matrices, matrix_order="F" if matlab else "C")


# What a file may declare, checked from its headers before any array is read (a forged
# .npz or .mat of a few kB may declare gigabytes, or inflate to them): a signal holds at most
# this many values (the capture files' limit), a file at most this many arrays, a CSV at
# most this many bytes of text.
_MAX_DECLARED_ARRAYS = 256
_MAX_TEXT_BYTES = 512 << 20


def _check_declared(path, declared):
    """``declared``: (name, shape) pairs read from the file's headers."""
    from fftune.analysis.capture import MAX_CAPTURE_SAMPLES

    if len(declared) > _MAX_DECLARED_ARRAYS:
        raise InputError(f"{path}: {len(declared)} arrays, at most {_MAX_DECLARED_ARRAYS}")
    for name, shape in declared:
        n = int(np.prod([int(d) for d in shape], dtype=object)) if shape else 1
        if n > MAX_CAPTURE_SAMPLES:
            raise InputError(f"{path}: variable {_shown(name)} declares {n} values (shape "
                             f"{_shown(tuple(shape))}), at most {MAX_CAPTURE_SAMPLES} a signal "
                             f"(fftune.analysis.capture.MAX_CAPTURE_SAMPLES); nothing was read")


def _npz_declared(path):
    """(name, shape) of every array of an .npz from its .npy headers, without reading data."""
    import zipfile

    out = []
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
            if len(infos) > _MAX_DECLARED_ARRAYS:
                return [(i.filename, ()) for i in infos]
            for info in infos:
                if not info.filename.endswith(".npy"):
                    continue            # (np.load reads other members as bytes: no signal)
                with z.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    reader = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                              else np.lib.format.read_array_header_2_0)
                    shape, _, _ = reader(fh)
                out.append((info.filename.removesuffix(".npy"), shape))
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, NotImplementedError, RuntimeError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})") from None
    return out


def load_npz(path):
    """NumPy .npz: every array is a signal (flattened); scalars fs/fs_hz, n_period ... are layout."""
    _check_declared(path, _npz_declared(path))
    try:
        with np.load(path, allow_pickle=False) as z:
            items = [(k, z[k]) for k in z.files]
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from None
    return _from_mapping(path, items)


def load_mat(path):
    """MATLAB .mat (scipy.io.loadmat, v5/v7): numeric variables are signals, scalars layout;
    a capture exported by :func:`fftune.analysis.capture.export_mat` (one struct) is read too."""
    import scipy.io

    try:       # the declared shapes first (headers only): a forged file is refused unread
        declared = [(name, shape) for name, shape, _ in scipy.io.whosmat(path)]
    except (OSError, ValueError, NotImplementedError, TypeError) as exc:
        raise InputError(f"{path}: not a readable .mat file ({exc})") from None
    _check_declared(path, declared)
    try:
        content = scipy.io.loadmat(path, simplify_cells=True)
    except (OSError, ValueError, NotImplementedError, TypeError) as exc:
        raise InputError(f"{path}: not a readable .mat file ({exc})") from None
    items = {k: v for k, v in content.items() if not k.startswith("__")}
    captures = [v for v in items.values()
                if isinstance(v, dict) and isinstance(v.get("signals"), dict) and "fs_hz" in v]
    if len(items) == 1 and len(captures) == 1:       # a capture exported by export_mat
        cap = captures[0]
        return _from_mapping(path, [*cap["signals"].items(),
                                    *[(k, cap[k]) for k in ("fs_hz", "n_period", "settle_periods",
                                                            "record_periods") if k in cap]],
                             matlab=True)
    return _from_mapping(path, [(k, v) for k, v in items.items() if not isinstance(v, dict)],
                         matlab=True)


def load_capture(path):
    """An fftune capture file (fftune.analysis.capture)."""
    from fftune.analysis.capture import read_run

    run = read_run(path)
    layout = {k: run.meta[k] for k in ("n_period", "settle_periods", "record_periods")}
    layout["realizations"] = 1
    return LoadedSignals(path=Path(path),
                         signals={k: v.astype(np.float64) for k, v in run.signals.items()},
                         fs_hz=run.meta["fs_hz"], layout=layout)


_LOADERS = {".csv": load_csv, ".txt": load_csv, ".npz": load_npz, ".mat": load_mat,
            ".h5": load_capture, ".hdf5": load_capture}


def load_capture_directory(path, experiment=None, level_index=None):
    """A directory of capture runs of one experiment and level (fftune.analysis.capture); a
    directory that mixes them (the host's captures/) needs ``experiment`` / ``level_index``."""
    from fftune.analysis.capture import load_experiment

    exp = load_experiment(path, experiment=experiment, level_index=level_index)
    m = len(exp.runs)
    return LoadedSignals(path=Path(path),
                         signals={k: v.astype(np.float64).reshape(-1)
                                  for k, v in exp.signals.items()},
                         fs_hz=exp.fs_hz,
                         layout={"n_period": exp.n_period, "settle_periods": exp.settle_periods,
                                 "record_periods": exp.record_periods, "realizations": m})


def load_signals(path, experiment=None, level_index=None):
    """Load a measurement file by its extension (.csv/.txt, .npz, .mat, .h5/.hdf5), or a
    directory of capture runs (realizations in the order of their index).

    Parameters
    ----------
    path : str or Path
    experiment, level_index : optional
        For a directory of capture runs: keep only runs of this experiment kind
        ('detect', 'quantify', 'tune') and level index. Not allowed for single files.

    Returns
    -------
    LoadedSignals
    """
    path = Path(path)
    if path.is_dir():
        return load_capture_directory(path, experiment, level_index)
    if experiment is not None or level_index is not None:
        raise InputError(f"{path}: --experiment/--level select runs in a directory of captures, "
                         "not in a single file")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    loader = _LOADERS.get(path.suffix.lower())
    if loader is None:
        raise InputError(f"{path}: unknown file type {path.suffix!r} (use .csv, .npz, .mat, .h5)")
    return loader(path)


def load_lines(path):
    """Excited lines from a text file: integer DFT bins separated by spaces, commas or
    new lines; '#' starts a comment.

    Returns
    -------
    ndarray of int
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file (excited lines)")
    try:
        if path.stat().st_size > _LINES_FILE_MAX_BYTES:
            raise InputError(f"{path}: {path.stat().st_size} bytes: a list of excited lines holds "
                             f"at most {_LINES_FILE_MAX_BYTES}")
        text = path.read_text()
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (excited lines)") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    bins = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        for token in line.split("#", 1)[0].replace(",", " ").split():
            try:
                value = int(token) if len(token) <= 30 else None
            except ValueError:
                value = None
            if value is None:
                raise InputError(f"{path} line {lineno}: {_shown(token)} is not an integer DFT bin") \
                    from None
            if not 1 <= value <= _LAYOUT_MAX:
                raise InputError(f"{path} line {lineno}: bin {_shown(value)} must be 1 .. "
                                 f"{_LAYOUT_MAX} (and below N/2 of the record)")
            bins.append(value)
    if not bins:
        raise InputError(f"{path}: no excited line listed")
    return np.array(sorted(set(bins)), dtype=np.int64)
