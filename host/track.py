"""``fftune track`` and ``fftune demo-track``: keep K_fc (and K_v, K_a) tuned from the
machine's own repeated task (issue 26, docs/track.md).

The host configures the task on the drive (object 0x2060), and per repetition: starts the
task run, waits for it, uploads the task statistics (0x2061, a few hundred bytes; the design
part 0x2062 once, it depends on the task only), hands them to
:func:`fftune.analysis.track.estimate_task` and :class:`fftune.analysis.track.Tracker`,
writes the gains the tracker decides, and records a row: estimate, sigma, applied gain,
tracking error rms, the bus traffic and, in simulation, the plant's truth. No excitation
other than the task is played. Optionally one short sine experiment at the end checks the
result with the paper's odd-harmonic ratio.

Estimates and decisions live in fftune.analysis.track; this module drives and records.
"""
import copy
import dataclasses
import math
import os
import time

import yaml

from fftune.analysis.errors import FftuneError
from fftune.analysis.track import (K_FC_MEANING, NotIdentifiable, Tracker, TrackSettings, estimate_task,
                                   parse_task_stats, sensor_noise_gain)
from fftune.host.atomic import write_atomic
from fftune.host.config import DEFAULTS as _CFG_DEFAULTS
from fftune.host.config import (_bool, _choice, _err, _merge, _number, output_session, read_yaml,
                                 validate_drive, validate_limits, validate_sim)
from fftune.host.drive import BusOptions, DriveClient, add_bus_arguments
from fftune.host.drive import frame_bits  # (one definition: the bus load below, the SDO bursts)
from fftune.host.odmap import RUN_STATES, STOP_REASONS

TASK_MODES = {"back_and_forth": 1, "forward": 2}

TRACK_DEFAULTS = {
    "output": "out/track",
    "sim": copy.deepcopy(_CFG_DEFAULTS["sim"]),
    "drive": copy.deepcopy(_CFG_DEFAULTS["drive"]),
    # the axis' motion limits (as fftune run's): the task and the odd-ratio check within them
    "limits": copy.deepcopy(_CFG_DEFAULTS["limits"]),
    "track": {
        "tasks": 100,                 # repetitions to run (each one task run on the drive)
        # repetitions played before the recorded one in each run: 1 makes the recorded one
        # start from the task's periodic state whatever the host's pause between runs (a
        # drive in real time); 0 records every repetition (a simulated drive in free-run
        # pauses nothing between runs: its repetitions are back to back)
        "settle_repetitions": 1,
        # repetitions recorded per run: one estimate and update from their sums (more:
        # less noise, fewer pauses between runs, slower tracking)
        "record_repetitions": 1,
        # true: one run of `tasks` repetitions, the drive latches each one's statistics and
        # the host reads them while the task goes on (a drive in real time; no pause between
        # repetitions, settle_repetitions only at the start); false: one run per row
        "continuous": False,
        "task": {"mode": "back_and_forth", "distance_rad": 1.0, "v_max": 4.0, "a_max": 40.0,
                 "jerk": 800.0, "dwell_s": 0.2},
        # gains at the start; None: the drive's present K_fc / K_v
        "initial": {"k_fc": None, "k_v": None, "k_a": 0.0},
        # false: K_v is held at its initial value (docs/track.md: the closed loop biases the
        # K_fc / K_v split of a point-to-point task); true: tracked where the task identifies it
        "track_k_v": False,
        "limits": {f: getattr(TrackSettings, f) for f in TrackSettings.__dataclass_fields__
                   if f != "update_kv"},
        "poll_s": 0.02,               # run state poll interval while waiting [s]
        "write_deadband_rel": 0.002,  # gains are written when they move by more than this
        "progress_pdo_off": True,     # switch the run-progress TPDO (0x1801) off while tracking
        # one sine experiment at the end: the paper's odd-harmonic ratio at the tracked K_fc
        "check": {"enabled": False, "every_tasks": 0, "frequency_hz": 0.625, "amplitude_rad": 0.5,
                  "period_samples": 4096, "periods": 2, "settle_periods": 2, "harmonics": 7},
        "bus_bitrate": 1000000,       # bit/s the bus load is stated against
    },
}


