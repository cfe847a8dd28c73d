"""``fftune fleet``: re-analyse a fleet's captures and CAN logs as a Dask task graph.

Each capture directory (an output directory of ``fftune run|demo`` or of one axis of
``fftune run --machine``: ``captures/*.h5`` / ``*.stats.json``) and each CAN log is one
task: the very experiment code of a live session (:mod:`fftune.host.experiments`, which
maps the pure functions of :mod:`fftune.analysis` over the runs) analyses its runs again,
served from the files instead of a drive. The tasks return rows (one per axis and date:
BLA levels, HOSIDF, K_fc*, the tune objective, or the reason the files could not be
analysed); the rows become one table (Parquet and CSV by default), a drift plot per axis
(K_fc* and the odd ratio over time, with 1-sigma bars) and a summary page (report.html).
Items go to the scheduler in batches, a few per worker; a ``--scheduler`` is probed with a
bounded connect and handshake first; every row passes one type check (a damaged input is
a row with its reason, never a crash of the run).

Scheduling is Dask's (``dask.delayed``): by default its local multiprocessing scheduler
(no server), with ``--scheduler tcp://HOST:PORT`` a ``dask.distributed`` cluster; the
graph and the table are the same. Dask is imported here only: ``fftune.analysis`` knows
nothing of it. A task never raises: a corrupt or partial capture is a row with its reason.
"""
import datetime
import glob
import json
import math
import os
import re
import sys
import tempfile

from fftune.analysis.errors import FftuneError

CANLOG_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".csv", ".db")
RESULTS_MAX_BYTES = 4 << 20          # a results.yaml is some 10 kB; a bigger one is not read
RESULTS_MAX_NODES = 1_000_000
CONNECT_TIMEOUT_S = 10.0             # --scheduler: connect, handshake, first worker
STEPS = ("detect", "quantify", "tune")

# The table's columns and their types (pyarrow names); every row has all of them.
COLUMNS = (
    ("source", "string"), ("kind", "string"), ("machine", "string"), ("axis", "string"),
    ("node_id", "int64"), ("date", "string"), ("status", "string"), ("reason", "string"),
    ("runs", "int64"),
    ("detect_verdict", "string"),
    ("bla_rms_levels", "list<double>"), ("bla_nl_re_output_db", "list<double>"),
    ("bla_noise_re_output_db", "list<double>"), ("bla_odd_re_output_db", "list<double>"),
    ("bla_even_re_output_db", "list<double>"), ("bla_max_change_db", "double"),
    ("hosidf_max_odd_rel", "double"), ("hosidf_max_even_rel", "double"),
    ("k_fc_star", "double"), ("k_fc_sigma", "double"), ("k_fc_converged", "bool"),
    ("tune_stop_reason", "string"), ("ratio_at_zero", "double"), ("ratio_at_zero_std", "double"),
    ("ratio_at_k_fc_star", "double"), ("ratio_at_k_fc_star_std", "double"),
    ("tune_experiments", "int64"), ("k_fc_true", "double"),
)


def _empty_row(source, kind):
    row = {name: None for name, _ in COLUMNS}
    row.update(source=source, kind=kind, status="error", reason="")
    return row


def _num(x):
    if x is None:
        return None
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


# ---------------------------------------------------------------------------------------
# finding the fleet's files
# ---------------------------------------------------------------------------------------
def _capture_files(d):
    return sorted(glob.glob(os.path.join(glob.escape(d), "*.h5")) +
                  glob.glob(os.path.join(glob.escape(d), "*.stats.json")))


def _capture_dir_of(path):
    """The captures folder of ``path`` (an output directory or the folder itself), or None."""
    sub = os.path.join(path, "captures")
    if os.path.isdir(sub) and _capture_files(sub):
        return sub
    if _capture_files(path):
        return path
    return None


def discover(paths):
    """The fleet's items and the paths that are none.

    Returns
    -------
    items : list of (kind, path)
        ``("captures", captures_folder)`` or ``("canlog", file)``, in a stable order.
    bad : list of (path, reason)
    """
    items, bad = [], []
    for p in paths:
        if os.path.isfile(p):
            if p.lower().endswith(CANLOG_SUFFIXES):
                items.append(("canlog", os.path.abspath(p)))
            elif p.endswith((".h5", ".stats.json")):
                items.append(("captures", os.path.abspath(os.path.dirname(p) or ".")))
            else:
                bad.append((p, f"not a capture directory nor a CAN log ({', '.join(CANLOG_SUFFIXES)})"))
            continue
        if not os.path.isdir(p):
            bad.append((p, "no such file or directory"))
            continue
        found = []
        for root, dirs, _files in os.walk(p):
            dirs.sort()
            cap = _capture_dir_of(root)
            if cap is not None and os.path.basename(root) != "captures":
                found.append(("captures", os.path.abspath(cap)))
                dirs[:] = [x for x in dirs if x != "captures"]
            elif cap is not None and root == p:
                found.append(("captures", os.path.abspath(cap)))
        if not found:
            bad.append((p, "no capture files (captures/*.h5, *.stats.json) in it or below"))
        items += found
    seen, unique = set(), []
    for it in items:
        if it not in seen:
            seen.add(it)
            unique.append(it)
    return unique, bad


