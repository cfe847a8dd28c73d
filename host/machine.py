"""A machine: several axes on one CAN bus, tuned concurrently (``fftune run|demo --machine``).

A machine file (YAML, e.g. ``configs/machine_demo.yaml``) lists the axes::

    machine: demo4                   # name (default: the file's)
    output: out/machine_demo         # default output directory
    config: configs/demo.yaml        # every axis' experiment configuration (default demo.yaml)
    overrides: {drive: {heartbeat_ms: 250}}   # merged into every axis' configuration
    sim: {bitrate: 1000000}          # fftune demo --machine: the one simulated bus
    axes:
      - name: x
        node_id: 1
        config: ...                  # optional: this axis' own configuration file
        overrides: {tune: {search: {k_fc_max: 0.4}}}    # merged into it (limits, ...)
        plant: configs/plant_twomass.yaml               # simulation: this axis' plant
        plant_overrides: {plant: {coulomb: 6.0e-3}}     # ... with these values changed

:func:`run_machine` connects one python-canopen ``Network`` (one bus) with a node per
axis, and runs the single-axis pipeline (:func:`fftune.host.pipeline.run_pipeline`) of
each axis in its own thread: the excitations overlap in time, the SDO requests to the
nodes interleave on the bus. An axis that fails (its node does not answer, is lost,
refuses a run; or its search does not converge) is reported and the others go on.
Ctrl-C / SIGTERM (in the main thread) or a lost bus cancels every axis at its next SDO
request, then each drive is stopped and disabled (``DriveClient.close``).

Output: ``<out>/<axis>/`` as ``fftune run`` writes it (results.yaml with an ``axis:``
block, captures, figures, report.html); ``<out>/results.yaml`` the machine summary (an
``axes:`` list, a ``time_budget_s`` with the machine's ``total``) and ``<out>/report.html``.
"""
import copy
import datetime
import html
import math
import os
import sys
import threading
import time

import yaml

from fftune.analysis.errors import FftuneError
from fftune.host.atomic import write_atomic
from fftune.host.config import show

_AXIS_KEYS = {"name", "node_id", "config", "overrides", "plant", "plant_overrides"}
_TOP_KEYS = {"machine", "output", "config", "overrides", "sim", "axes"}


def _deep_merge(base, over, where):
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v, f"{where}.{k}")
        else:
            out[k] = copy.deepcopy(v)
    return out


def _resolve(path, machine_file):
    """A file named in the machine file: as given (from the working directory), else beside
    the machine file, else the packaged ``configs/NAME``."""
    from fftune.host.resources import config_path

    if os.path.isabs(path) or os.path.exists(path):
        return path
    beside = os.path.join(os.path.dirname(os.path.abspath(machine_file)), path)
    if os.path.exists(beside):
        return beside
    packaged = config_path(os.path.basename(path))
    if os.path.exists(packaged):
        return packaged
    return path


def _mapping(value, where, what, allow_none=True):
    if value is None and allow_none:
        return {}
    if not isinstance(value, dict):
        raise FftuneError(f"{where}: expected {what}, got {show(value)}")
    return value