def validate_track_config(raw, path):
    """Defaults overlaid with the user's values and checked; one FftuneError line naming the
    key on a bad value."""
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise _err(path, "", f"expected a mapping at the top level, got {type(raw).__name__}")
    cfg = _merge(TRACK_DEFAULTS, raw, path, "")
    t = "track"
    _number(cfg, path, f"{t}.tasks", low=1, high=100000, integer=True)
    _number(cfg, path, f"{t}.settle_repetitions", low=0, high=100, integer=True)
    _number(cfg, path, f"{t}.record_repetitions", low=1, high=100, integer=True)
    _bool(cfg, path, f"{t}.continuous")
    if cfg[t]["continuous"] and cfg[t]["tasks"] > 1000:
        raise _err(path, f"{t}.tasks", f"continuous: at most 1000 repetitions in one run, got {cfg[t]['tasks']}")
    if cfg[t]["continuous"] and cfg[t]["record_repetitions"] != 1:
        raise _err(path, f"{t}.record_repetitions", "continuous: each repetition is read on its own (1)")
    _choice(cfg, path, f"{t}.task.mode", tuple(TASK_MODES))
    for key, high in (("distance_rad", 1000.0), ("v_max", 1e4), ("a_max", 1e6), ("jerk", 1e9)):
        _number(cfg, path, f"{t}.task.{key}", low=0.0, low_inclusive=False, high=high)
    _number(cfg, path, f"{t}.task.dwell_s", low=0.0, high=100.0)
    _number(cfg, path, f"{t}.initial.k_fc", low=0.0, high=100.0, allow_none=True)
    _number(cfg, path, f"{t}.initial.k_v", low=0.0, high=100.0, allow_none=True)
    _number(cfg, path, f"{t}.initial.k_a", low=0.0, high=100.0)
    _bool(cfg, path, f"{t}.track_k_v")
    lim = cfg[t]["limits"]
    for key in lim:
        if key in ("max_rollbacks", "max_uncertain"):
            _number(cfg, path, f"{t}.limits.{key}", low=1, high=1000, integer=True)
        elif key in ("gain",):
            _number(cfg, path, f"{t}.limits.{key}", low=0.0, low_inclusive=False, high=2.0)
        elif key == "rollback_ratio":
            _number(cfg, path, f"{t}.limits.{key}", low=1.0, low_inclusive=False, high=1000.0)
        else:
            # steps and sigmas relative (<= 10 x), absolute gain steps within the feed-forward
            # objects' range (100 V, 100 V s/rad), rms in rad: a huge value (1e300) is a typo
            _number(cfg, path, f"{t}.limits.{key}", low=0.0,
                    high=10.0 if key.endswith("_rel") else 1000.0 if key.endswith("_rad") else 100.0)
    _number(cfg, path, f"{t}.poll_s", low=0.001, high=10.0)
    _number(cfg, path, f"{t}.write_deadband_rel", low=0.0, high=0.1)
    _bool(cfg, path, f"{t}.check.enabled")
    _number(cfg, path, f"{t}.check.every_tasks", low=0, high=100000, integer=True)
    _bool(cfg, path, f"{t}.progress_pdo_off")
    _number(cfg, path, f"{t}.check.frequency_hz", low=0.0, low_inclusive=False)
    _number(cfg, path, f"{t}.check.amplitude_rad", low=0.0, low_inclusive=False, high=1000.0)
    _number(cfg, path, f"{t}.check.period_samples", low=16, high=8192, integer=True)
    _number(cfg, path, f"{t}.check.periods", low=1, high=1000, integer=True)
    _number(cfg, path, f"{t}.check.settle_periods", low=0, high=1000, integer=True)
    _number(cfg, path, f"{t}.check.harmonics", low=3, high=15, integer=True)
    _number(cfg, path, f"{t}.bus_bitrate", low=10000, high=1000000, integer=True)
    validate_drive(cfg, path)           # (fftune run's rules: one host heartbeat, <= 16383 ms)
    validate_limits(cfg, path)
    validate_sim(cfg, path)
    if not isinstance(cfg["output"], str) or not cfg["output"] or "\0" in cfg["output"]:
        raise _err(path, "output", f"expected a directory name, got {cfg['output']!r}")
    return cfg


def load_track_config(path):
    """Read (:func:`fftune.host.config.read_yaml`, the one loader) and validate a ``fftune
    track`` configuration (YAML)."""
    raw = read_yaml(path, "track configuration")
    cfg = validate_track_config(raw, path)
    cfg["_source"] = os.path.abspath(path)
    return cfg


# ---- bus traffic ------------------------------------------------------------------------

class BusCounter:
    """Counts the frames the host sends (network.send_message) and receives (all frames on
    the bus, through the network's notifier), and their bit times."""

    def __init__(self, network):
        self.frames = 0
        self.bits = 0
        self._net = network
        self._orig_send = network.send_message

        def send(can_id, data, remote=False):
            self.frames += 1
            self.bits += frame_bits(len(data))
            return self._orig_send(can_id, data, remote)
        network.send_message = send
        network.notifier.add_listener(self)

    def __call__(self, msg):
        self.frames += 1
        self.bits += frame_bits(len(msg.data))

    def snapshot(self):
        return self.frames, self.bits