# ---------------------------------------------------------------------------------------
# one task: a capture directory or a CAN log -> rows
# ---------------------------------------------------------------------------------------
class CaptureReplay:
    """The drive-client interface over a captures folder: every run is resumed from its
    capture; a run that is not there is a partial capture (the session stops with that)."""

    def __init__(self, meta, truth):
        self.meta, self.truth = meta, truth

    def identity(self):
        ident = dict(self.meta.get("metadata", {}).get("identity") or {})
        ident["bus"] = "captures (fftune fleet)"
        return ident

    def plant_truth(self):
        return self.truth

    def get(self, name):
        if name == "fs":
            return float(self.meta["fs_hz"])
        params = self.meta.get("parameters") or {}
        if name in params:
            return params[name]
        raise FftuneError(f"parameter '{name}' is not in the captures")

    def run(self, parameters, desc="run", **_kw):
        raise FftuneError(f"partial capture: run {desc} is missing")


def _first_meta(files):
    """(metadata of the first readable capture, reasons of those that were not)."""
    from fftune.analysis import capture as _capture
    from fftune.host.captures import read_stats_document

    problems = []
    for f in files:
        try:
            if f.endswith(".h5"):
                return _capture.read_run(f).meta, problems
            return read_stats_document(f)["meta"], problems
        except Exception as exc:  # a damaged file: try the next one, say why
            problems.append(f"{os.path.basename(f)}: {exc}")
    return None, problems


def _steps_on_disk(files):
    """Per step, the capture mode its files show ('raw', 'stats', 'both'), or absent."""
    modes = {}
    for step in STEPS:
        h5 = any(os.path.basename(f).startswith(step + "-") and f.endswith(".h5") for f in files)
        st = any(os.path.basename(f).startswith(step + "-") and f.endswith(".stats.json") for f in files)
        if h5 or st:
            modes[step] = "both" if (h5 and st) else ("raw" if h5 else "stats")
    return modes


def _fill_results(row, results):
    det = results.get("detect")
    if det:
        row["detect_verdict"] = det.get("verdict")
        levels = det.get("levels") or []
        row["bla_rms_levels"] = [_num(lv.get("rms_requested")) for lv in levels]
        for col, key in (("bla_nl_re_output_db", "nl_re_output_db"),
                         ("bla_noise_re_output_db", "noise_re_output_db"),
                         ("bla_odd_re_output_db", "odd_re_output_db"),
                         ("bla_even_re_output_db", "even_re_output_db")):
            row[col] = [_num(lv.get("summary_db", {}).get(key)) for lv in levels]
        row["bla_max_change_db"] = _num(det.get("bla_max_change_over_levels_db"))
    q = results.get("quantify")
    if q:
        row["hosidf_max_odd_rel"] = _num(q.get("max_odd_relative_level"))
        row["hosidf_max_even_rel"] = _num(q.get("max_even_relative_level"))
    t = results.get("tune")
    if t:
        s = t["search"]
        row["k_fc_star"] = _num(t.get("k_fc_star"))
        row["k_fc_sigma"] = _num(s.get("sigma_v"))
        row["k_fc_converged"] = bool(s.get("converged"))
        row["tune_stop_reason"] = s.get("stop_reason")
        row["ratio_at_zero"] = _num(t.get("ratio_at_zero"))
        row["ratio_at_k_fc_star"] = _num(t.get("ratio_at_k_fc_star"))
        # the ratios' standard deviations: the search's evaluations at K_fc = 0 and at the
        # verification experiment (the measured point nearest K_fc*)
        evals = [e for e in s.get("evaluations") or [] if e.get("k_fc") is not None]

        def std_at(k):
            if k is None or not evals:
                return None
            e = min(evals, key=lambda e: abs(e["k_fc"] - k))   # (the K_fc sent: float32)
            return _num(e.get("ratio_std")) if abs(e["k_fc"] - k) <= 1e-6 * max(1.0, abs(k)) else None
        row["ratio_at_zero_std"] = std_at(0.0)
        row["ratio_at_k_fc_star_std"] = std_at(s.get("verification_k_fc"))
        row["tune_experiments"] = int(s.get("experiments") or 0)
        row["k_fc_true"] = _num(t.get("true_coulomb_v"))


def _run_steps(session, steps, row):
    """Run the steps on a session; failures of one step are recorded, the others run."""
    from fftune.host import experiments as ex

    results, errors = {}, []
    for step in steps:
        try:
            if step == "detect":
                results["detect"], _ = ex.detect(session)
            elif step == "quantify":
                results["quantify"], _ = ex.quantify(session)
            else:
                results["tune"], _ = ex.tune(session)
        except Exception as exc:  # one step's damage does not hide the other steps
            msg = str(exc) if isinstance(exc, FftuneError) else f"{type(exc).__name__}: {exc}"
            errors.append(f"{step}: {msg}")
    _fill_results(row, results)
    row["runs"] = session.counts["resumed"] + session.counts["measured"]
    if not results:
        row["status"] = "error"
    else:
        row["status"] = "partial" if errors else "ok"
    row["reason"] = "; ".join(errors)
    return row