def load_machine(path):
    """Read and validate a machine file; one FftuneError line naming file and key.

    Every file it names is read by the one loader (:func:`fftune.host.config.read_yaml`:
    size, depth, aliases, UTF-8, ``1e-3`` a number); the machine's and the axes' names become
    folder names and are checked as such; one host heartbeat serves the bus, so every axis
    has the same ``drive.host_node_id`` and ``drive.heartbeat_ms`` (an axis whose value
    differs is refused, naming it: unifying it silently would change the consumer time that
    axis' configuration asked for), and the host id is no axis' node id.

    Returns
    -------
    dict
        ``name``, ``output``, ``bitrate`` (simulation), ``axes``: list of dicts with
        ``name``, ``node_id``, ``cfg`` (validated configuration), ``plant``,
        ``plant_overrides``.
    """
    from fftune.host.config import file_name, read_plant, read_yaml, safe_name, unknown_key_text, validate

    raw = read_yaml(path, "machine file")
    if not isinstance(raw, dict):
        raise FftuneError(f"{path}: expected a mapping with 'axes', got {show(raw)}")
    unknown = sorted(str(k) for k in set(raw) - _TOP_KEYS)
    if unknown:
        raise FftuneError(f"{path}: key '{unknown[0][:60]}': {unknown_key_text(unknown[0], sorted(_TOP_KEYS))}")
    axes_raw = raw.get("axes")
    if not isinstance(axes_raw, list) or not axes_raw:
        raise FftuneError(f"{path}: key 'axes': expected a list of at least one axis")
    if len(axes_raw) > 8:
        raise FftuneError(f"{path}: key 'axes': {len(axes_raw)} axes, at most 8 on one simulated bus")
    sim = _mapping(raw.get("sim"), f"{path}: key 'sim'", "{bitrate: B}")
    if set(sim) - {"bitrate"}:
        raise FftuneError(f"{path}: key 'sim': expected {{bitrate: B}}")
    bitrate = sim.get("bitrate")
    if isinstance(bitrate, float) and bitrate.is_integer():
        bitrate = int(bitrate)          # (1e6: a number as in every configuration)
    if bitrate is not None and (isinstance(bitrate, bool) or not isinstance(bitrate, int)
                                or not 10_000 <= bitrate <= 1_000_000):
        raise FftuneError(f"{path}: key 'sim.bitrate': expected 10000 .. 1000000 bit/s, got {show(bitrate)}")
    name = safe_name(raw["machine"], path, "machine") if raw.get("machine") is not None else \
        safe_name(os.path.splitext(os.path.basename(path))[0], path, "machine (from the file name)")
    output = raw.get("output")
    if output is not None and (not isinstance(output, str) or not output or "\0" in output):
        raise FftuneError(f"{path}: key 'output': expected a directory name, got {show(output)}")
    base_name = file_name(raw["config"], path, "config") if raw.get("config") is not None else "demo.yaml"
    base_file = _resolve(base_name, path)
    try:
        base_raw = read_yaml(base_file, "configuration") or {}
    except FftuneError as exc:
        raise FftuneError(f"{path}: key 'config': {exc}") from None
    base_raw = _mapping(base_raw, f"{path}: key 'config': {base_file}", "a configuration mapping")
    common = _mapping(raw.get("overrides"), f"{path}: key 'overrides'", "a mapping of configuration keys")
    axes, by_id, by_name = [], {}, {}
    bus_hb = None                       # (host id, period, the axis that set them)
    for i, a in enumerate(axes_raw):
        where = f"{path}: axes[{i}]"
        if not isinstance(a, dict):
            raise FftuneError(f"{where}: expected a mapping (name, node_id, ...), got {show(a)}")
        unknown = sorted(str(k) for k in set(a) - _AXIS_KEYS)
        if unknown:
            raise FftuneError(f"{where}: key '{unknown[0][:60]}': {unknown_key_text(unknown[0], sorted(_AXIS_KEYS))}")
        aname = a.get("name")
        if not isinstance(aname, str) or not aname or len(aname) > 64 \
                or not all(c.isascii() and (c.isalnum() or c in "-_") for c in aname):
            raise FftuneError(f"{where}.name: expected a name of letters, digits, - and _, got {show(aname)}")
        nid = a.get("node_id")
        if isinstance(nid, float) and nid.is_integer():
            nid = int(nid)              # (3.0 or 3e0: an integer, as in every configuration)
        if isinstance(nid, bool) or not isinstance(nid, int) or not 1 <= nid <= 127:
            raise FftuneError(f"{where}.node_id: expected 1 .. 127, got {show(nid)}")
        if nid in by_id:
            raise FftuneError(f"{where}.node_id: {nid} is also the node id of axis '{by_id[nid]}' "
                              f"(node ids must be unique on one bus)")
        if aname in by_name:
            raise FftuneError(f"{where}.name: '{aname}' names axes[{by_name[aname]}] too")
        by_id[nid], by_name[aname] = aname, i
        if a.get("config") is not None:
            cfile = _resolve(file_name(a["config"], where, "config"), path)
            try:
                craw = read_yaml(cfile, "configuration") or {}
            except FftuneError as exc:
                raise FftuneError(f"{where}.config: {exc}") from None
            craw = _mapping(craw, f"{where}.config: {cfile}", "a configuration mapping")
        else:
            craw = base_raw
        over = _mapping(a.get("overrides"), f"{where}.overrides", "a mapping of configuration keys")
        merged = _deep_merge(_deep_merge(craw, common, "overrides"), over, f"{where}.overrides")
        drive = merged.setdefault("drive", {})
        if not isinstance(drive, dict):
            raise FftuneError(f"{where} (configuration with overrides): key 'drive': expected a "
                              f"mapping, got {show(drive)}")
        drive["node_id"] = nid
        cfg = validate(merged, f"{where} (configuration with overrides)")
        cfg["_source"] = f"{os.path.abspath(path)}#axes[{i}]"
        d = cfg["drive"]
        if bus_hb is None:
            bus_hb = (d["host_node_id"], d["heartbeat_ms"], f"axes[0] '{aname}'")
        else:
            for key, value, first in (("host_node_id", d["host_node_id"], bus_hb[0]),
                                      ("heartbeat_ms", d["heartbeat_ms"], bus_hb[1])):
                if value != first:
                    raise FftuneError(
                        f"{where} '{aname}': key 'drive.{key}': {value} differs from {first} of "
                        f"{bus_hb[2]}: the host sends one heartbeat on the bus, every axis' consumer "
                        f"watches it (set drive.{key} in the machine's overrides)")
        po = _mapping(a.get("plant_overrides"), f"{where}.plant_overrides", "{section: {key: number}}")
        for section, values in po.items():
            _mapping(values, f"{where}.plant_overrides.{str(section)[:40]}", "{key: number}", allow_none=False)
            for key, value in values.items():
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                    raise FftuneError(f"{where}.plant_overrides.{str(section)[:40]}.{str(key)[:40]}: "
                                      f"expected a finite number, got {show(value)}")
        plant = None
        if a.get("plant") is not None:
            plant = _resolve(file_name(a["plant"], where, "plant"), path)
            if not os.path.lexists(plant):
                raise FftuneError(f"{where}.plant: {a['plant']}: no such plant file")
            try:
                read_plant(plant)           # (the one loader: a FIFO, bomb or wrong shape refused)
            except FftuneError as exc:
                raise FftuneError(f"{where}.plant: {exc}") from None
        axes.append({"name": aname, "node_id": nid, "cfg": cfg, "plant": plant, "plant_overrides": po})
    if bus_hb[0] in by_id:
        raise FftuneError(f"{path}: key 'drive.host_node_id': {bus_hb[0]} is the node id of axis "
                          f"'{by_id[bus_hb[0]]}': the host's heartbeat needs an id of its own")
    return {"name": name, "output": output or f"out/{name}", "bitrate": bitrate,
            "axes": axes, "file": os.path.abspath(path)}