# ---- the tracking session ---------------------------------------------------------------

def _f(x, digits=6):
    return None if x is None or not math.isfinite(x) else float(f"{x:.{digits}g}")


class TaskDrive:
    """The drive side of tracking: task configuration, one task run, its statistics."""

    def __init__(self, client, cfg):
        self.c = client
        self.cfg = cfg
        self.design_raw = None
        self.fs = float(client.get("fs"))
        self.sim = 0x2100 in client.node.object_dictionary

    def configure(self):
        task = self.cfg["track"]["task"]
        self.settle = self.cfg["track"]["settle_repetitions"]
        self.record = self.cfg["track"]["record_repetitions"]
        self.c.set_parameters({
            "exc_kind": 0, "exc_settle_periods": self.settle, "exc_record_periods": self.record,
            "rec_signals": 0,
            "stat_harmonics": 0, "stat_power": 0, "stat_line_mode": 0,
            "task_distance": task["distance_rad"], "task_v_max": task["v_max"],
            "task_a_max": task["a_max"], "task_jerk": task["jerk"], "task_dwell": task["dwell_s"],
            "task_mode": TASK_MODES[task["mode"]]})
        self.period = int(self.c.get("task_period"))
        if self.period == 0:
            raise FftuneError(f"{self.cfg['_source']}: key 'track.task': the drive makes no task of it "
                              f"(a repetition must hold 64 .. 2^24 samples at {self.fs:g} Hz)")
        self.task_s = self.period / self.fs
        self.run_s = (self.settle + self.record) * self.task_s  # one row: a run of the drive
        if self.cfg["track"]["continuous"]:
            self.run_s = self.task_s  # one row: one repetition of the continuous run

    def run_task(self):
        """One run (settle_repetitions + record_repetitions); returns the TaskStats. Looks at the
        run state after poll_s, then waits for the run's expected end, then polls every
        poll_s. A start that the drive accepted has left DONE: state 3 is this run's end."""
        boots0 = self.c._bootups
        self.c._run_active = True
        self.c.set("run_command", 1)  # (the drive is SETTLING / RECORDING once this returns)
        t0 = time.monotonic()
        deadline = t0 + self.c.run_timeout_s
        poll = self.cfg["track"]["poll_s"]
        # a drive in real time takes the run's duration: after one look (a simulated drive
        # in free-run is done at once) wait for it instead of polling the bus all along
        t_expected = t0 + self.run_s
        time.sleep(poll)
        first = True
        while True:
            state = int(self.c.get("run_state"))
            if self.c._bootups != boots0:
                raise FftuneError(f"node {self.c.opts.node_id} rebooted during a task run (boot-up seen)")
            if state == 3:
                break
            if state in (0, 4, 5):
                self.c._run_active = False
                reason = int(self.c.get("run_last_error"))
                raise FftuneError(f"task run stopped by the drive: state {RUN_STATES.get(state, state)}, "
                                  f"reason {reason} ({STOP_REASONS.get(reason, 'unknown')})")
            if time.monotonic() > deadline:
                self.c.set("run_command", 2)
                raise FftuneError(f"task run did not finish within {self.c.run_timeout_s:g} s; aborted it")
            self.c._check_heartbeat()
            time.sleep(max(poll, t_expected - time.monotonic()) if first else poll)
            first = False
        self.c._run_active = False
        if self.design_raw is None:  # the design part depends on the task only
            self.design_raw = self.c._block_upload(0x2062, 0)
        data_raw = self.c._block_upload(0x2061, 0)
        stats = parse_task_stats(self.design_raw, data_raw)
        if stats.repetitions != self.record or stats.samples != self.period:
            raise FftuneError(f"task statistics from node {self.c.opts.node_id}: {stats.repetitions} repetitions "
                              f"of {stats.samples} samples, the run recorded {self.record} of {self.period}")
        return stats

    # ---- continuous: one run of many repetitions, each latched record read while it runs ----
    def start_continuous(self, repetitions):
        """Start one run of settle_repetitions + ``repetitions`` recorded repetitions."""
        self.c.set("exc_record_periods", repetitions)
        self.c._run_active = True
        self.c.set("run_command", 1)
        self.t_run0 = time.monotonic()
        self.seen = 0
        self.skipped = 0

    def next_repetition(self):
        """Wait for the next latched repetition (polls 0x2060:10 from its expected end on);
        returns its TaskStats (one repetition) and its 1-based index in the run."""
        poll = self.cfg["track"]["poll_s"]
        deadline = time.monotonic() + self.c.run_timeout_s
        while True:
            # the next latch one repetition after the last one was seen (the drive's clock,
            # not the host's: a drive in real time may fall behind the wall clock)
            t_expected = (self.t_run0 + (self.settle + 1) * self.task_s if self.seen == 0
                          else self.t_seen + self.task_s - poll)
            now = time.monotonic()
            if now < t_expected:
                time.sleep(max(poll, t_expected - now))
            latched = int(self.c.get("task_latched"))
            if latched > self.seen:
                break
            if time.monotonic() > t_expected + self.task_s:  # late: is the run still going?
                state = int(self.c.get("run_state"))
                if state != 1 and state != 2:
                    self.c._run_active = False
                    reason = int(self.c.get("run_last_error"))
                    raise FftuneError(f"task run stopped by the drive: state {RUN_STATES.get(state, state)}, "
                                      f"reason {reason} ({STOP_REASONS.get(reason, 'unknown')})")
            if time.monotonic() > deadline:
                raise FftuneError(f"no task repetition completed within {self.c.run_timeout_s:g} s")
            self.c._check_heartbeat()
            time.sleep(poll)
        self.t_seen = time.monotonic()
        if self.design_raw is None:  # one repetition's design part: the same every repetition
            self.design_raw = self.c._block_upload(0x2064, 0)
        data_raw = self.c._block_upload(0x2063, 0)  # (a latch under it aborts it: retried)
        # the design part was read with an earlier count in its header
        stats = parse_task_stats(data_raw[:8] + self.design_raw[8:], data_raw)
        index = stats.repetitions  # the header counts the repetitions latched; the record is one
        if index > self.seen + 1:
            self.skipped += index - self.seen - 1
        self.seen = index
        return dataclasses.replace(stats, repetitions=1), index

    def stop_continuous(self):
        if self.c._run_active:
            self.c.set("run_command", 2)  # (the task holds where its reference is)
            self.c._run_active = False

    def truth(self):
        if not self.sim:
            return None, None
        return float(self.c.get("sim_fc_volt")), float(self.c.get("sim_fv_volt"))


