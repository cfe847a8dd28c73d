"""Benchmark: CAN bus traffic of one tune experiment with on-drive statistics vs raw samples.

drive_sim (twomass plant) over socketcand; a second bus client counts every frame on the
bus (both directions) while DriveClient.run does one experiment of configs/demo.yaml's tune
step (sine 0.625 Hz, N 4096, 2 settle + 2 recorded periods), captured as statistics
(capture: stats) and as raw samples (capture: raw).

Printed: the statistics payload (object 0x2041, the issue's acceptance: <= 200 bytes per
tune experiment) and the frames / CAN data bytes of its upload, the recording payload of
the raw run, and the whole experiment's traffic (parameter writes, the 20 ms status polls,
the read-back of every parameter after the run, the upload). The classic CAN frame time of
that traffic at 1 Mbit/s (about 111 + stuff bits for 8 data bytes; here 47 + 8 x DLC bits
plus the worst-case stuffing, an upper bound) is printed beside.
"""
import os
import sys
import threading
import time

import can

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.join(REPO, "tests"))

from fftune.host.config import load_config  # noqa: E402
from fftune.host.drive import BusOptions, DriveClient  # noqa: E402
from fftune.host.experiments import sine_request  # noqa: E402
from fftune.host.sim import start_drive_sim  # noqa: E402
from host_fixtures import EDS, drive_sim_missing_reason  # noqa: E402

PLANT = os.path.join(REPO, "configs", "plant_twomass.yaml")
DEMO = os.path.join(REPO, "configs", "demo.yaml")


class Counter(can.Listener):
    def __init__(self):
        self.lock = threading.Lock()
        self.frames = self.data = self.bits = 0
        self.on = False

    def on_message_received(self, msg):
        if not self.on:
            return
        with self.lock:
            self.frames += 1
            self.data += msg.dlc
            body = 47 + 8 * msg.dlc
            self.bits += body + (34 + 8 * msg.dlc - 1) // 4   # worst-case stuff bits

    def snapshot(self):
        with self.lock:
            return self.frames, self.data, self.bits


def measure(drive, counter, req, capture):
    stats = {"harmonics": 7, "signals": ["reference", "motor_angle"], "power": ["error"]}
    counter.on = True
    f0, d0, b0 = counter.snapshot()
    rec = drive.run(req, signals=("reference", "motor_angle", "error"), capture=capture,
                    stats=stats if capture != "raw" else None, desc=capture)
    f1, d1, b1 = counter.snapshot()
    payload = int(drive.get("stat_bytes")) if capture == "stats" else int(drive.get("rec_bytes"))
    counter.on = False
    return rec, payload, f1 - f0, d1 - d0, b1 - b0


def upload_only(drive, counter, capture):
    time.sleep(0.2)
    counter.on = True
    f0, d0, _ = counter.snapshot()
    if capture == "stats":
        drive.upload_stats()
    else:
        drive.upload_recording()
    time.sleep(0.2)
    f1, d1, _ = counter.snapshot()
    counter.on = False
    return f1 - f0, d1 - d0


def main():
    reason = drive_sim_missing_reason()
    if reason:
        print(f"bench_stats: skipped: {reason}")
        return 0
    t = load_config(DEMO)["tune"]
    # "auto" probes for the amplitude; one tune experiment here uses the first probe's
    amplitude = t["amplitude_start_rad"] if t["amplitude_rad"] == "auto" else t["amplitude_rad"]
    fs = 2560.0
    cycles = int(round(t["frequency_hz"] * t["period_samples"] / fs))
    req = sine_request(inject="reference", amplitude_peak=amplitude, n=t["period_samples"],
                       cycles=cycles, settle=t["settle_periods"], periods=t["periods"], kfc=0.1, kv=0.0)
    sim = start_drive_sim(PLANT, log_path=os.devnull)
    sniff = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    counter = Counter()
    notifier = can.Notifier(sniff, [counter])
    try:
        with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False) as drive:
            drive.enable()
            for capture in ("stats", "raw"):
                rec, payload, frames, data, bits = measure(drive, counter, req, capture)
                uf, ud = upload_only(drive, counter, capture)
                what = "statistics (0x2041)" if capture == "stats" else "recording (0x2021)"
                print(f"tune experiment, capture {capture}: {what} payload {payload} bytes; its upload "
                      f"{uf} frames, {ud} bytes of CAN data; whole experiment {frames} frames, {data} "
                      f"bytes of CAN data (<= {bits / 1e6 * 1e3:.1f} ms of bus time at 1 Mbit/s)")
                if capture == "stats":
                    print(f"bus bytes per tune experiment with statistics (statistics payload): {payload} "
                          f"(acceptance <= 200: {'met' if payload <= 200 else 'NOT met'})")
    finally:
        notifier.stop()
        sniff.shutdown()
        sim.stop()
    detect_stats_vs_raw()
    return 0


def detect_stats_vs_raw():
    """Detect of configs/demo.yaml with capture 'both' on the C core (ctypes, the same data
    for both paths), for the demo plant and for noise levels around it: the BLA and the
    verdict from the drive's line statistics against the samples' (results.yaml's
    detect.stats_vs_raw)."""
    import tempfile

    sys.path.insert(0, os.path.join(REPO, "firmware_sim", "tests"))
    from fftune.host import experiments as ex
    from fwsim_drive import FwSimDrive, plant_file

    cfg = load_config(DEMO)
    cfg["detect"]["capture"] = "both"
    print("detect (configs/demo.yaml, 3 levels x 4 realizations) from line statistics vs raw "
          "samples of the same runs (capture both, C core):")
    print(f"  {'plant':34s} {'G':>9s} {'var_total':>10s} {'var_noise':>10s} {'causes':>7s} {'sat':>5s}")
    rows = [("demo (viscous 2e-3)", {"plant": {"viscous": 2e-3}}),
            ("demo, noise 2e-3 rad", {"plant": {"viscous": 2e-3}, "sensor": {"noise_std": 2e-3}}),
            ("demo, ideal encoder, no noise", {"plant": {"viscous": 2e-3},
                                               "sensor": {"counts_per_rev": 0, "noise_std": 0.0}}),
            ("asymmetric Coulomb 0.2 (even)", {"plant": {"viscous": 2e-3, "coulomb_asymmetry": 0.2,
                                                         "static": 5.785e-3 * 1.2}}),
            ("no friction", {"plant": {"viscous": 2e-3, "coulomb": 0.0, "static": 0.0}}),
            ("no friction, ideal encoder, no noise", {"plant": {"viscous": 2e-3, "coulomb": 0.0, "static": 0.0},
                                                      "sensor": {"counts_per_rev": 0, "noise_std": 0.0}})]
    for name, over in rows:
        with tempfile.TemporaryDirectory() as d:
            with FwSimDrive(plant_file(over, directory=d)) as drive:
                drive.enable()
                res, _ = ex.detect(ex.Session(drive, cfg, os.path.join(d, "o"), log=lambda s: None))
        c = res["stats_vs_raw"]
        print(f"  {name:34s} {c['max_rel_diff_G']:9.1e} {c['max_rel_diff_var_total']:10.1e} "
              f"{c['max_rel_diff_var_noise']:10.1e} {'equal' if c['same_causes'] else 'DIFFER':>7s} "
              f"{c['max_abs_diff_saturation_fraction']:5.0g}")
    print("  (largest relative differences over levels and lines, re the largest value; goal <= 1e-5;\n"
          "   a variance far below |G|^2 is bounded by the float32 means instead: about 2e-7 |G| / sigma_G)")


if __name__ == "__main__":
    sys.exit(main())