def _names_for(folder):
    """(machine, axis, node_id, truth, out_dir, display) of a captures folder: machine and
    axis from its results.yaml (an axis of a machine run names both), else the folder names:
    <machine>/<axis>/captures or <machine>/<axis>/<date>/captures (a folder name starting
    YYYY-MM); ``display`` names the axis for a person (the results' axis block, else the
    drive's identity: device name, serial, node). A damaged results.yaml axis block raises
    FftuneError naming the key (the task makes it the row's reason)."""
    machine, axis, out_dir = _folder_names(folder)
    node_id, truth, display = None, None, None
    res_path = os.path.join(out_dir, "results.yaml")
    if os.path.exists(res_path):
        res = _read_results(res_path)
        ax = res.get("axis")
        if ax is not None and not isinstance(ax, dict):
            raise FftuneError(f"{res_path}: key 'axis': expected a mapping, got {type(ax).__name__}")
        ax = ax or {}
        for key in ("name", "machine"):
            v = ax.get(key)
            if v is not None and (not isinstance(v, str) or not v.strip() or len(v) > 200):
                raise FftuneError(f"{res_path}: key 'axis.{key}': expected a name (text of 1 to 200 "
                                  f"characters), got {_short(v)}")
        axis = ax.get("name", axis)
        machine = ax.get("machine", machine)
        node_id = _node_id(ax.get("node_id"), f"{res_path}: key 'axis.node_id'")
        drive = res.get("drive") if isinstance(res.get("drive"), dict) else {}
        truth = drive.get("plant_truth") if isinstance(drive.get("plant_truth"), dict) else None
        ident = drive.get("identity") if isinstance(drive.get("identity"), dict) else {}
        if ax.get("name") is not None:
            display = f"{machine} / {axis}"
        elif ident.get("device_name"):
            serial = ident.get("serial")
            nid = ident.get("node_id")
            display = (f"{str(ident['device_name'])[:80]}"
                       + (f" serial {serial}" if isinstance(serial, int) and serial else "")
                       + (f", node {nid}" if isinstance(nid, int) and not isinstance(nid, bool) else ""))
        if node_id is None and ident.get("node_id") is not None:
            try:
                node_id = _node_id(ident.get("node_id"), f"{res_path}: key 'drive.identity.node_id'")
            except FftuneError:
                pass
    return machine, axis, node_id, truth, out_dir, display or f"{machine} / {axis}"


def _folder_names(folder):
    """(machine, axis, out_dir) of a captures folder from the folder names alone."""
    out_dir = os.path.dirname(folder) if os.path.basename(folder) == "captures" else folder
    parts = os.path.abspath(out_dir).split(os.sep)
    if re.match(r"\d{4}-\d\d", parts[-1]) and len(parts) >= 3:
        parts = parts[:-1]          # <machine>/<axis>/<date>/captures
    return parts[-2], parts[-1], out_dir


def _short(v):
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


def _node_id(v, where):
    """A CANopen node id (1..127) or None; FftuneError naming ``where`` otherwise."""
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 127:
        raise FftuneError(f"{where}: expected a node id 1..127, got {_short(v)}")
    return v


def _read_results(path):
    """results.yaml as a dict through the project's one safe loader (size, depth, aliases);
    FftuneError naming the file when it is not one."""
    from fftune.host.config import read_text, safe_yaml_load

    # the one reader of user files (a FIFO or device refused, not waited on; size; UTF-8)
    text = read_text(path, "results file", max_bytes=RESULTS_MAX_BYTES)
    res = safe_yaml_load(text, path, max_bytes=RESULTS_MAX_BYTES, max_nodes=RESULTS_MAX_NODES)
    if res is None:
        return {}
    if not isinstance(res, dict):
        raise FftuneError(f"{path}: expected a mapping at the top level, got {type(res).__name__}")
    return res


def analyse_captures(folder):
    """Rows (a list of one) for the capture folder ``folder``; never raises."""
    row = _empty_row(folder, "captures")
    try:
        machine, axis, _ = _folder_names(folder)
        row.update(machine=machine, axis=axis)
        machine, axis, node_id, truth, out_dir, display = _names_for(folder)
        row.update(machine=machine, axis=axis, node_id=node_id)
        row["_display"] = display
        files = _capture_files(folder)
        meta, problems = _first_meta(files)
        if meta is None:
            row["reason"] = "no readable capture: " + "; ".join(problems[:3])
            return [row]
        ident = meta.get("metadata", {}).get("identity") or {}
        if row["node_id"] is None and ident.get("node_id") is not None:
            row["node_id"] = _node_id(ident["node_id"], "the captures' metadata.identity.node_id")
        row["date"] = meta.get("started_at") or None
        cfg = dict(meta.get("metadata", {}).get("config") or {})
        if not cfg:
            row["reason"] = "the captures hold no configuration (metadata.config)"
            return [row]
        modes = _steps_on_disk(files)
        for step, mode in modes.items():
            cfg[step] = dict(cfg.get(step) or {}, capture=mode)
        cfg["_source"] = os.path.join(folder, os.path.basename(files[0]))
        from fftune.host import experiments as ex
        session = ex.Session(CaptureReplay(meta, truth), cfg, out_dir, log=lambda s: None)
        _run_steps(session, [s for s in STEPS if s in modes and cfg.get(s, {}).get("enabled", True)], row)
        if problems and row["status"] == "ok":
            row["status"] = "partial"
            row["reason"] = "; ".join(problems[:3])
    except Exception as exc:
        row["status"] = "error"
        row["reason"] = str(exc) if isinstance(exc, FftuneError) else f"{type(exc).__name__}: {exc}"
    return [row]