# ---------------------------------------------------------------------------------------
# running the axes
# ---------------------------------------------------------------------------------------
def _axis_entry(ax, results=None, status="failed", error=None, truth=None):
    t = (results or {}).get("tune") or {}
    s = t.get("search") or {}
    entry = {"name": ax["name"], "node_id": ax["node_id"], "status": status,
             "k_fc_star": t.get("k_fc_star"), "sigma": s.get("sigma_v"),
             "k_fc_true": t.get("true_coulomb_v", (truth or {}).get("sim_fc_volt")),
             "k_fc_error_re_truth": t.get("k_fc_star_error_re_truth"),
             "converged": s.get("converged"), "stop_reason": s.get("stop_reason"),
             "verdict": ((results or {}).get("detect") or {}).get("verdict"),
             "experiments": (results or {}).get("experiments"),
             "time_budget_s": ((results or {}).get("time_budget_s") or {}).get("total"),
             "error": error, "results": f"{ax['name']}/results.yaml" if results else None}
    return entry


def _figure_worker_init():
    """The figure process: Ctrl-C is the parent's to handle (it ends this process), a low
    priority (the bus threads of the axes still measuring come first), matplotlib loaded."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        os.nice(10)
    except OSError:
        pass
    import matplotlib
    matplotlib.use("Agg")
    from fftune.analysis import plots  # noqa: F401  (imported once, before the first axis)


def _warm():
    """The figure process' first job: one small figure drawn (fonts and the Agg renderer
    loaded before the first axis' figures)."""
    import io

    from matplotlib.figure import Figure

    fig = Figure(figsize=(2, 1), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([0, 1], [1, 0], "o-", label="warm")
    ax.set_xlabel("x")
    ax.legend()
    fig.savefig(io.BytesIO(), format="png", dpi=50, bbox_inches="tight")
    return os.getpid()


_STEP_DATA = {"detect": "detect_levels", "quantify": "hos", "tune": "tune_data"}


def _draw_step_figures(out_dir, step, obj, results):
    """In the figure process: the figures of one step of an axis (``obj``: the step's analysis
    object; ``results``: the axis' results so far); returns ``({name: (file, caption)},
    seconds)``. Each figure is written atomically (``.tmp-NAME.png`` renamed when complete)."""
    from fftune.host.report import make_figures

    t0 = time.monotonic()
    figs = make_figures(out_dir, results=results, **{_STEP_DATA[step]: obj})
    return figs, time.monotonic() - t0


class _FigurePool:
    """One worker process (``spawn``: a fresh interpreter with its own GIL, none of the
    parent's threads or bus sockets) drawing the axes' figures step by step, in the order
    the steps end: an axis' detect and quantify figures are drawn while its tune step
    measures, the shorter axes' figures while the longest axis measures. Started at once,
    so that its imports overlap the first excitations; at a low priority (nice 10)."""

    def __init__(self, log, log_error):
        import concurrent.futures
        import multiprocessing

        self._log, self._log_error = log, log_error
        self._futures = {}          # axis -> [(node id, step, future)]
        self._lock = threading.Lock()
        self._dirs = []
        self._ended = False
        self._ex = concurrent.futures.ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn"),
            initializer=_figure_worker_init)
        self._ex.submit(_warm)

    def submit(self, name, node_id, out_dir, step, obj, results):
        """Draw ``step``'s figures of axis ``name`` (``results``: copied now, the axis goes on)."""
        import concurrent.futures

        if obj is None:
            return
        snapshot = copy.deepcopy({k: v for k, v in results.items() if k in ("detect", "quantify", "tune")})
        with self._lock:
            if self._ended:         # (Ctrl-C / SIGTERM: no figures any more)
                return
            if out_dir not in self._dirs:
                self._dirs.append(out_dir)
            try:
                fut = self._ex.submit(_draw_step_figures, out_dir, step, obj, snapshot)
            except Exception as exc:    # (a broken figure process: no figures, the axis goes on)
                fut = concurrent.futures.Future()
                fut.set_exception(exc)
            self._futures.setdefault(name, []).append((node_id, step, fut))

        def drawn(f):
            if not f.cancelled() and f.exception() is None:
                figs, sec = f.result()
                self._log(f"[{name}] figures of {step}: {len(figs)} drawn in {sec:.1f} s (figure process)")
        fut.add_done_callback(drawn)

    def wait(self):
        """Wait for every axis' figures; returns ``({axis: {name: (file, caption)}}, {axis:
        error})`` (a failure also one line ``fftune: error: axis 'NAME' (node N): figures
        of STEP: ...``)."""
        import concurrent.futures

        figs, errors = {}, {}
        with self._lock:
            jobs = {k: list(v) for k, v in self._futures.items()}
        for name, items in jobs.items():
            figs[name] = {}
            for nid, step, fut in items:
                while True:
                    try:
                        made, _ = fut.result(timeout=0.2)   # short waits: Ctrl-C / SIGTERM reach us
                        figs[name].update(made)
                        break
                    except concurrent.futures.TimeoutError:
                        continue
                    except Exception as exc:
                        errors[name] = f"figures of {step}: {type(exc).__name__}: {exc}"
                        self._log_error(f"fftune: error: axis '{name}' (node {nid}): {errors[name]}")
                        break
        self._ex.shutdown(wait=True)
        return figs, errors

    def terminate(self):
        """End the figure process now (Ctrl-C, SIGTERM) and remove what it left half-written
        (its figures are written as ``.tmp-NAME.png`` and renamed when complete)."""
        with self._lock:
            first, self._ended = not self._ended, True
        procs = list((getattr(self._ex, "_processes", None) or {}).values())
        if first:
            self._ex.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            try:
                p.terminate()
            except Exception:
                pass
        for p in procs:
            p.join(5.0)
        with self._lock:
            dirs = list(self._dirs)
        for d in dirs:
            try:
                names = os.listdir(d)
            except OSError:
                continue
            for n in names:
                if n.startswith(".tmp-"):
                    try:
                        os.remove(os.path.join(d, n))
                    except OSError:
                        pass