def _odd_check(client, cfg, k_fc, k_v, fs):
    """The paper's criterion at the tracked gains: one sine experiment on the reference,
    odd-harmonic ratio rms(|H_3|, |H_5|, ...) / |H_1| of the motor angle."""
    import numpy as np

    from fftune.analysis.hosidf import hosidf
    from fftune.analysis.tuning import harmonic_orders, odd_ratio

    c = cfg["track"]["check"]
    n = c["period_samples"]
    cycles = max(1, round(c["frequency_hz"] * n / fs))
    client.set("task_mode", 0)
    rec = client.run({"exc_kind": 1, "exc_inject": 0, "exc_amplitude": c["amplitude_rad"],
                      "exc_offset": 0.0, "exc_period": n, "exc_sine_cycles": cycles,
                      "exc_settle_periods": c["settle_periods"], "exc_record_periods": c["periods"],
                      "kfc": k_fc, "kv": k_v, "task_ka": 0.0},
                     signals=("reference", "motor_angle"), desc="odd-ratio check")
    r = rec.signals["reference"].reshape(1, c["periods"], n)
    y = rec.signals["motor_angle"].reshape(1, c["periods"], n)
    hos = hosidf(r, y, fs=fs, n_harmonics=c["harmonics"], f0=cycles * fs / n)
    ratio = float(odd_ratio(hos.H, harmonic_orders(c["harmonics"])))
    return {"duration_s": (c["settle_periods"] + c["periods"]) * n / fs,
            "k_fc": _f(k_fc), "k_v": _f(k_v), "frequency_hz": _f(cycles * fs / n),
            "amplitude_rad": _f(c["amplitude_rad"]), "odd_ratio": _f(ratio),
            "h1_abs": _f(float(np.abs(hos.H[0])))}