def _log_node_ids(path):
    """Node ids whose SDO server answers (0x581..0x5FF) appear in the CAN log."""
    import can

    ids = set()
    reader = can.LogReader(path)
    try:
        for msg in reader:
            if not msg.is_extended_id and 0x581 <= msg.arbitration_id <= 0x5FF:
                ids.add(msg.arbitration_id - 0x580)
    finally:
        stop = getattr(reader, "stop", None)
        if stop:
            stop()
    return sorted(ids)


def _logged_steps(sess, cfg):
    """Which steps a logged session ran, from its runs: multisines are detect; sines at the
    period and cycles of quantify's frequencies are quantify, at tune's frequency tune (the
    configuration tells which is which)."""
    from fftune.host.odmap import EXC_KINDS

    fs = None
    sines, multisine = set(), False
    for _, rec in sess.runs:
        kind = int(rec.parameters.get("exc_kind", -1))
        fs = fs or float(rec.parameters.get("fs") or rec.fs_hz or 0) or None
        if kind == EXC_KINDS["multisine"]:
            multisine = True
        elif kind == EXC_KINDS["sine"]:
            sines.add((int(rec.parameters.get("exc_period", 0)), int(rec.parameters.get("exc_sine_cycles", 0))))

    def cycles(f, n):
        return int(round(f * n / fs)) if fs else None
    q, t = cfg["quantify"], cfg["tune"]
    q_lines = {(q["period_samples"], cycles(f, q["period_samples"])) for f in q["frequencies_hz"]}
    t_line = (t["period_samples"], cycles(t["frequency_hz"], t["period_samples"]))
    return {"detect": multisine, "quantify": bool(sines & q_lines), "tune": t_line in sines}


def analyse_canlog(path, config_path=None, eds=None):
    """Rows (one per node answering in the log) for the CAN log ``path``; never raises."""
    from fftune.host.canlog import ReplayDrive, read_transfers, session_from_transfers
    from fftune.host.config import load_config
    from fftune.host.odmap import DEFAULT_EDS
    from fftune.host.resources import config_path as _packaged

    machine = os.path.basename(os.path.dirname(os.path.abspath(path)))
    try:
        nodes = _log_node_ids(path)
    except Exception as exc:
        row = _empty_row(path, "canlog")
        row.update(machine=machine, reason=f"cannot read the CAN log: {type(exc).__name__}: {exc}")
        return [row]
    if not nodes:
        row = _empty_row(path, "canlog")
        row.update(machine=machine, reason="no SDO answers of any node in the log")
        return [row]
    rows = []
    for node in nodes:
        row = _empty_row(path, "canlog")
        row.update(machine=machine, axis=f"node{node}", node_id=node)
        try:
            cfg = load_config(config_path or _packaged("demo.yaml"))
            transfers = read_transfers(path, node)
            sess = session_from_transfers(transfers, eds or cfg["drive"]["eds"] or DEFAULT_EDS, node)
            if not sess.runs:
                row["reason"] = f"no complete run (start + recorder upload) of node {node} in the log"
                rows.append(row)
                continue
            row["date"] = datetime.datetime.fromtimestamp(
                sess.runs[0][1].t_start, datetime.timezone.utc).isoformat(timespec="milliseconds")
            for step in STEPS:
                cfg[step]["capture"] = "raw"
            logged = _logged_steps(sess, cfg)
            steps = [s for s in STEPS if cfg[s]["enabled"] and logged[s]]
            with tempfile.TemporaryDirectory(prefix="fftune-fleet-") as tmp:
                from fftune.host import experiments as ex
                session = ex.Session(ReplayDrive(sess, path), cfg, tmp, log=lambda s: None)
                _run_steps(session, steps, row)
        except Exception as exc:
            row["status"] = "error"
            row["reason"] = str(exc) if isinstance(exc, FftuneError) else f"{type(exc).__name__}: {exc}"
        rows.append(row)
    return rows


def analyse_item(item, config_path=None, eds=None):
    """One task of the graph: rows of a ``(kind, path)`` item of :func:`discover`."""
    kind, path = item
    if kind == "canlog":
        return analyse_canlog(path, config_path, eds)
    return analyse_captures(path)


# ---------------------------------------------------------------------------------------
# the graph, the table, the plots
# ---------------------------------------------------------------------------------------
def _sort_key(row):
    return (str(row.get("machine") or ""), str(row.get("axis") or ""), str(row.get("date") or ""),
            str(row.get("source") or ""), row["node_id"] if isinstance(row.get("node_id"), int) else 0)


_INT64 = (-(1 << 63), (1 << 63) - 1)