def run_machine(machine, bus_opts, out, *, steps=("detect", "quantify", "tune"), figures=True,
                log=print, progress=False, log_error=None):
    """Run ``steps`` on every axis concurrently over one bus; returns the machine summary.

    Parameters
    ----------
    machine : dict
        :func:`load_machine`.
    bus_opts : fftune.host.drive.BusOptions
        The one bus (node id and EDS per axis come from the machine file / the default EDS).
    out : str
        Output directory (``<out>/<axis name>/`` per axis).
    log, log_error : callable
        Progress lines (prefixed ``[axis]``); an axis' failure, one line ``fftune: error:
        axis 'NAME' (node N): ...`` (default: standard error).
    """
    import canopen

    from fftune.host.drive import (SDO_BLKSIZE_MAX, BusOptions, Cancelled, DriveClient, HostHeartbeat,
                                   _BusErrorListener, _open_bus, _SdoPacer, sdo_burst_frames)
    from fftune.host.odmap import DEFAULT_EDS
    from fftune.host.pipeline import check_plan, run_pipeline

    if log_error is None:
        def log_error(text):
            print(text, file=sys.stderr, flush=True)
    t0 = time.monotonic()
    started = datetime.datetime.now().isoformat(timespec="seconds")
    d0 = machine["axes"][0]["cfg"]["drive"]
    for ax in machine["axes"]:          # (load_machine refuses these; a dict built elsewhere)
        d = ax["cfg"]["drive"]
        if (d["host_node_id"], d["heartbeat_ms"]) != (d0["host_node_id"], d0["heartbeat_ms"]) \
                or d0["host_node_id"] == ax["node_id"]:
            raise FftuneError(f"axis '{ax['name']}': drive.host_node_id / drive.heartbeat_ms "
                              f"({d['host_node_id']}, {d['heartbeat_ms']} ms) differ from the bus' "
                              f"({d0['host_node_id']}, {d0['heartbeat_ms']} ms) or name the axis itself")
    bitrate = bus_opts.bitrate or bus_opts.model_bitrate
    burst = sdo_burst_frames(bitrate, d0["heartbeat_ms"], len(machine["axes"]))
    bus = _open_bus(bus_opts)
    network = canopen.Network(bus)
    network.connect()
    network.notifier.add_listener(_BusErrorListener())
    if burst < SDO_BLKSIZE_MAX:
        _SdoPacer(network, bitrate, burst)
    hb_ms = d0["heartbeat_ms"]
    hb_task = None
    cancel = threading.Event()
    clients, entries, threads, done_res = {}, {}, [], {}
    # the figures of each axis are drawn in a separate process (its own interpreter: no GIL
    # shared with the bus threads) as soon as that axis has measured, so the figures of the
    # shorter axes overlap the longest axis' measuring
    pool = None
    measuring = {"left": 0}
    measured = threading.Lock()

    def done_measuring():
        with measured:
            measuring["left"] -= 1
            if measuring["left"] == 0:
                measuring["wall_s"] = time.monotonic() - t0
    try:
        if figures:
            pool = _FigurePool(log, log_error)
        if hb_ms:
            # one producer for the bus (after listening for another one on its COB-ID)
            hb_task = HostHeartbeat(network, d0["host_node_id"], hb_ms).start()
        # connect every axis (each probes its node: one that does not answer is reported)
        for ax in machine["axes"]:
            d = ax["cfg"]["drive"]
            opts = BusOptions(interface=bus_opts.interface, channel=bus_opts.channel,
                              bitrate=bus_opts.bitrate, host=bus_opts.host, port=bus_opts.port,
                              node_id=ax["node_id"], eds=d["eds"] or bus_opts.eds or DEFAULT_EDS,
                              model_bitrate=bus_opts.model_bitrate)
            try:
                c = DriveClient(opts, sdo_timeout_s=d["sdo_timeout_s"], sdo_retries=d["sdo_retries"],
                                heartbeat_ms=d["heartbeat_ms"], host_node_id=d["host_node_id"],
                                run_timeout_s=d["run_timeout_s"], progress=progress, network=network,
                                host_heartbeat=hb_task, bus_nodes=len(machine["axes"]))
                c.cancel = cancel
                c.connect()
            except FftuneError as exc:
                log_error(f"fftune: error: axis '{ax['name']}' (node {ax['node_id']}): {exc}")
                entries[ax["name"]] = _axis_entry(ax, error=str(exc))
                continue
            clients[ax["name"]] = c

        def work(ax, client):
            name = ax["name"]
            axis_out = os.path.join(out, name)
            waited = []

            def before_figures():
                waited.append(True)
                client.close()              # measured: this drive stopped and disabled now
                done_measuring()
            try:
                # the plan against this drive's limits and the axis' limits:, before enabling
                check_plan(client, ax["cfg"], steps)
                os.makedirs(axis_out, exist_ok=True)
                client.enable()
                res = run_pipeline(client, ax["cfg"], axis_out, steps=steps, figures=False,
                                   log=lambda s: log(f"[{name}] {s}"), preflight=False,
                                   before_figures=before_figures, after_step=None if pool is None else
                                   (lambda step, results, obj: pool.submit(name, ax["node_id"], axis_out,
                                                                           step, obj, results)))
                res["axis"] = {"machine": machine["name"], "name": name, "node_id": ax["node_id"]}
                from fftune.host.report import write_html, write_results
                write_results(axis_out, res)
                write_html(axis_out, res, {})   # (again with its figures once they are drawn)
                done_res[name] = (axis_out, res)
                tune = res.get("tune")
                status = "ok" if (tune is None or tune["search"]["converged"]) else "unconverged"
                entries[name] = _axis_entry(ax, res, status, None if status == "ok" else
                                            f"not converged: {tune['search']['stop_reason']}")
            except Cancelled:
                entries[name] = _axis_entry(ax, status="cancelled", error="cancelled (Ctrl-C / SIGTERM)")
            except Exception as exc:  # an axis' own failure never takes the machine down
                if cancel.is_set():     # (the bus closed under an axis late to see the cancel:
                    # the cancel's doing, no line; it could outlive this session's output)
                    entries[name] = _axis_entry(ax, status="cancelled", error="cancelled (Ctrl-C / SIGTERM)")
                else:
                    text = str(exc) if isinstance(exc, FftuneError) else f"{type(exc).__name__}: {exc}"
                    log_error(f"fftune: error: axis '{name}' (node {ax['node_id']}): {text}")
                    entries[name] = _axis_entry(ax, error=text)
            finally:
                if not waited:
                    done_measuring()        # (failed before its figures: no longer measuring)
                try:
                    client.close()          # stop a run, disable the drive (its own SDO, this thread)
                except BaseException:
                    pass

        measuring["left"] = len(clients)
        for ax in machine["axes"]:
            if ax["name"] in clients:
                th = threading.Thread(target=work, args=(ax, clients[ax["name"]]),
                                      name=f"fftune-axis-{ax['name']}", daemon=True)
                threads.append(th)
                th.start()
        for th in threads:
            while th.is_alive():
                th.join(0.2)        # short joins: Ctrl-C / SIGTERM reach the main thread
        if pool is not None:
            from fftune.host.report import write_html
            figs, errors = pool.wait()          # (short waits, as above)
            for name, err in errors.items():
                if name in entries:
                    entries[name]["figures_error"] = err
            for name, (axis_out, res) in done_res.items():
                if figs.get(name):
                    write_html(axis_out, res, figs[name])
    except BaseException:
        cancel.set()                # every axis stops at its next SDO request ...
        if pool is not None:
            pool.terminate()        # ... the figure process is ended (no half-written file) ...
        for th in threads:
            th.join(10.0)
        for c in clients.values():  # ... and each drive is left stopped and disabled
            try:
                c.close()
            except BaseException:
                pass
        if pool is not None:
            pool.terminate()        # (a figure job an axis submitted meanwhile)
        raise
    finally:
        if hb_task is not None:
            try:
                hb_task.stop()
            except Exception:
                pass
        try:
            network.disconnect()
        except Exception:
            pass
    wall = time.monotonic() - t0
    axes = [entries.get(ax["name"]) or _axis_entry(ax, error="no result") for ax in machine["axes"]]
    return machine_summary(machine, axes, wall, started, measure_wall_s=measuring.get("wall_s"))