def track_session(client, cfg, out, log=print, figures=True):
    """Run the tracking session on a connected, enabled drive; write results.yaml and the
    figure into ``out``; return the results dict."""
    tc = cfg["track"]
    drive = TaskDrive(client, cfg)
    drive.configure()
    init = tc["initial"]
    k_fc = init["k_fc"] if init["k_fc"] is not None else float(client.get("kfc"))
    k_v = init["k_v"] if init["k_v"] is not None else float(client.get("kv"))
    k_a = init["k_a"]
    settings = TrackSettings(**tc["limits"], update_kv=tc["track_k_v"])
    tracker = Tracker(k_fc=k_fc, k_v=k_v, k_a=k_a, settings=settings)
    on_drive = {"kfc": k_fc, "kv": k_v, "task_ka": k_a}
    client.set_parameters(on_drive)
    counter = BusCounter(client.network)
    pdo_saved = _progress_pdo_off(client) if tc["progress_pdo_off"] else None
    try:
        return _track_loop(client, cfg, out, log, figures, drive, tracker, on_drive, counter, k_fc, k_v, k_a)
    finally:
        if pdo_saved is not None:
            try:
                client.write(*PROGRESS_TPDO, pdo_saved)
            except FftuneError:
                pass  # the drive went away: nothing to restore


# The drive's run state / progress TPDO (od.yaml's second TPDO: 0x2010:2, 0x2010:3, every 50 ms
# while a run is active); the host polls the run state by SDO and does not use it.
PROGRESS_TPDO = (0x1801, 1)


def _progress_pdo_off(client):
    """Switch the progress TPDO off for the session (COB-ID bit 31); returns the COB-ID to
    restore, or None if there is no such PDO or it is off already."""
    if 0x1801 not in client.node.object_dictionary:
        return None
    cob = int(client.read(*PROGRESS_TPDO))
    if cob & 0x80000000:
        return None
    client.write(*PROGRESS_TPDO, cob | 0x80000000)
    return cob


def _noise_gain(client, fs):
    """The rms of u per rad of sensor noise of the drive's PD (its gains read back), or None
    when the drive does not give them (the noise bias is then not corrected)."""
    try:
        return sensor_noise_gain(float(client.get("kp")), float(client.get("kd")),
                                 float(client.get("tau_d")), float(fs))
    except (FftuneError, KeyError, AttributeError, TypeError, ValueError, ZeroDivisionError):
        return None