def _value_ok(v, t):
    if v is None:
        return True
    if t == "string":
        return isinstance(v, str)
    if t == "bool":
        return isinstance(v, bool)
    if t == "int64":
        return isinstance(v, int) and not isinstance(v, bool) and _INT64[0] <= v <= _INT64[1]
    if t == "double":
        return isinstance(v, (int, float)) and not isinstance(v, bool)
    if t == "list<double>":
        return isinstance(v, list) and all(x is None or (isinstance(x, (int, float)) and not isinstance(x, bool))
                                           for x in v)
    return False


def checked_row(row):
    """``row`` with every column of :data:`COLUMNS` of its type: a value that is not (from a
    damaged input) is dropped (None) and named in the row's reason, the row an error. The one
    place every row passes before the table (never a crash of the whole run)."""
    out = {name: row.get(name) for name, _ in COLUMNS}
    for k in ("_display",):
        if k in row:
            out[k] = row[k]
    bad = []
    for name, t in COLUMNS:
        if not _value_ok(out[name], t):
            bad.append(f"column {name}: {_short(out[name])} is not {t}")
            out[name] = None
    if bad:
        if not isinstance(out.get("source"), str):
            out["source"] = _short(row.get("source"))
        out["status"] = "error"
        out["reason"] = "; ".join(([out["reason"]] if isinstance(out.get("reason"), str) and out["reason"] else [])
                                  + bad)
    return out


def analyse_batch(items, config_path=None, eds=None):
    """One task of the graph: the rows of several items (:func:`analyse_item` each): a
    task per capture directory is too small for a distributed scheduler (its overhead per
    task and per result outweighs the analysis), a batch per worker slot is not."""
    return [r for it in items for r in analyse_item(it, config_path, eds)]


def batches(items, n_slots, per_slot=2):
    """``items`` in about ``n_slots * per_slot`` batches of consecutive items, in order
    (a few per worker: the work spreads, a slow batch does not hold the others)."""
    n = max(1, min(len(items), int(n_slots) * per_slot))
    size = -(-len(items) // n) if items else 1
    return [items[i:i + size] for i in range(0, len(items), size)]


def _check_scheduler_address(scheduler):
    """(host, port) of ``tcp://HOST:PORT``; FftuneError naming it otherwise."""
    m = re.fullmatch(r"tcp://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})", scheduler or "")
    if not m or not 1 <= int(m.group(2)) <= 65535:
        raise FftuneError(f"--scheduler {scheduler}: expected tcp://HOST:PORT (port 1..65535)")
    return m.group(1).strip("[]"), int(m.group(2))


def probe_scheduler(scheduler, timeout_s=CONNECT_TIMEOUT_S):
    """Connect to ``tcp://HOST:PORT`` and read the first frame header of its handshake
    (a Dask scheduler sends its handshake as soon as it accepts), each step within
    ``timeout_s``: FftuneError with the cause for a refused or silent port or a server that
    does not speak Dask's protocol (a frame of implausible size), before the Dask client
    (whose connect can wait without bound on a silent port) is made."""
    import socket
    import struct

    host, port = _check_scheduler_address(scheduler)
    where = f"--scheduler {scheduler}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except socket.timeout:
        raise FftuneError(f"{where}: no connection within {timeout_s:g} s") from None
    except OSError as exc:
        raise FftuneError(f"{where}: cannot connect ({exc.strerror or exc})") from None
    try:
        sock.settimeout(timeout_s)
        head = b""
        try:
            while len(head) < 8:
                chunk = sock.recv(8 - len(head))
                if not chunk:
                    raise FftuneError(f"{where}: the server closed the connection without a Dask "
                                      f"handshake (not a Dask scheduler?)")
                head += chunk
        except socket.timeout:
            raise FftuneError(f"{where}: connected, but no Dask handshake within {timeout_s:g} s "
                              f"(not a Dask scheduler, or a busy one)") from None
        (n,) = struct.unpack("<Q", head)
        if not 0 < n <= 1 << 20:
            raise FftuneError(f"{where}: the server's first bytes {head!r} are no Dask handshake "
                              f"(not a Dask scheduler)")
    except OSError as exc:
        raise FftuneError(f"{where}: connection failed ({exc.strerror or exc})") from None
    finally:
        sock.close()


def _distributed_client(scheduler, timeout_s=CONNECT_TIMEOUT_S):
    """A dask.distributed Client on ``scheduler`` with a worker, or one FftuneError line."""
    try:
        from distributed import Client
    except ImportError:
        raise FftuneError("--scheduler tcp://...: needs dask.distributed (pip install distributed)") from None
    probe_scheduler(scheduler, timeout_s)
    try:
        client = Client(scheduler, timeout=timeout_s, set_as_default=False)
    except Exception as exc:     # connect/handshake failures come as several types
        raise FftuneError(f"--scheduler {scheduler}: cannot connect ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except Exception:
        client.close()
        raise FftuneError(f"--scheduler {scheduler}: the scheduler has no worker (none joined "
                          f"within {timeout_s:g} s)") from None
    return client


def run_graph(items, *, scheduler=None, workers=None, config_path=None, eds=None):
    """Analyse ``items`` as a Dask graph; returns the rows sorted by machine, axis, date.

    ``scheduler``: None = Dask's local multiprocessing scheduler (``workers`` processes,
    default one per core), 'sync' = in this process (debugging), ``tcp://HOST:PORT`` = a
    dask.distributed scheduler (its workers need the same files at the same paths). The
    items go in batches, a few per worker (:func:`batches`). Every row passes
    :func:`checked_row`.
    """
    try:
        import dask
    except ImportError:
        raise FftuneError("fftune fleet needs dask (pip install 'fftune[fleet]'; make setup installs it)") from None

    def graph(n_slots):
        return [dask.delayed(analyse_batch, pure=True)(b, config_path, eds, dask_key_name=f"analyse-{i}")
                for i, b in enumerate(batches(items, n_slots))]
    if scheduler and scheduler.startswith("tcp://"):
        client = _distributed_client(scheduler)
        try:
            n_slots = sum(w.get("nthreads", 1) for w in client.scheduler_info()["workers"].values()) or 1
            results = client.gather(client.compute(graph(n_slots)))
        finally:
            client.close()
    elif scheduler in (None, "processes"):
        n = workers or os.cpu_count() or 1
        results = dask.compute(*graph(n), scheduler="processes", num_workers=n)
    elif scheduler in ("sync", "synchronous", "threads"):
        results = dask.compute(*graph(workers or 1),
                               scheduler=scheduler if scheduler != "sync" else "synchronous")
    else:
        raise FftuneError(f"--scheduler {scheduler}: expected tcp://HOST:PORT, processes, threads or sync")
    rows = [checked_row(r) for rows in results for r in rows]
    return sorted(rows, key=_sort_key)


def arrow_table(rows):
    """The rows as a pyarrow Table with the fixed schema :data:`COLUMNS`."""
    import pyarrow as pa

    types = {"string": pa.string(), "int64": pa.int64(), "double": pa.float64(), "bool": pa.bool_(),
             "list<double>": pa.list_(pa.float64())}
    schema = pa.schema([(name, types[t]) for name, t in COLUMNS])
    return pa.Table.from_pylist([{k: r.get(k) for k, _ in COLUMNS} for r in rows], schema=schema)


def write_table(rows, path, fmt="parquet"):
    """Write the table atomically as Parquet or CSV (list columns as JSON text)."""
    import pyarrow as pa

    table = arrow_table(rows)
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix="-" + os.path.basename(path), dir=d)
    os.close(fd)
    try:
        if fmt == "parquet":
            import pyarrow.parquet as pq
            pq.write_table(table, tmp)
        else:
            import pyarrow.csv as pcsv
            cols = {}
            for name, t in COLUMNS:
                col = table.column(name)
                if t.startswith("list"):
                    col = pa.array([None if v is None else json.dumps(v) for v in col.to_pylist()],
                                   pa.string())
                cols[name] = col
            pcsv.write_csv(pa.table(cols), tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def read_table(path):
    """A written table back as a list of row dicts (Parquet or CSV)."""
    if path.endswith(".parquet"):
        import pyarrow.parquet as pq
        return pq.read_table(path).to_pylist()
    import pyarrow.csv as pcsv
    return pcsv.read_csv(path).to_pylist()


def _safe(name):
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name))