def machine_summary(machine, axes, wall_s, started, bus_model=None, measure_wall_s=None):
    """The machine's results dict: ``axes`` and its ``time_budget_s``.

    ``time_budget_s.total``: ``excitation`` = the longest axis' excitation (the machine's
    physical minimum when the axes overlap), ``excitation_sum`` (what sequential sessions
    would need at least), ``bus`` = the time the one bus carried frames when a bus model
    counted them (``bus_model``), else the longest axis' SDO transfer time, ``bus_sdo_wall``
    = the axes' SDO transfer times outside the runs summed (with waiting for the shared bus),
    ``host`` = wall - bus - the longest axis' wait for its runs (at most its excitation),
    at least 0; ``wall``, ``wall_re_longest_excitation``; ``measure_wall`` = from the start
    until the last axis has measured (the time the machine is busy; the figures are drawn
    after it) and ``measure_re_longest_excitation``.
    """
    budgets = {a["name"]: a["time_budget_s"] for a in axes if a.get("time_budget_s")}
    exc = [b["excitation"] for b in budgets.values()]
    longest = max(exc) if exc else 0.0
    sdo = [b["bus"] for b in budgets.values()]
    bus = bus_model["busy_s"] if bus_model else (max(sdo) if sdo else 0.0)
    # the drive's share of the wall time: the longest axis' waiting for its runs (shorter
    # than its excitation when the simulation free-runs)
    drive = max((min(b["excitation"], b["drive_wait"]) for b in budgets.values()), default=0.0)
    total = {"excitation": round(longest, 3), "excitation_sum": round(sum(exc), 3),
             "bus": round(bus, 3), "bus_sdo_wall": round(sum(sdo), 3),
             "host": round(max(0.0, wall_s - bus - drive), 3), "wall": round(wall_s, 3),
             "wall_re_longest_excitation": round(wall_s / longest, 3) if longest else None,
             "measure_wall": None if measure_wall_s is None else round(measure_wall_s, 3),
             "measure_re_longest_excitation": round(measure_wall_s / longest, 3)
             if (longest and measure_wall_s is not None) else None,
             "bus_re_longest_excitation": round(bus / longest, 4) if longest else None}
    return {"machine": machine["name"], "machine_file": machine.get("file"), "started": started,
            "finished": datetime.datetime.now().isoformat(timespec="seconds"),
            "axes": axes, "bus_model": bus_model,
            # (copies: the same dict twice would be a YAML alias)
            "time_budget_s": dict({f"axis_{k}": dict(v) for k, v in budgets.items()}, total=total)}