def _track_loop(client, cfg, out, log, figures, drive, tracker, on_drive, counter, k_fc, k_v, k_a):
    tc = cfg["track"]
    rows = []
    recent_k_fc = []  # the K_fc estimates so far: their scatter is K_fc sigma's statistical part
    recent = []  # the estimates so far: a viscous change with K_v held, the sensor noise
    noise_gain = _noise_gain(client, drive.fs)
    checks = []
    stop = None
    t_s = 0.0
    wall = 0.0
    how = (f"one run of {drive.settle} + {tc['tasks']} repetitions (settle + recorded, each read while the "
           f"next one runs)" if tc["continuous"] else
           f"{tc['tasks']} runs of {drive.settle} + {drive.record} repetitions (settle + recorded)")
    log(f"fftune track: task of {drive.period} samples ({drive.task_s:.3f} s), {how}, "
        f"start K_fc {k_fc:.5g} V, K_v {k_v:.5g} V s/rad, K_a {k_a:.5g} V s^2/rad")
    cont = tc["continuous"]
    if cont:
        drive.start_continuous(tc["tasks"])
    task = -1
    while task + 1 < tc["tasks"]:
        f0, b0 = counter.snapshot()
        w0 = time.monotonic()
        gains = (on_drive["kfc"], on_drive["kv"], on_drive["task_ka"])
        if cont:
            # the gains written after the last record take effect in the repetition that
            # follows it (a write during its first move mixes them there)
            stats, index = drive.next_repetition()
            task = index - 1
            t_s = (drive.settle + index) * drive.task_s
        else:
            task += 1
            stats = drive.run_task()
            t_s += drive.run_s
        try:
            est = estimate_task(stats, k_v_hold=tracker.k_v, hold_k_v=not tc["track_k_v"],
                                recent_k_fc=recent_k_fc, noise_gain=noise_gain, recent=recent,
                                k_fc_applied=gains[0])
            recent_k_fc.append(est.k_fc)
            recent.append(est)
        except NotIdentifiable as exc:
            est = exc
        decision = tracker.after_task(est)
        if decision.action != "stop":
            # write a gain only when it moved by more than write_deadband_rel of the value on
            # the drive (the task-to-task scatter of the estimate; saves the bus)
            db = tc["write_deadband_rel"]
            changes = {}
            for name, val in (("kfc", decision.k_fc), ("kv", decision.k_v), ("task_ka", decision.k_a)):
                if abs(val - on_drive[name]) > db * abs(on_drive[name]) or decision.action == "rollback":
                    changes[name] = val
            client.set_parameters(changes)
            on_drive.update(changes)
        f1, b1 = counter.snapshot()
        wall += time.monotonic() - w0
        fc_true, fv_true = drive.truth()  # (simulation only; not counted as task traffic)
        ok = not isinstance(est, NotIdentifiable)
        row = {"task": task, "t_s": _f(t_s), "k_fc": _f(gains[0]),
               "k_fc_estimate": _f(est.k_fc) if ok else None,
               "k_fc_sigma": _f(est.k_fc_sigma) if ok else None,
               "k_fc_next": _f(decision.k_fc), "k_v": _f(gains[1]),
               "k_v_estimate": _f(est.k_v) if ok and est.k_v_identified else None,
               "k_a": _f(gains[2]), "k_a_estimate": _f(est.k_a) if ok else None,
               "offset": _f(est.offset) if ok else None,
               "rms_error": _f(est.rms_error) if ok else None,
               "action": decision.action, "bus_frames": f1 - f0, "bus_bits": b1 - b0}
        if ok and est.notes:
            row["notes"] = list(est.notes)
        if ok and math.isfinite(est.sensor_noise_rad):
            row["sensor_noise_rad"] = _f(est.sensor_noise_rad)
            row["k_fc_noise_correction"] = _f(est.k_fc_noise_correction)
        if ok and est.k_v_shift:
            row["k_v_shift"] = _f(est.k_v_shift)
        if ok and est.k_fc_sigma_viscous:
            row["k_fc_sigma_viscous"] = _f(est.k_fc_sigma_viscous)
        if ok and est.k_fc_sigma_model:
            row["k_fc_sigma_model"] = _f(est.k_fc_sigma_model)
        if ok and est.k_fc_sigma_split:
            row["k_fc_sigma_split"] = _f(est.k_fc_sigma_split)
        if decision.cause:
            row["cause"] = decision.cause
        if fc_true is not None:
            row["k_fc_true"] = _f(fc_true)
            row["k_v_true"] = _f(fv_true)
        rows.append(row)
        if decision.action == "rollback":
            log(f"  task {task}: rollback: {decision.reason}")
        if decision.action == "stop":
            if cont:
                drive.stop_continuous()
            stop = {"task": task, "cause": decision.cause, "reason": decision.reason}
            log(f"  task {task}: stop ({decision.cause}): {decision.reason}")
            break
        every = tc["check"]["every_tasks"]
        if tc["check"]["enabled"] and every and not cont and (task + 1) % every == 0 and task != tc["tasks"] - 1:
            # a periodic check where production allows one sine experiment; then the task again
            log(f"  task {task}: odd-ratio check (one sine experiment)")
            check = _odd_check(client, cfg, tracker.k_fc, tracker.k_v, drive.fs)
            t_s += check.pop("duration_s")
            checks.append(dict(check, task=task, t_s=_f(t_s)))
            drive.configure()
            client.set_parameters(on_drive)
        if task % 10 == 0 or task == tc["tasks"] - 1:
            truth = f", truth {fc_true:.5g} V" if fc_true is not None else ""
            log(f"  task {task}: t {t_s:.1f} s, K_fc {gains[0]:.5g} V, estimate {row['k_fc_estimate']} "
                f"+- {row['k_fc_sigma']} V{truth}, rms error {row['rms_error']} rad")
    if cont:
        drive.stop_continuous()
        if drive.skipped:
            log(f"fftune track: {drive.skipped} repetitions completed while the host was busy and were not "
                f"used (a simulated drive in free-run outruns the host: --realtime)")
    bits = [r["bus_bits"] for r in rows[1:]] or [rows[0]["bus_bits"]]
    bus = {"bitrate": tc["bus_bitrate"], "bits_per_task_max": max(bits), "task_s": _f(drive.task_s),
           "first_task_bits": rows[0]["bus_bits"],
           "task_traffic_load": _f(max(bits) / (drive.run_s * tc["bus_bitrate"])),
           "heartbeat_load": _f(2 * frame_bits(1) / (cfg["drive"]["heartbeat_ms"] / 1000.0)
                                / tc["bus_bitrate"]) if cfg["drive"]["heartbeat_ms"] else 0.0,
           # every frame on the bus during the tasks (the drive's PDOs and heartbeat included)
           # over their wall time, plus the host's heartbeat: a measurement only when the drive
           # runs in real time (drive_sim --realtime, a real drive)
           "measured_load": (_f((sum(r["bus_bits"] for r in rows) / wall
                                 + (frame_bits(1) / (cfg["drive"]["heartbeat_ms"] / 1000.0)
                                    if cfg["drive"]["heartbeat_ms"] else 0.0)) / tc["bus_bitrate"])
                             if wall >= 0.8 * len(rows) * drive.run_s and not (cont and drive.skipped)
                             else None),
           "note": "task_traffic_load: the largest task's frames after the first (SDO: start, polls, "
                   "statistics upload, gain writes; worst-case bit stuffing) over its duration at fs; "
                   "the first task also uploads the design part (first_task_bits); "
                   "heartbeat_load: host and drive heartbeats; measured_load: all frames during the "
                   "tasks over their wall time (null unless the drive ran in real time)"}
    check = None
    if tc["check"]["enabled"] and stop is None:
        log("fftune track: odd-ratio check (one sine experiment) at the tracked gains")
        check = _odd_check(client, cfg, tracker.k_fc, tracker.k_v, drive.fs)
        t_s += check.pop("duration_s")
        checks.append(dict(check, task=len(rows) - 1, t_s=_f(t_s)))
        log(f"  odd-harmonic ratio {check['odd_ratio']} at K_fc {check['k_fc']} V")
    summary = {"tasks": len(rows), "task_samples": drive.period, "task_s": _f(drive.task_s),
               "continuous": cont, "repetitions_not_used": drive.skipped if cont else 0,
               "k_fc_final": _f(tracker.k_fc), "k_v_final": _f(tracker.k_v), "k_a_final": _f(tracker.k_a),
               "stop": stop, "bus": bus, "check": check, "checks": checks,
               "excitation": "the task only (exc_kind 0 during tracking)",
               "k_fc_meaning": K_FC_MEANING,
               "sensor_noise_gain_v_per_rad": _f(noise_gain),
               "viscous_changes": [r["task"] for r in rows if "viscous_change_detected" in r.get("notes", ())]}
    if rows and "k_fc_true" in rows[-1]:
        summary["k_fc_true_final"] = rows[-1]["k_fc_true"]
    results = {"track": rows, "track_summary": summary}
    write_atomic(os.path.join(out, "results.yaml"), yaml.safe_dump(results, sort_keys=False))
    if figures:
        plot_track(rows, os.path.join(out, "track_kfc.png"))
    from fftune.host.track_report import write_track_report
    log(f"fftune track: open {os.path.relpath(write_track_report(out, results, cfg, figures))}")
    return results