def _date(text):
    try:
        t = datetime.datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    except ValueError:
        return None
    return t if t.tzinfo is None else t.astimezone(datetime.timezone.utc).replace(tzinfo=None)


def _groups(rows):
    """{(machine, axis): rows with a K_fc* and a date, by date}."""
    groups = {}
    for r in rows:
        if r["status"] != "error" and r["k_fc_star"] is not None and r["date"] and _date(r["date"]):
            groups.setdefault((r["machine"] or "", r["axis"] or ""), []).append(r)
    for rs in groups.values():
        rs.sort(key=lambda r: _date(r["date"]))
    return groups


def drift_plots(rows, out_dir):
    """One PNG per axis (machine, axis) with analysed K_fc*: K_fc* with its 1-sigma bar (and
    the simulated truth, drawn where known) and the odd ratio at 0 and at K_fc* over the
    date; the time axis spans the dates (a single analysis: a day around it), the title
    names the axis from its results (:func:`_names_for`). Returns the files written."""
    written = []
    groups = sorted(_groups(rows).items())
    names = [rs[-1].get("_display") or f"{m} / {a}" for (m, a), rs in groups]
    for ((machine, axis), rs), name in zip(groups, names):
        if names.count(name) > 1:     # one drive in several folders: say which plot is which
            rs = [dict(r, _display=f"{name} [{machine}/{axis}]") for r in rs]
        fig = drift_figure(rs, machine, axis)
        path = os.path.join(out_dir, f"drift_{_safe(machine)}_{_safe(axis)}.png")
        fig.savefig(path + ".tmp.png", dpi=90)
        os.replace(path + ".tmp.png", path)
        written.append(path)
    return written