def write_machine(out, summary):
    """``<out>/results.yaml`` (the summary) and ``<out>/report.html`` (one page)."""
    from fftune.host.report import gain_text, sigma_text
    write_atomic(os.path.join(out, "results.yaml"),
                 yaml.safe_dump(summary, sort_keys=False, default_flow_style=None, width=100))

    def f(x, unit="", pct=False, sig=False):
        if x is None:
            return "&ndash;"
        return f"{100 * x:+.2f} %" if pct else html.escape((sigma_text if sig else gain_text)(x, unit.strip()))
    rows, recs = [], []
    for a in summary["axes"]:
        rec = None
        if a.get("results") and os.path.isfile(os.path.join(out, a["results"])):
            with open(os.path.join(out, a["results"]), encoding="utf-8") as fh:
                rec = (yaml.safe_load(fh) or {}).get("recommendation")
        text = rec["text"] if rec else f"nothing to set ({a['status']}: {a.get('error') or a.get('stop_reason')})"
        recs.append(f"<li><b>{html.escape(a['name'])}</b>: {html.escape(text)}</li>")
        link = (f"<a href='{html.escape(a['name'])}/report.html'>{html.escape(a['name'])}</a>"
                if a.get("results") else html.escape(a["name"]))
        note = a.get("error") or a.get("verdict") or ""
        rows.append(f"<tr><td>{link}</td><td>{a['node_id']}</td><td>{html.escape(a['status'])}</td>"
                    f"<td>{f(a['k_fc_star'], ' V')}</td><td>{f(a['sigma'], ' V', sig=True)}</td>"
                    f"<td>{f(a['k_fc_true'], ' V')}</td><td>{f(a['k_fc_error_re_truth'], pct=True)}</td>"
                    f"<td>{f((a.get('time_budget_s') or {}).get('excitation'), ' s')}</td>"
                    f"<td>{html.escape(str(note))}</td></tr>")
    tot = summary["time_budget_s"]["total"]
    page = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>fftune machine report</title>"
            "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:"
            "collapse}th,td{border:1px solid #bbb;padding:3px 8px;text-align:left}"
            ".rec{border:2px solid #2a7;background:#eefaf2;padding:4px 8px 4px 24px}</style></head><body>"
            f"<h1>fftune machine {html.escape(summary['machine'])}</h1>"
            "<h2>Recommendation</h2><ul class='rec'>" + "".join(recs) + "</ul>"
            f"<p>{html.escape(summary['started'])} .. {html.escape(summary['finished'])}; "
            f"{len(summary['axes'])} axes tuned concurrently on one bus; the loop with and without "
            "the feed-forward: each axis' report (the link).</p>"
            "<h2>Axes</h2><table><tr><th>axis</th><th>node</th><th>status</th><th>K_fc*</th><th>sigma</th>"
            "<th>true (sim)</th><th>error re truth</th><th>excitation</th><th>verdict / error</th></tr>"
            + "".join(rows) + "</table>"
            f"<h2>Time budget</h2><p>wall {tot['wall']:.1f} s; longest axis' excitation "
            f"{tot['excitation']:.1f} s (all axes {tot['excitation_sum']:.1f} s in sequence); "
            f"bus {tot['bus']:.2f} s; wall / longest excitation "
            f"{tot['wall_re_longest_excitation'] if tot['wall_re_longest_excitation'] is not None else 'n/a'}.</p>"
            f"<details><summary>All results (results.yaml)</summary>"
            f"<pre>{html.escape(yaml.safe_dump(summary, sort_keys=False, width=100))}</pre></details></body></html>")
    write_atomic(os.path.join(out, "report.html"), page)