def plot_track(rows, path):
    """The K_fc path (applied, estimates +- sigma, the truth where known) over the tracking
    error per task (:func:`fftune.host.track_report.track_figure`: legends beside the axes)."""
    from fftune.host.track_report import track_figure

    fig = track_figure(rows)
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)


def summary_lines(results, out):
    rows = results["track"]
    s = results["track_summary"]
    lines = [f"fftune track: {s['tasks']} tasks of {s['task_s']} s; final K_fc {s['k_fc_final']} V"
             + (f" (truth {s['k_fc_true_final']} V)" if "k_fc_true_final" in s else "")]
    if s["stop"]:
        lines.append(f"  stopped at task {s['stop']['task']}: {s['stop']['cause']}: {s['stop']['reason']}")
    lines.append(f"  bus: at most {s['bus']['bits_per_task_max']} bits per task = "
                 f"{100 * s['bus']['task_traffic_load']:.2f} % of {s['bus']['bitrate']} bit/s "
                 f"(+ heartbeats {100 * s['bus']['heartbeat_load']:.2f} %)")
    if s["bus"]["measured_load"] is not None:
        lines.append(f"  bus measured in real time (all frames, PDOs and heartbeats included): "
                     f"{100 * s['bus']['measured_load']:.2f} %")
    rb = sum(1 for r in rows if r["action"] == "rollback")
    if rb:
        lines.append(f"  rollbacks: {rb}")
    if s["check"]:
        lines.append(f"  odd-ratio check: {s['check']['odd_ratio']} at K_fc {s['check']['k_fc']} V")
    lines.append(f"  results: {os.path.relpath(os.path.join(out, 'results.yaml'))}, "
                 f"figure {os.path.relpath(os.path.join(out, 'track_kfc.png'))}")
    return lines


# ---- command line -----------------------------------------------------------------------

def _client(cfg, opts, progress):
    d = cfg["drive"]
    return DriveClient(opts, sdo_timeout_s=d["sdo_timeout_s"], sdo_retries=d["sdo_retries"],
                       heartbeat_ms=d["heartbeat_ms"], host_node_id=d["host_node_id"],
                       run_timeout_s=d["run_timeout_s"], progress=progress)


def preflight_track(cfg, client=None):
    """The envelope of every command that moves an axis (:func:`fftune.host.plan.preflight`,
    step ``track``): the task and the check against ``limits:`` and, with ``client``, the
    drive's limits (fs, u_max, capacities); one FftuneError line naming the key."""
    from fftune.host.plan import preflight, read_drive_limits

    return preflight(cfg, None if client is None else read_drive_limits(client, cfg), steps=("track",))