def drift_figure(rs, machine, axis):
    """The drift plot of one axis' rows (with K_fc* and a date, sorted by date): a Figure."""
    import matplotlib.dates as mdates
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure      # no pyplot: no global figure state

    t = [_date(r["date"]) for r in rs]
    fig = Figure(figsize=(8, 5), layout="constrained")
    FigureCanvasAgg(fig)
    a1, a2 = fig.subplots(2, 1, sharex=True)
    a1.errorbar(t, [r["k_fc_star"] for r in rs], yerr=[r["k_fc_sigma"] or 0.0 for r in rs],
                fmt="o-", capsize=4, label="K_fc* (1 sigma)")
    truths = [r["k_fc_true"] for r in rs]
    if any(v is not None for v in truths):
        a1.plot(t, [math.nan if v is None else v for v in truths], "kx--", ms=7,
                label="true Coulomb level (simulation)")
    a1.set_ylabel("K_fc* [V]")
    a1.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=8)
    name = rs[-1].get("_display") or f"{machine} / {axis}"
    a1.set_title(f"{name} ({len(rs)} analys{'is' if len(rs) == 1 else 'es'})\n"
                 f"K_fc* and the odd-harmonic ratio over time", fontsize=10)
    for key, fmt, label in (("ratio_at_zero", "s-", "odd ratio at K_fc = 0"),
                            ("ratio_at_k_fc_star", "o-", "odd ratio at K_fc* (verification run)")):
        vals = [r[key] if r[key] is not None and r[key] > 0 else math.nan for r in rs]
        a2.errorbar(t, vals, yerr=[r[key + "_std"] or 0.0 for r in rs], fmt=fmt, capsize=4,
                    label=label + " (1 sigma)")
    if any(r["ratio_at_zero"] or r["ratio_at_k_fc_star"] for r in rs):
        a2.set_yscale("log")
    a2.set_ylabel("odd-harmonic ratio")
    a2.set_xlabel("date of the first run (UTC)")
    a2.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=8)
    span = max(t) - min(t)
    pad = datetime.timedelta(hours=12) if span < datetime.timedelta(hours=1) else span * 0.08
    a2.set_xlim(min(t) - pad, max(t) + pad)
    loc = mdates.AutoDateLocator(minticks=3, maxticks=8)
    a2.xaxis.set_major_locator(loc)
    a2.xaxis.set_major_formatter(mdates.ConciseDateFormatter(loc))
    for ax in (a1, a2):
        ax.grid(True, alpha=0.3)
    return fig


def _when(text):
    """A row's date as the summary shows it: UTC to the minute."""
    t = _date(text)
    return t.strftime("%Y-%m-%d %H:%M UTC") if t else str(text)


def summary_items(rows):
    """The fleet's summary, one line per axis with an analysed K_fc* (its latest value, what
    to set, and its change over the analyses in sigma) and one for the rows not analysed:
    the first thing the page shows."""
    from fftune.host.report import _object_of, gain_text, sigma_text

    obj = _object_of("kfc")[0]
    out = []
    groups = sorted(_groups(rows).items())
    names = [rs[-1].get("_display") or f"{m} / {a}" for (m, a), rs in groups]
    for ((machine, axis), rs), name in zip(groups, names):
        last, first = rs[-1], rs[0]
        if names.count(name) > 1:       # one drive in several folders: which one (as the plots)
            name = f"{name} [{machine}/{axis}]"
        text = (f"{name}: K_fc* = {gain_text(last['k_fc_star'])} +- {sigma_text(last['k_fc_sigma'])} "
                f"on object {obj} (latest analysis, {_when(last['date'])})")
        if len(rs) > 1:
            d = last["k_fc_star"] - first["k_fc_star"]
            sig = math.hypot(first["k_fc_sigma"] or 0.0, last["k_fc_sigma"] or 0.0)
            text += (f"; {100 * d / first['k_fc_star']:+.1f} % since {_when(first['date'])} over {len(rs)} analyses"
                     + (f" ({abs(d) / sig:.1f} sigma)" if sig > 0 else "")
                     if first["k_fc_star"] else "")
        out.append(text)
    bad = [r for r in rows if r["status"] == "error" or r["k_fc_star"] is None]
    if bad:
        out.append(f"{len(bad)} of {len(rows)} rows without a K_fc* (the table says why)")
    if not out:
        out.append("no rows")
    return out