def summary_lines(summary, out):
    lines = [f"fftune machine {summary['machine']}: results in {os.path.relpath(out)}/ "
             f"(results.yaml, report.html, one folder per axis)"]
    for a in summary["axes"]:
        if a["k_fc_star"] is not None:
            est = f"K_fc* = {a['k_fc_star']:.4g} V +- {a['sigma'] or math.nan:.2g} V"
            if a["k_fc_true"]:
                est += f" (truth {a['k_fc_true']:.4g} V, {100 * (a['k_fc_star'] / a['k_fc_true'] - 1):+.2f} %)"
        else:
            est = a.get("error") or "no K_fc*"
        lines.append(f"  {a['name']:<8} node {a['node_id']:<3} {a['status']:<11} {est}")
    t = summary["time_budget_s"]["total"]
    lines.append(f"  time: wall {t['wall']:.1f} s"
                 + (f" (measuring {t['measure_wall']:.1f} s)" if t.get("measure_wall") is not None else "")
                 + f", longest axis' excitation {t['excitation']:.1f} s "
                 f"(sum {t['excitation_sum']:.1f} s), bus {t['bus']:.2f} s"
                 + (f" ({100 * t['bus_re_longest_excitation']:.1f} % of the longest excitation)"
                    if t["bus_re_longest_excitation"] is not None else ""))
    return lines


def exit_code(summary):
    """0: every axis ok; 1: some axis unconverged (reported, not an error); 2: an axis failed."""
    st = [a["status"] for a in summary["axes"]]
    if any(s in ("failed", "cancelled") for s in st):
        return 2
    return 1 if "unconverged" in st else 0


# ---------------------------------------------------------------------------------------
# fftune run --machine, fftune demo --machine
# ---------------------------------------------------------------------------------------
def preflight_axes(machine, steps=("detect", "quantify", "tune")):
    """What every axis' configuration alone tells (:func:`fftune.host.plan.preflight`: its
    limits:, drive.fs_hz, controller.u_max), before any drive is contacted; one line."""
    from fftune.host.plan import preflight

    for ax in machine["axes"]:
        try:
            preflight(ax["cfg"], steps=steps)
        except FftuneError as exc:
            raise FftuneError(f"axis '{ax['name']}': {exc}") from None


def run_cli(args):
    """``fftune run --machine FILE`` (and detect|quantify|tune): against a running bus."""
    from fftune.host.config import output_session
    from fftune.host.drive import BusOptions
    from fftune.host.odmap import DEFAULT_EDS

    if args.node_id is not None:
        raise FftuneError(f"--node-id {args.node_id}: not with --machine (each axis' node id is in "
                          f"{args.machine})")
    if getattr(args, "dry_run", False):
        raise FftuneError("--dry-run: not with --machine (check each axis with its own configuration "
                          "and --node-id)")
    machine = load_machine(args.machine)
    preflight_axes(machine, args.steps)
    opts = BusOptions.from_args(args, {"node_id": machine["axes"][0]["node_id"]})
    opts.eds = args.eds or DEFAULT_EDS
    # made now, removed again if no axis measured (an unreachable bus: nothing left behind)
    with output_session(args.out or machine["output"]) as out:
        summary = run_machine(machine, opts, out, steps=args.steps, figures=not args.no_figures,
                              log=lambda s: print(s, flush=True))
        write_machine(out, summary)
    print("\n".join(summary_lines(summary, out)))
    return exit_code(summary)