def _track(args):
    cfg = load_track_config(args.config)
    preflight_track(cfg)                # (before the drive is contacted)
    opts = BusOptions.from_args(args, cfg["drive"])
    client = _client(cfg, opts, not args.no_progress)
    # made now; removed again when the session fails before it wrote its results (an
    # unreachable drive, a refused preflight: nothing left behind)
    with output_session(args.out or cfg["output"]) as out, client:
        preflight_track(cfg, client)    # the drive's own limits, before it is enabled
        client.enable()
        results = track_session(client, cfg, out, figures=not args.no_figures,
                                log=lambda s: print(s, flush=True))
    print("\n".join(summary_lines(results, out)))
    return 0


def _demo_track(args):
    from fftune.host.resources import config_path
    from fftune.host.sim import DEFAULT_PLANT, check_bus

    t0 = time.monotonic()
    # demo-track starts its own drive on a free port: python-can's configuration plays no part
    args.interface = args.interface or "socketcand"
    cfg = load_track_config(args.config)
    preflight_track(cfg)
    bitrate = args.bitrate if args.bitrate is not None else cfg["sim"]["bitrate"]
    check_bus(args.interface, args.channel, bitrate)
    plant = args.plant or cfg["sim"]["plant"] or DEFAULT_PLANT
    if not os.path.isabs(plant) and not os.path.exists(plant):
        packaged = config_path(os.path.basename(plant))
        if os.path.exists(packaged):
            plant = packaged
    with output_session(args.out or cfg["output"]) as out:
        results = _demo_track_session(args, cfg, out, plant, bitrate)
    print("\n".join(summary_lines(results, out)))
    print(f"fftune demo-track: done in {time.monotonic() - t0:.1f} s")
    return 0


def _demo_track_session(args, cfg, out, plant, bitrate):
    """drive_sim with ``plant`` (and the configuration's sim.overrides) and the tracking
    session against it; ``out`` is made (and removed again on a failure before results)."""
    from fftune.host.sim import derived_plant, start_drive_sim

    if cfg["sim"]["overrides"]:
        plant = derived_plant(plant, cfg["sim"]["overrides"], os.path.join(out, "plant.yaml"),
                              where=f"{args.config}: key 'sim.overrides'")
    d = cfg["drive"]
    node_id = args.node_id if args.node_id is not None else d["node_id"]
    sim = start_drive_sim(plant, host=args.host, port=args.port, node_id=node_id,
                          log_path=os.path.join(out, "drive_sim.log"), interface=args.interface,
                          channel=args.channel, bitrate=bitrate, realtime=args.realtime)
    try:
        print(f"fftune demo-track: drive_sim ({os.path.relpath(plant)}) on {sim.describe()}", flush=True)
        opts = sim.bus_options(node_id, d["eds"] or None)
        with _client(cfg, opts, not args.no_progress) as client:
            preflight_track(cfg, client)
            client.enable()
            return track_session(client, cfg, out, figures=not args.no_figures,
                                 log=lambda s: print(s, flush=True))
    finally:
        sim.stop()


def add_parser(sub):
    from fftune.host.resources import config_path

    p = sub.add_parser("track", help="track K_fc (K_v, K_a) from the machine's repeated task",
                       description="Play the configured task on the drive repeatedly, estimate the "
                                   "friction from the drive's task statistics after each repetition "
                                   "and apply bounded updates (docs/track.md).")
    p.add_argument("--config", required=True, help="track configuration YAML (e.g. configs/track_demo.yaml)")
    p.add_argument("--out", default=None, help="output directory (default: the configuration's 'output')")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--no-figures", action="store_true")
    add_bus_arguments(p)
    p.set_defaults(func=_track)

    p = sub.add_parser("demo-track", help="tracking on the simulated drive with friction drift (make demo-track)",
                       description="Start drive_sim with a drifting plant (a +30 % Coulomb step, then a "
                                   "ramp), run `fftune track` against it and stop it.")
    p.add_argument("--config", default=config_path("track_demo.yaml"),
                   help="track configuration (default configs/track_demo.yaml)")
    p.add_argument("--plant", default=None, help="plant of the simulated drive (default: the configuration's sim.plant)")
    p.add_argument("--out", default=None, help="output directory (default: the configuration's 'output')")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--realtime", action="store_true", help="the simulated drive steps at its controller rate")
    add_bus_arguments(p, drive_side=True, port_default=0)
    p.set_defaults(func=_demo_track)