def write_summary_html(rows, out_dir, tables, plots, items):
    """``<out_dir>/report.html``: the fleet at a glance (counts, one line per axis and date
    with K_fc* +- sigma, the truth where known, the odd ratios, the reason of a row not
    analysed), the drift plots, links to the tables."""
    import html as _html

    from fftune.host.atomic import write_atomic
    from fftune.host.report import _CSS, gain_text, sigma_text

    def pct(v):
        return "-" if v is None else f"{100 * v:.3g} %"
    n = {k: sum(r["status"] == k for r in rows) for k in ("ok", "partial", "error")}
    parts = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>fftune fleet</title>",
             f"<style>{_CSS}</style></head><body><h1>fftune fleet</h1>",
             f"<p class='meta'>{_html.escape(datetime.datetime.now().isoformat(timespec='seconds'))}"
             f" &mdash; {len(items)} items, {len(rows)} rows: {n['ok']} ok, {n['partial']} partial, "
             f"{n['error']} not analysed; tables: "
             + ", ".join(f"<a href='{_html.escape(os.path.basename(t))}'>{_html.escape(os.path.basename(t))}</a>"
                         for t in tables) + "</p>",
             "<h2>Summary</h2><ul class='rec'>"
             + "".join(f"<li>{_html.escape(x)}</li>" for x in summary_items(rows)) + "</ul>",
             "<h2>K_fc* per axis and date</h2><table><tr><th>axis</th><th>node</th><th>date</th>"
             "<th>status</th><th>K_fc* (1 sigma)</th><th>true (simulation)</th>"
             "<th>odd ratio at 0 -> at K_fc*</th><th>reason / source</th></tr>"]
    for r in rows:
        name = r.get("_display") or f"{r['machine'] or '?'} / {r['axis'] or '?'}"
        kfc = (f"{gain_text(r['k_fc_star'])} +- {sigma_text(r['k_fc_sigma'])}"
               if r["k_fc_star"] is not None else ("not converged: " + (r["tune_stop_reason"] or "")
                                                   if r["k_fc_converged"] is False else "-"))
        parts.append("<tr>" + "".join(f"<td>{_html.escape(str(x))}</td>" for x in (
            name, r["node_id"] if r["node_id"] is not None else "-", r["date"] or "-", r["status"],
            kfc, gain_text(r["k_fc_true"]) if r["k_fc_true"] is not None else "-",
            f"{pct(r['ratio_at_zero'])} -> {pct(r['ratio_at_k_fc_star'])}",
            (r["reason"] + " " if r["reason"] else "") + f"({r['source']})")) + "</tr>")
    parts.append("</table>")
    if plots:
        parts.append("<h2>Drift per axis</h2><div class='figs'>")
        for p in plots:
            f = os.path.basename(p)
            parts.append(f"<figure><a href='{_html.escape(f)}'><img src='{_html.escape(f)}' "
                         f"alt='{_html.escape(f)}'></a></figure>")
        parts.append("</div>")
    parts.append("</body></html>")
    path = os.path.join(out_dir, "report.html")
    write_atomic(path, "\n".join(parts))
    return path


# ---------------------------------------------------------------------------------------
# the command
# ---------------------------------------------------------------------------------------
def add_parser(sub):
    p = sub.add_parser("fleet", help="re-analyse many capture directories and CAN logs on Dask",
                       description="Re-analyse capture directories (searched recursively) and CAN "
                                   "logs as a Dask task graph: BLA levels, HOSIDF, K_fc* and the "
                                   "tune objective per axis and date, into one table and a drift "
                                   "plot per axis.")
    p.add_argument("paths", nargs="+", help="capture directories, folders of them, CAN logs")
    p.add_argument("--out", default="out/fleet", help="output directory (default out/fleet)")
    p.add_argument("--format", choices=("both", "parquet", "csv"), default="both",
                   help="table format (default both: fleet.parquet and fleet.csv, list columns "
                        "as JSON text)")
    p.add_argument("--scheduler", default=None,
                   help="tcp://HOST:PORT of a dask.distributed scheduler (default: Dask's local "
                        "multiprocessing scheduler; 'threads' or 'sync' also accepted)")
    p.add_argument("--workers", type=int, default=None, help="local scheduler: processes (default: cores)")
    p.add_argument("--config", default=None, help="configuration for CAN logs (default configs/demo.yaml)")
    p.add_argument("--eds", default=None, help="the drive's EDS for CAN logs")
    p.add_argument("--no-figures", action="store_true", help="no drift plots")
    p.set_defaults(func=_run)


def _run(args):
    from fftune.host.config import check_output_dir

    if args.workers is not None and args.workers < 1:
        raise FftuneError(f"--workers {args.workers}: at least 1")
    if args.scheduler and not args.scheduler.startswith("tcp://") and \
            args.scheduler not in ("processes", "threads", "sync", "synchronous"):
        raise FftuneError(f"--scheduler {args.scheduler}: expected tcp://HOST:PORT, processes, threads or sync")
    if args.scheduler and args.scheduler.startswith("tcp://"):
        _check_scheduler_address(args.scheduler)
    items, bad = discover(args.paths)
    for path, reason in bad:
        print(f"fftune fleet: {path}: {reason} (skipped)", file=sys.stderr)
    if not items:
        raise FftuneError("fleet: nothing to analyse (no capture directory or CAN log among the paths)")
    out = check_output_dir(args.out)
    rows = run_graph(items, scheduler=args.scheduler, workers=args.workers,
                     config_path=args.config, eds=args.eds)
    tables = []
    for fmt in (("parquet", "csv") if args.format == "both" else (args.format,)):
        tables.append(write_table(rows, os.path.join(out, f"fleet.{fmt}"), fmt))
    plots = [] if args.no_figures else drift_plots(rows, out)
    page = write_summary_html(rows, out, tables, plots, items)
    n_ok = sum(r["status"] == "ok" for r in rows)
    print(f"fftune fleet: {len(items)} items, {len(rows)} rows ({n_ok} ok, "
          f"{sum(r['status'] == 'partial' for r in rows)} partial, "
          f"{sum(r['status'] == 'error' for r in rows)} not analysed) -> "
          + ", ".join(os.path.relpath(t) for t in tables)
          + (f", {len(plots)} drift plots" if plots else "") + f"; open {os.path.relpath(page)}")
    for r in rows:
        if r["status"] != "ok":
            print(f"  {r['status']}: {r['source']}: {r['reason']}")
    return 0