def _bus_model_figures(log_path, bitrate):
    """Frames and bits the simulated bus carried (drive_sim's exit line), or None."""
    import re

    try:
        with open(log_path, "r", encoding="utf-8", errors="replace") as fh:
            text = fh.read()
    except OSError:
        return None
    m = re.search(r"CAN bus model: (\d+) frames, (\d+) bits at (\d+) bit/s", text)
    if not m:
        return None
    frames, bits, rate = int(m.group(1)), int(m.group(2)), int(m.group(3))
    return {"frames": frames, "bits": bits, "bitrate": rate, "busy_s": round(bits / rate, 3),
            "source": "drive_sim's bus model (every node's and the host's frames, whole session)"}


def sim_axis_args(machine, plant_dir=None, plant_path=None):
    """drive_sim's ``--axis ID:PLANT`` options for a machine (a dict of :func:`load_machine`
    or its file). Plants with ``plant_overrides`` are written to ``plant_dir``, or handed to
    ``plant_path(text) -> path`` (``fftune sim``: memory files that survive its exec)."""
    from fftune.host.sim import DEFAULT_PLANT, derived_plant_text

    if isinstance(machine, str):
        machine = load_machine(machine)
    extra = []
    for ax in machine["axes"]:
        plant = ax["plant"] or DEFAULT_PLANT
        if ax["plant_overrides"]:
            text = derived_plant_text(plant, ax["plant_overrides"],
                                      where=f"{machine['file']}: axis '{ax['name']}' plant_overrides")
            if plant_path is not None:
                plant = plant_path(text)
            else:
                plant = os.path.join(plant_dir, f"plant_{ax['name']}.yaml")
                write_atomic(plant, text)
        extra += ["--axis", f"{ax['node_id']}:{plant}"]
    return extra


def demo_cli(args):
    """``fftune demo --machine FILE``: one drive_sim serving every axis' node on one bus."""
    from fftune.host.config import output_session
    from fftune.host.drive import BusOptions
    from fftune.host.odmap import DEFAULT_EDS
    from fftune.host.sim import DEFAULT_PLANT, check_bus, start_drive_sim

    t0 = time.monotonic()
    if args.node_id is not None:
        raise FftuneError(f"--node-id {args.node_id}: not with --machine (each axis' node id is in "
                          f"{args.machine})")
    machine = load_machine(args.machine)
    preflight_axes(machine)
    bitrate = args.bitrate if args.bitrate is not None else machine["bitrate"]
    args.interface = args.interface or "socketcand"
    if args.interface != "socketcand":
        raise FftuneError("fftune demo --machine: the simulated machine serves its nodes over "
                          "socketcand (-i socketcand)")
    check_bus(args.interface, args.channel, bitrate)
    for ax in machine["axes"]:
        ax["cfg"]["sim"]["bitrate"] = bitrate   # the steps' default capture follows it
    # a fresh run: an earlier output directory is kept as <out>.previous; a failure before any
    # axis measured leaves the folders as they were (the earlier one put back)
    with output_session(args.out or machine["output"], set_aside=True) as out:
        extra = sim_axis_args(machine, out)
        log_path = os.path.join(out, "drive_sim.log")
        sim = start_drive_sim(machine["axes"][0]["plant"] or DEFAULT_PLANT, host=args.host, port=args.port,
                              node_id=machine["axes"][0]["node_id"], extra=extra, log_path=log_path,
                              bitrate=bitrate, realtime=args.realtime)
        try:
            print(f"fftune demo: drive_sim with {len(machine['axes'])} nodes "
                  f"({', '.join(str(a['node_id']) for a in machine['axes'])}) on {sim.describe()}"
                  + (f", CAN bus model {bitrate} bit/s" if bitrate else ""), flush=True)
            opts = BusOptions(interface="socketcand", channel="can0", host=sim.host, port=sim.port,
                              node_id=machine["axes"][0]["node_id"], eds=DEFAULT_EDS, model_bitrate=bitrate)
            summary = run_machine(machine, opts, out, figures=True, log=lambda s: print(s, flush=True),
                                  progress=False)
        finally:
            sim.stop()
    if bitrate:
        model = _bus_model_figures(log_path, bitrate)
        if model:
            tot = summary["time_budget_s"]["total"]
            summary = machine_summary(machine, summary["axes"], tot["wall"], summary["started"],
                                      bus_model=model, measure_wall_s=tot["measure_wall"])
    write_machine(out, summary)
    print("\n".join(summary_lines(summary, out)))
    print(f"fftune demo --machine: done in {time.monotonic() - t0:.1f} s; open {os.path.relpath(out)}/report.html")
    return exit_code(summary)
